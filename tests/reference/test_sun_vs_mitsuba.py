"""A sun in our renderer against Mitsuba's: a unit sphere (convex: it neither shadows nor lights
itself) under an environment that is a 3-degree disc and nothing else, path-traced by Mitsuba
with one bounce (its envmap emitter's own importance sampling and the BSDF's) for a white
Lambertian surface and for TANGO's microfacet BRDF evaluated exactly per direction
(``stages/reference/tango_bsdf.py``); ours: the sun found in the same map (:func:`find_suns`) and
shaded by the BRDF at 32 directions of its disc, at the very pixels Mitsuba rendered. Judged per
band of ``n . l`` (where the disc's cosine changes across the sphere) and over the lit pixels."""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from conftest import require_tool

from stages.geometry.meshio import TriMesh
from stages.geometry.raycache import RayCache, ViewSet, trace_views
from stages.geometry.tracing import EmbreeTracer
from stages.model.lights.sun import find_suns
from stages.reference import mitsuba as mref
from stages.reference import tango_bsdf
from stages.render.brdf import TANGO
from stages.render.envmap import equirect_directions
from stages.render.light.sun import SunLight

RADIUS = math.radians(3.0)
RADIANCE = 40.0
AXIS = np.array([math.cos(0.5) * math.cos(0.9), math.sin(0.5), math.cos(0.5) * math.sin(0.9)])
SPP = 128


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    try:
        mi_ok = mref.import_mitsuba() is not None
    except ImportError:
        mi_ok = False
    require_tool(mi_ok, "Mitsuba 3 is not installed (pip install -e '.[reference]')")
    import trimesh

    from stages.reference.targets import ENV_TO_WORLD, _mesh, mitsuba_rows

    s = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    mesh = TriMesh(np.asarray(s.vertices, np.float64), np.asarray(s.faces, np.int64))
    views = ViewSet(np.array([0.9 + 0.6]), np.array([0.3]), np.array([3.0]), 45.0, 96, 0.3, 0.2)
    arrays, _ = trace_views(mesh, views, EmbreeTracer(mesh))
    d = tmp_path_factory.mktemp("sunmi")
    np.savez(Path(d) / "c.npz", **arrays)
    hits = RayCache(Path(d) / "c.npz").view(0)
    h = 512
    dirs = equirect_directions(h, 2 * h).numpy().astype(np.float64)
    angle = np.arccos(np.clip(dirs @ AXIS, -1.0, 1.0))
    cover = np.clip((RADIUS - angle) / (math.pi / h) + 0.5, 0.0, 1.0)
    env = (cover[..., None] * np.array([RADIANCE, RADIANCE, RADIANCE])).astype(np.float32)
    mi = mref.import_mitsuba(mref.choose_variant("auto"))
    emitter = {
        "type": "envmap",
        "bitmap": mi.Bitmap(np.ascontiguousarray(mitsuba_rows(env))),
        "to_world": mi.ScalarTransform4f(ENV_TO_WORLD.tolist()),
    }
    integrator = mi.load_dict({"type": "path", "max_depth": 2, "hide_emitters": True})
    cam = mi.load_dict(mref.sensor(views.c2w[0], 45.0, 96, SPP, centred=False, alpha=True, mi=mi))
    plugin = tango_bsdf.register(mi)

    def render(bsdf: dict) -> tuple[np.ndarray, np.ndarray]:
        obj = _mesh(mi, mesh, np.zeros((len(mesh.faces), 3, 2)), mi.load_dict(bsdf))
        scene = mi.load_dict({"type": "scene", "object": obj, "light": emitter})
        img = np.array(mi.render(scene, sensor=cam, integrator=integrator, seed=0, spp=SPP), np.float64).reshape(-1, 4)
        return img[hits.pixel, :3], img[hits.pixel, 3]

    n = hits.normal.astype(np.float64)
    v = -hits.direction.astype(np.float64)
    n = np.where(((n * v).sum(1) < 0)[:, None], -n, n)
    (sun,), _ = find_suns(env, 1)
    light = SunLight(
        torch.from_numpy(sun.direction)[None],
        torch.from_numpy(sun.irradiance)[None],
        torch.tensor([[sun.radius]], dtype=torch.float64),
        32,
    )
    return SimpleNamespace(n=torch.from_numpy(n), v=torch.from_numpy(v), render=render, plugin=plugin, light=light)


def _bands(ours: np.ndarray, theirs: np.ndarray, alpha: np.ndarray, nl: np.ndarray) -> list[float]:
    """``sum(ours) / sum(Mitsuba) - 1`` per band of the disc's cosine over fully covered, lit pixels,
    for the bands that hold at least 1e-3 of the light Mitsuba rendered (a highlight leaves the
    others dark: 1e-24 of it)."""
    out = []
    lit = (alpha > 0.999) & (nl > 0)
    for lo, hi in ((0.05, 0.3), (0.3, 0.6), (0.6, 1.0)):
        m = (alpha > 0.999) & (nl >= lo) & (nl < hi)
        assert m.sum() > 50, (lo, hi, int(m.sum()))
        if theirs[m].sum() >= 1e-3 * theirs[lit].sum():
            out.append(float(ours[m].sum() / theirs[m].sum() - 1.0))
    assert out
    return out


@pytest.mark.slow(minutes=0.5)
def test_a_sun_on_a_lambertian_sphere_matches_mitsuba(scene):
    """A white Lambertian sphere: within 2% of Mitsuba's render in every band of ``n . l``
    (Mitsuba's own noise at 128 samples is well below that over each band)."""
    theirs, alpha = scene.render({"type": "diffuse", "reflectance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}})
    m = SimpleNamespace(albedo=torch.ones_like(scene.n), specular=None, roughness=None)
    ours = scene.light.shade(TANGO, scene.n, scene.v, m, None, None).rgb.numpy()
    nl = scene.n.numpy() @ scene.light.direction[0].numpy()
    bands = _bands(ours, theirs, alpha, nl)
    assert all(abs(b) < 0.02 for b in bands), bands


@pytest.mark.slow(minutes=0.5)
@pytest.mark.parametrize("roughness", [0.3, 0.6])
def test_a_suns_highlight_on_a_sphere_matches_mitsuba(scene, roughness):
    """TANGO's specular term (F0 0.5), exact per direction on both sides: within 4% of Mitsuba's in
    every band that holds a part of the highlight, and over the whole of it."""
    theirs, alpha = scene.render({"type": scene.plugin, "f0": 0.5, "roughness": roughness})
    m = SimpleNamespace(
        albedo=torch.zeros_like(scene.n),
        specular=torch.full_like(scene.n, 0.5),
        roughness=torch.full((len(scene.n), 1), roughness, dtype=torch.float64),
    )
    ours = scene.light.shade(TANGO, scene.n, scene.v, m, None, None).rgb.numpy()
    nl = scene.n.numpy() @ scene.light.direction[0].numpy()
    bands = _bands(ours, theirs, alpha, nl)
    full = (alpha > 0.999) & (nl > 0)
    whole = float(ours[full].sum() / theirs[full].sum() - 1.0)
    assert all(abs(b) < 0.04 for b in bands) and abs(whole) < 0.04, (bands, whole)
