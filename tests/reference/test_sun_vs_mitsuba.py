"""A sun in our renderer against Mitsuba's: a unit sphere (convex: it neither shadows nor lights
itself) under an environment that is a 3-degree disc and nothing else, path-traced by Mitsuba
with one bounce (its envmap emitter's own importance sampling and the BSDF's) for a white
Lambertian surface and for TANGO's microfacet BRDF evaluated exactly per direction
(``stages/reference/tango_bsdf.py``); ours: the sun found in the same map (:func:`find_suns`) and
shaded by the BRDF at 32 directions of its disc, at the very pixels Mitsuba rendered. Judged per
band of ``n . l`` (where the disc's cosine changes across the sphere) and over the lit pixels."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from conftest import require_tool

from stages.geometry.meshio import TriMesh
from stages.geometry.raycache import RayCache, ViewSet, trace_views
from stages.geometry.tracing import EmbreeTracer
from stages.model.lights.sun import find_suns
from stages.model.shadows import ShadowCache
from stages.reference import mitsuba as mref
from stages.reference import tango_bsdf
from stages.render.brdf import TANGO
from stages.render.envmap import equirect_directions
from stages.render.light.sun import SunLight

RADIUS = math.radians(3.0)
RADIANCE = 40.0
AXIS = np.array([math.cos(0.5) * math.cos(0.9), math.sin(0.5), math.cos(0.5) * math.sin(0.9)])
SPP = 128


def _mitsuba():
    try:
        ok = mref.import_mitsuba() is not None
    except ImportError:
        ok = False
    require_tool(ok, "Mitsuba 3 is not installed (pip install -e '.[reference]')")
    return mref.import_mitsuba(mref.choose_variant("auto"))


def _disc_map(axis: np.ndarray, h: int = 512) -> np.ndarray:
    """An equirectangular map ``(h, 2h, 3)`` holding a ``RADIUS`` disc of ``RADIANCE`` about
    ``axis`` (its edge antialiased over one texel) and nothing else."""
    dirs = equirect_directions(h, 2 * h).numpy().astype(np.float64)
    angle = np.arccos(np.clip(dirs @ axis, -1.0, 1.0))
    cover = np.clip((RADIUS - angle) / (math.pi / h) + 0.5, 0.0, 1.0)
    return (cover[..., None] * np.array([RADIANCE, RADIANCE, RADIANCE])).astype(np.float32)


def _renderer(mi, mesh: TriMesh, views: ViewSet, env: np.ndarray, hits, depth: int = 2, spp: int = SPP):
    """Mitsuba's path tracer to ``depth`` (2: direct light alone) under ``env`` at the pixels
    ``hits`` of view 0, ``spp`` samples a pixel: a function of a BSDF dict -> (RGB (P, 3), alpha
    (P,)) float64."""
    from stages.reference.targets import ENV_TO_WORLD, _mesh, mitsuba_rows

    emitter = {
        "type": "envmap",
        "bitmap": mi.Bitmap(np.ascontiguousarray(mitsuba_rows(env))),
        "to_world": mi.ScalarTransform4f(ENV_TO_WORLD.tolist()),
    }
    integrator = mi.load_dict({"type": "path", "max_depth": depth, "hide_emitters": True})
    cam = mi.load_dict(mref.sensor(views.c2w[0], views.fov_deg, views.width, spp, centred=False, alpha=True, mi=mi))

    def render(bsdf: dict) -> tuple[np.ndarray, np.ndarray]:
        obj = _mesh(mi, mesh, np.zeros((len(mesh.faces), 3, 2)), mi.load_dict(bsdf))
        scene = mi.load_dict({"type": "scene", "object": obj, "light": emitter})
        img = np.array(mi.render(scene, sensor=cam, integrator=integrator, seed=0, spp=spp), np.float64).reshape(-1, 4)
        return img[hits.pixel, :3], img[hits.pixel, 3]

    return render


def _hits(mesh: TriMesh, views: ViewSet):
    arrays, _ = trace_views(mesh, views, EmbreeTracer(mesh))
    return RayCache("memory", arrays).view(0)


def _found_sun(env: np.ndarray, samples: int) -> SunLight:
    (sun,), _ = find_suns(env, 1)
    return SunLight(
        torch.from_numpy(sun.direction)[None],
        torch.from_numpy(sun.irradiance)[None],
        torch.tensor([[sun.radius]], dtype=torch.float64),
        samples,
    )


@pytest.fixture(scope="module")
def scene():
    mi = _mitsuba()
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    mesh = TriMesh(np.asarray(s.vertices, np.float64), np.asarray(s.faces, np.int64))
    views = ViewSet(np.array([0.9 + 0.6]), np.array([0.3]), np.array([3.0]), 45.0, 96, 0.3, 0.2)
    hits = _hits(mesh, views)
    env = _disc_map(AXIS)
    render = _renderer(mi, mesh, views, env, hits)
    plugin = tango_bsdf.register(mi)
    n = hits.normal.astype(np.float64)
    v = -hits.direction.astype(np.float64)
    n = np.where(((n * v).sum(1) < 0)[:, None], -n, n)
    light = _found_sun(env, 32)
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


def _box_on_a_floor() -> tuple[TriMesh, int]:
    """A closed box ``[1, 2] x [0, 0.6] x [-0.5, 0.5]`` on a floor quad ``[-8, 8]^2`` at ``y = 0``
    (normals up): the mesh and the index of the floor's first face."""
    import trimesh

    box = trimesh.creation.box(extents=(1.0, 0.6, 1.0))
    bv = np.asarray(box.vertices, np.float64) + np.array([1.5, 0.3, 0.0])
    fv = np.array([[-8, 0, -8], [8, 0, -8], [8, 0, 8], [-8, 0, 8]], np.float64)
    ff = np.array([[0, 2, 1], [0, 3, 2]], np.int64) + len(bv)
    faces = np.vstack([np.asarray(box.faces, np.int64), ff])
    return TriMesh(np.vstack([bv, fv]), faces), len(box.faces)


@pytest.mark.slow(minutes=0.5)
def test_a_grazing_suns_shadow_edge_on_a_box_matches_mitsuba():
    """A 3-degree disc 10 degrees above the horizon along +x behind a box on a white Lambertian
    floor: the box's shadow runs 3.4 units along the floor and its penumbra widens to about 1 unit
    at its far end. Ours (the sun found in the map, 32 directions, one shadow ray each from the
    floor's points) against Mitsuba's one-bounce render at the same pixels, floor pixels whose
    neighbours are floor too: the lit floor within 2%, the shadowed within 1% of the lit level,
    the light missing from the shadow (against each one's lit floor) within 2%, and across the penumbra (pixels between 5% and
    95% lit) a median difference under 4% of the lit level (32 directions quantise a share in
    steps of 3%, Mitsuba's 128 samples add their own noise)."""
    mi = _mitsuba()
    mesh, floor = _box_on_a_floor()
    views = ViewSet(np.array([math.pi / 2]), np.array([math.radians(65.0)]), np.array([7.0]), 50.0, 128, 0.0, 0.0)
    hits = _hits(mesh, views)
    el = math.radians(10.0)
    env = _disc_map(np.array([math.cos(el), math.sin(el), 0.0]))
    theirs, alpha = _renderer(mi, mesh, views, env, hits)({"type": "diffuse", "reflectance": {"type": "rgb", "value": [1.0] * 3}})
    face = np.full(views.width**2, -1)
    face[hits.pixel] = hits.face
    grid = face.reshape(views.width, views.width)
    pad = np.pad(grid, 1, constant_values=-1)
    inner = np.ones_like(grid, bool)
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            inner &= pad[dy : dy + views.width, dx : dx + views.width] >= floor
    keep = inner.reshape(-1)[hits.pixel] & (alpha > 0.999)
    points = hits.point.astype(np.float64)[keep]
    normals = np.tile([0.0, 1.0, 0.0], (len(points), 1))
    sun = _found_sun(env, 32)
    cache = ShadowCache(mesh, points, normals, EmbreeTracer(mesh), directions=64, samples=0)
    share = cache.sun_shares(sun)
    m = SimpleNamespace(albedo=torch.ones(len(points), 3, dtype=torch.float64), specular=None, roughness=None)
    n = torch.from_numpy(normals)
    v = -torch.from_numpy(hits.direction.astype(np.float64)[keep])
    ours = sun.shade(TANGO, n, v, m, None, share).rgb.numpy().mean(1)
    theirs = theirs[keep].mean(1)
    level = float(sun.shade(TANGO, n[:1], v[:1], m, None, None).rgb.mean())  # the unshadowed floor
    lit = theirs / level  # the regions as Mitsuba rendered them
    full, dark, edge = lit > 0.99, lit < 0.01, (lit > 0.05) & (lit < 0.95)
    assert full.sum() > 2000 and dark.sum() > 300 and edge.sum() > 100, (full.sum(), dark.sum(), edge.sum())
    assert abs(theirs[full].mean() / level - 1.0) < 0.02 and abs(ours[full].mean() / level - 1.0) < 0.01
    assert ours[dark].mean() < 0.01 * level
    # the light missing from the shadow, each against its own lit floor, over where a disc twice as
    # wide would cast any shade (chosen by the geometry, not by either render's noise)
    wide = SunLight(sun.direction, sun.irradiance, 2.0 * sun.radius, 64)
    shade = cache.sun_shares(wide).numpy().min(1) < 1.0
    missing_ours, missing_theirs = (level - ours[shade]).sum(), (theirs[full].mean() - theirs[shade]).sum()
    assert abs(missing_ours / missing_theirs - 1.0) < 0.02, (missing_ours, missing_theirs)
    assert np.median(np.abs(ours[edge] - theirs[edge])) < 0.04 * level
