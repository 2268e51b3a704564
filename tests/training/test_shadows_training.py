"""Shadows through the workflow's own path: the raycache stage traces each hit's visibility when
``raycache.visibility`` says so (``auto`` from the measured self-occlusion), every view of a
field that casts shadows is shaded with them (dimmer where the mesh blocks the light, never
brighter), ``optimize.shadows: false`` switches them off, and an optimisation on such a cache
runs and records what it cast."""

import json

import numpy as np
import pytest
import torch

from stages import optimize, raycache
from stages.config.sections import NormalizeSettings, OptimizeSettings, RaycacheSettings
from stages.geometry.meshio import save_ply
from stages.geometry.normalization import normalize_mesh
from stages.geometry.raycache import RayCache
from stages.imaging.views import ViewStore
from stages.model.field import StyleField

SMALL = dict(views=3, resolution=32, eval_azimuths=2, eval_elevations_deg=(20.0,), eval_resolution=24)


@pytest.fixture(scope="module")
def knot(tmp_path_factory):
    d = tmp_path_factory.mktemp("knot")
    save_ply(d / "knot.ply", normalize_mesh("builtin:knot", NormalizeSettings()).mesh)
    return d


def _run(d, name, **settings):
    out = d / name
    raycache.run(d / "knot.ply", out / "train.npz", out / "eval.npz", out / "meta.json", RaycacheSettings(**SMALL, **settings))
    return out, json.loads((out / "meta.json").read_text())


def test_the_raycache_traces_visibility_when_asked_or_when_the_mesh_needs_it(knot):
    on, meta = _run(knot, "on", visibility="on", visibility_directions=64)
    cache = RayCache(on / "train.npz")
    assert cache.visibility_directions == 64 and cache.arrays["visibility"].shape == (len(cache.arrays["face"]), 8)
    assert meta["visibility"]["on"] and meta["stats"]["train"]["visibility_bytes"] == 8 * len(cache.arrays["face"])
    assert cache.visibility(1).shape == (cache.arrays["offsets"][2] - cache.arrays["offsets"][1], 8)
    off, meta = _run(knot, "off", visibility="off")
    assert RayCache(off / "train.npz").visibility_directions == 0 and not meta["visibility"]["on"]
    # auto: the 95th percentile of the knot's self-occlusion (about 0.45) against the threshold
    p95 = meta["self_occlusion"]["p95"]
    assert 0.3 < p95 < 0.6
    _, meta = _run(knot, "auto-on", visibility="auto", visibility_directions=64, visibility_auto_p95=p95 - 0.05)
    assert meta["visibility"]["on"] and "auto" in meta["visibility"]["why"]
    _, meta = _run(knot, "auto-off", visibility="auto", visibility_directions=64, visibility_auto_p95=p95 + 0.05)
    assert not meta["visibility"]["on"]


def test_by_default_a_convex_mesh_pays_nothing_and_the_knot_casts_shadows(knot, tmp_path):
    """The default ``auto``: a sphere (self-occlusion 0 everywhere) gets no visibility, the knot
    (95th percentile about 0.45) gets it."""
    import trimesh

    assert RaycacheSettings().visibility == "auto"
    ball = trimesh.creation.icosphere(subdivisions=3)
    ball.export(tmp_path / "ball.obj")
    save_ply(tmp_path / "ball.ply", normalize_mesh(str(tmp_path / "ball.obj"), NormalizeSettings()).mesh)
    rc = RaycacheSettings(**SMALL)
    raycache.run(tmp_path / "ball.ply", tmp_path / "train.npz", tmp_path / "eval.npz", tmp_path / "meta.json", rc)
    meta = json.loads((tmp_path / "meta.json").read_text())
    assert meta["self_occlusion"]["p95"] == 0.0 and not meta["visibility"]["on"]
    assert RayCache(tmp_path / "train.npz").visibility_directions == 0
    assert "visibility" not in meta["timings_s"] or meta["timings_s"]["visibility"] < 0.01
    _, meta = _run(knot, "default")
    assert meta["visibility"]["on"] and "p95" in meta["visibility"]["why"]


def test_a_field_casts_shadows_where_the_cache_holds_visibility(knot):
    out, _ = _run(knot, "shadowed", visibility="on", visibility_directions=256)
    cache = RayCache(out / "train.npz")
    field = StyleField(OptimizeSettings(width=16, light_lobes=8).field_settings())
    lit = ViewStore(cache, "cpu", field.normals, shadows=True)
    bare = ViewStore(cache, "cpu", field.normals, shadows=False)
    with torch.no_grad():
        shadowed = torch.cat([lit[i].shade(field).shading.rgb for i in range(len(cache))])
        plain = torch.cat([bare[i].shade(field).shading.rgb for i in range(len(cache))])
    assert torch.isfinite(shadowed).all()
    # a share never exceeds 1; the clamped cosine's SG fit dips 0.006 below zero past the horizon,
    # so dimming such a lobe can raise the sum by that much of its term (measured: 1.4e-4)
    assert (shadowed <= plain + 5e-4).all()
    darker = (shadowed.sum(1) < 0.9 * plain.sum(1)).float().mean()
    assert darker > 0.05, float(darker)  # the knot's crossings shadow each other
    # a field that does not cast shadows ignores the cache's visibility
    unshadowed = StyleField(OptimizeSettings(width=16, light_lobes=8, shadows=False).field_settings())
    assert not ViewStore(cache, "cpu", unshadowed.normals, shadows=unshadowed.shadows).shadows


@pytest.mark.slow
def test_an_optimisation_on_a_cache_with_visibility_casts_and_records_shadows(knot, tmp_path):
    out, _ = _run(knot, "train", visibility="on", visibility_directions=128)
    s = OptimizeSettings(iterations=3, clip_tiny_test=True, image_size=64, width=16, crops=1, light_lobes=8, eval_width=24)
    optimize.run(out / "train.npz", out / "eval.npz", "a knot made of wood", tmp_path, s, "cpu")
    meta = json.loads((tmp_path / "meta.json").read_text())
    assert meta["shadows"] == {"cast": True, "why": "visibility of 128 directions per hit", "directions": 128}
    losses = [float(r.split(",")[1]) for r in (tmp_path / "loss.csv").read_text().splitlines()[1:]]
    assert len(losses) == 3 and np.isfinite(losses).all()
    off = OptimizeSettings(**{**s.to_dict(), "shadows": False})
    optimize.run(out / "train.npz", out / "eval.npz", "a knot made of wood", tmp_path / "off", off, "cpu")
    assert json.loads((tmp_path / "off" / "meta.json").read_text())["shadows"]["cast"] is False
