"""Mitsuba 3 sees through our cameras: same pinhole model, field of view, resolution and pixel
centres as the ray cache, judged by Mitsuba's own silhouette and hit points."""

import numpy as np
import pytest
from conftest import require_tool

from stages.config.sections import RaycacheSettings
from stages.geometry.meshio import TriMesh, save_ply
from stages.geometry.normalization import normalization_transform
from stages.geometry.raycache import RayCache, evaluation_views, trace_views, training_views
from stages.geometry.shapes import builtin_mesh
from stages.geometry.tracing import EmbreeTracer

mitsuba = pytest.importorskip("stages.reference.mitsuba")


def have_mitsuba() -> bool:
    try:
        mitsuba.import_mitsuba()
        return True
    except ImportError:
        return False


@pytest.fixture(scope="module")
def knot(tmp_path_factory):
    require_tool(have_mitsuba(), "Mitsuba 3 is not installed (pip install -e '.[reference]')")
    v, f = builtin_mesh("knot")
    mesh = TriMesh(normalization_transform(v).forward(v), f)
    path = tmp_path_factory.mktemp("mi") / "knot.ply"
    save_ply(path, mesh)
    return mesh, path


def cached(mesh, views, tmp_path, name):
    arrays, _ = trace_views(mesh, views, EmbreeTracer(mesh))
    np.savez(tmp_path / f"{name}.npz", **arrays)
    return RayCache(tmp_path / f"{name}.npz")


def compare(cache: RayCache, mesh_path, i: int, c2w=None) -> tuple[int, float, int]:
    """Pixels whose hit/miss differs, the largest hit-point distance on pixels both hit, and the
    number of object pixels of view ``i``."""
    c2w = cache.arrays["c2w"][i] if c2w is None else c2w
    mask, position = mitsuba.hit_positions(mesh_path, c2w, cache.fov_deg, cache.width)
    ours = cache.mask(i)
    hits = cache.view(i)
    ours_pos = np.zeros((cache.width * cache.width, 3), np.float32)
    ours_pos[hits.pixel] = hits.point
    ours_pos = ours_pos.reshape(cache.width, cache.width, 3)
    both = ours & mask
    gap = float(np.abs(position[both] - ours_pos[both]).max()) if both.any() else np.inf
    return int((ours != mask).sum()), gap, int(ours.sum())


@pytest.mark.parametrize("which", ["train", "eval"])
def test_silhouette_and_hit_points_match_the_ray_cache(knot, tmp_path, which):
    mesh, path = knot
    s = RaycacheSettings(
        views=4, resolution=96, eval_azimuths=4, eval_elevations_deg=(-30.0, 30.0), eval_resolution=80, eval_fov_deg=45.0
    )
    views = training_views(s) if which == "train" else evaluation_views(s)
    cache = cached(mesh, views, tmp_path, which)
    for i in range(len(cache)):
        differ, gap, pixels = compare(cache, path, i)
        assert pixels > 500
        # a ray that grazes an edge may go either way in two float32 tracers: allow 0.1% of the
        # object's pixels; hit points agree to float32 rounding of the unit-sphere scene
        assert differ <= max(2, pixels // 1000), (i, differ)
        assert gap < 2e-5, (i, gap)


def test_the_comparison_detects_a_wrong_camera(knot, tmp_path):
    """Mutations of the camera model (mirrored image, half-pixel shift, other field of view) are
    caught by the same comparison."""
    mesh, path = knot
    s = RaycacheSettings(eval_azimuths=1, eval_elevations_deg=(20.0,), eval_resolution=64)
    cache = cached(mesh, evaluation_views(s), tmp_path, "one")
    c2w = cache.arrays["c2w"][0]
    assert compare(cache, path, 0)[0] <= 2
    mirrored = c2w @ np.diag([-1.0, 1.0, 1.0, 1.0])  # x flipped: Mitsuba's left-handed image
    theta = np.arctan(np.tan(np.deg2rad(cache.fov_deg) / 2) / cache.width)  # half a pixel
    turn = np.eye(4)
    turn[[0, 0, 2, 2], [0, 2, 0, 2]] = [np.cos(theta), np.sin(theta), -np.sin(theta), np.cos(theta)]
    tilted = c2w @ turn  # the optical axis turned by half a pixel: pixel corners, not centres
    for wrong in (mirrored, tilted):
        differ, gap, pixels = compare(cache, path, 0, wrong)
        assert differ > pixels // 100 or gap > 1e-3, (differ, gap)
