"""raycache: cameras, Embree hits against analytic ray-sphere answers, Embree vs trimesh's
pure-Python tracer, the cache format and its reader."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import icosphere

from stages import raycache
from stages.config.sections import RaycacheSettings
from stages.core.errors import StageInputError
from stages.geometry.cameras import (
    POLE_MARGIN,
    camera_positions,
    camera_space_directions,
    grid_views,
    look_at,
    sample_views,
    world_rays,
)
from stages.geometry.meshio import TriMesh, save_ply
from stages.geometry.raycache import RayCache, ViewSet, evaluation_views, trace_views
from stages.geometry.tracing import EmbreeTracer, TrimeshTracer


def test_look_at_is_orthonormal_and_faces_origin(rng):
    az = rng.uniform(-np.pi, np.pi, 200)
    el = rng.uniform(-np.pi / 2 + POLE_MARGIN, np.pi / 2 - POLE_MARGIN, 200)
    eye = camera_positions(az, el, 2.5)
    c2w = look_at(eye)
    r = c2w[:, :3, :3]
    np.testing.assert_allclose(np.einsum("vij,vik->vjk", r, r), np.broadcast_to(np.eye(3), r.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-12)
    # the camera's -z axis points at the origin; +x (image right) is horizontal
    np.testing.assert_allclose(-r[:, :, 2], -eye / 2.5, atol=1e-12)
    np.testing.assert_allclose(r[:, 1, 0], 0.0, atol=1e-12)
    assert (r[:, 1, 1] > 0).all()  # image up has a positive world-y component


def test_camera_directions_centre_and_corners():
    d = camera_space_directions(4, 90.0).reshape(4, 4, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0)
    assert (d[..., 2] < 0).all()
    # top-left pixel points up-left, bottom-right down-right; tan(45 deg) = 1 at the image edge
    assert d[0, 0, 0] < 0 < d[0, 0, 1] and d[3, 3, 1] < 0 < d[3, 3, 0]
    x_over_z = -d[0, :, 0] / d[0, :, 2]
    np.testing.assert_allclose(x_over_z, [-0.75, -0.25, 0.25, 0.75])


def test_view_sampler_statistics():
    n = 20000
    az, el = sample_views(n, anchor_azimuth=1.0, anchor_elevation=0.2, std=8.0, rng=np.random.default_rng(0))
    assert (az[0], el[0]) == (1.0, 0.2)
    # spreads pi/std (elevation) and 2 pi/std (azimuth): sample std within 4 standard errors
    # (the std of a normal sample has standard error sigma / sqrt(2 n))
    for sample, sigma, mean in ((az[1:], 2 * np.pi / 8, 1.0), (el[1:], np.pi / 8, 0.2)):
        se = sigma / np.sqrt(2 * n)
        assert abs(sample.std() - sigma) < 4 * se
        assert abs(sample.mean() - mean) < 4 * sigma / np.sqrt(n)
    again = sample_views(n, anchor_azimuth=1.0, anchor_elevation=0.2, std=8.0, rng=np.random.default_rng(0))
    np.testing.assert_array_equal(again[0], az)


def test_elevations_clamped_away_from_poles():
    _, el = sample_views(1000, anchor_azimuth=0.0, anchor_elevation=1.5, std=1.0, rng=np.random.default_rng(1))
    assert np.abs(el).max() <= np.pi / 2 - POLE_MARGIN
    assert np.isfinite(look_at(camera_positions(0.3, el, 2.0))).all()


def test_grid_views():
    az, el = grid_views(8, (-30.0, 0.0, 30.0))
    assert len(az) == 24
    np.testing.assert_allclose(np.unique(np.rad2deg(el)), [-30, 0, 30])
    np.testing.assert_allclose(np.unique(az), np.arange(8) * np.pi / 4)


@pytest.mark.parametrize(("az", "el"), [(1.96, 0.63), (0.0, 0.0), (-2.5, -1.2), (0.7, np.pi / 2 - POLE_MARGIN)])
def test_hits_agree_with_analytic_sphere(az, el):
    """Icosphere (vertices on the unit sphere) against the analytic unit sphere.

    The polyhedron lies between the unit sphere and the sphere of radius ``1 - h`` through its
    faces' planes' closest points (``h`` = max over faces of ``1 - n_f . v0``), so for every ray
    the first hit depth lies between the analytic depths on those two spheres, the hit radius
    in ``[1 - h, 1]``, and the face normal within ``acos(1 - h)`` of the radial direction. These
    bounds are exact; the extra ``2e-6`` allows for float32 arithmetic in Embree.
    """
    mesh = icosphere(5)
    h = float((1.0 - np.einsum("ij,ij->i", mesh.face_normals, mesh.vertices[mesh.faces[:, 0]])).max())
    assert 0 < h < 1e-3
    width, fov, radius = 96, 60.0, 2.5
    views = ViewSet(np.array([az]), np.array([el]), np.array([radius]), fov, width, 0.0, 0.0)
    arrays, stats = trace_views(mesh, views, EmbreeTracer(mesh))
    cache_file = {k: v for k, v in arrays.items()}
    origins, dirs = world_rays(views.c2w[0], camera_space_directions(width, fov))
    o = origins[0]

    def sphere_depth(r):
        b = dirs @ o
        disc = b * b - (o @ o - r * r)
        return np.where(disc >= 0, -b - np.sqrt(np.maximum(disc, 0.0)), np.inf)

    t_outer, t_inner = sphere_depth(1.0), sphere_depth(1.0 - h)
    hit = np.zeros(width * width, bool)
    hit[cache_file["pixel"]] = True
    eps = 2e-6
    # coverage: rays that reach the inner sphere must hit; rays missing the unit sphere must not
    assert hit[np.isfinite(t_inner)].all()
    assert not hit[~np.isfinite(t_outer)].any()
    # depths, points and normals through the cache reader
    path_cache = RayCacheFromArrays(cache_file)
    v = path_cache.view(0)
    t = np.einsum("ij,ij->i", v.point - o, v.direction)
    assert (t >= t_outer[v.pixel] - eps).all()
    inner_ok = np.isfinite(t_inner[v.pixel])
    assert (t[inner_ok] <= t_inner[v.pixel][inner_ok] + eps).all()
    rad = np.linalg.norm(v.point, axis=1)
    assert ((rad >= 1 - h - eps) & (rad <= 1 + eps)).all()
    cos = np.einsum("ij,ij->i", v.normal, v.point / rad[:, None])
    assert (cos >= 1 - h - eps).all()
    # the hit faces face the camera on a closed convex mesh
    assert (np.einsum("ij,ij->i", v.normal, v.direction) < 0).all()
    assert stats.hits == len(v.pixel)


class RayCacheFromArrays(RayCache):
    def __init__(self, arrays):  # bypass the file
        self.arrays = arrays
        self.width = int(arrays["width"])
        self.fov_deg = float(arrays["fov_deg"])


def test_embree_matches_trimesh_tracer(rng):
    mesh = icosphere(2)
    # a non-convex, off-centre mesh: two spheres, one half inside the other
    mesh = TriMesh(
        np.concatenate([mesh.vertices * 0.6 + [0.2, 0, 0], mesh.vertices * 0.4 - [0.3, 0.1, 0]]),
        np.concatenate([mesh.faces, mesh.faces + len(mesh.vertices)]),
    )
    views = ViewSet(np.array([0.3, 2.0]), np.array([0.2, -0.5]), np.array([2.0, 2.0]), 60.0, 20, 0.0, 0.0)
    c2w = views.c2w
    cam = camera_space_directions(20, 60.0)
    embree, ref = EmbreeTracer(mesh), TrimeshTracer(mesh)
    for i in range(len(views)):
        o, d = world_rays(c2w[i], cam)
        a, b = embree.trace(o, d), ref.trace(o, d)
        np.testing.assert_array_equal(a.face >= 0, b.face >= 0)
        both = a.face >= 0
        # rays grazing an edge may legitimately pick either neighbour: compare away from edges
        u, v = a.bary[:, 0], a.bary[:, 1]
        interior = both & (np.minimum(np.minimum(u, v), 1 - u - v) > 1e-4)
        assert interior.sum() > 0.8 * both.sum() > 0
        np.testing.assert_array_equal(a.face[interior], b.face[interior])
        np.testing.assert_allclose(a.depth[interior], b.depth[interior], rtol=1e-5)
        np.testing.assert_allclose(a.bary[interior], b.bary[interior], atol=1e-4)


def test_cache_files_and_metadata(tmp_path):
    rng = np.random.default_rng(3)
    mesh = icosphere(3)
    # add degenerate faces: they must not produce NaNs anywhere
    mesh = TriMesh(mesh.vertices, np.concatenate([mesh.faces, [[0, 0, 1], [2, 2, 2]]]))
    src = tmp_path / "sphere.ply"
    save_ply(src, mesh)
    settings = RaycacheSettings(views=5, resolution=40, eval_azimuths=4, eval_elevations_deg=(0.0, 45.0), eval_resolution=24)
    out = tmp_path / "rc"
    code = raycache.main(
        [
            "--input",
            str(src),
            "--train",
            str(out / "train.npz"),
            "--eval",
            str(out / "eval.npz"),
            "--meta",
            str(out / "meta.json"),
            "--settings",
            json.dumps(settings.to_dict()),
        ]
    )
    assert code == 0
    train, ev = RayCache(out / "train.npz"), RayCache(out / "eval.npz")
    assert len(train) == 5 and len(ev) == 8 and train.width == 40 and ev.width == 24
    a = train.arrays
    assert a["pixel"].dtype == np.uint32 and a["face"].dtype == np.int32 and a["bary"].dtype == np.uint16
    np.testing.assert_allclose(a["azimuth"][0], settings.anchor_azimuth)
    np.testing.assert_allclose(np.linalg.norm(a["c2w"][:, :3, 3], axis=1), settings.radius)
    for i in range(len(train)):
        v = train.view(i)
        assert np.isfinite(v.point).all() and np.isfinite(v.normal).all()
        assert np.all(np.diff(v.pixel) > 0)  # raster order, no duplicates
        assert train.mask(i).sum() == len(v.pixel)
    meta = json.loads((out / "meta.json").read_text())
    assert meta["seed"] == 0 and meta["settings"]["views"] == 5
    bpv = meta["stats"]["train"]["bytes_per_view"]
    assert bpv == pytest.approx(train.bytes_per_view())
    assert bpv == pytest.approx(12 * a["offsets"][-1] / 5)
    # a convex mesh blocks nothing of what its outside sees; its inside is never seen
    occ = meta["self_occlusion"]
    assert occ["median"] == 0.0 and occ["p95"] == 0.0 and occ["sides_seen"] == pytest.approx(0.5, abs=0.01)
    # same seed -> same cache; another seed -> other views
    again = tmp_path / "again"
    raycache.run(src, again / "t.npz", again / "e.npz", again / "m.json", settings)
    np.testing.assert_array_equal(RayCache(again / "t.npz").arrays["pixel"], a["pixel"])
    del rng


def test_pixel_index_convention():
    """A small square seen in the upper-left of the image lands in the upper-left pixels."""
    # camera at azimuth 0, elevation 0 -> eye on +x, looking at -x; image right is -z, up is +y
    eye_x = 3.0
    sq = np.array([[0, 0.5, 0.3], [0, 0.9, 0.3], [0, 0.9, 0.7], [0, 0.5, 0.7]], float)
    mesh = TriMesh(sq, np.array([[0, 1, 2], [0, 2, 3]]))
    views = ViewSet(np.array([0.0]), np.array([0.0]), np.array([eye_x]), 60.0, 32, 0.0, 0.0)
    arrays, _ = trace_views(mesh, views, EmbreeTracer(mesh))
    rows, cols = np.divmod(arrays["pixel"].astype(int), 32)
    assert rows.max() < 16 and cols.max() < 16  # upper-left quadrant
    # exactly the pixels whose centre ray crosses the plane x = 0 inside the square
    o, d = world_rays(views.c2w[0], camera_space_directions(32, 60.0))
    p = o + d * (-o[:, :1] / d[:, :1])
    inside = (p[:, 1] > 0.5) & (p[:, 1] < 0.9) & (p[:, 2] > 0.3) & (p[:, 2] < 0.7)
    np.testing.assert_array_equal(np.flatnonzero(inside), arrays["pixel"])


@pytest.mark.parametrize("anchor", [(1.96, 0.63), (0.2, -0.4), (4.0, 0.0)])
def test_front_view_is_the_view_nearest_the_recorded_anchor(tmp_path, anchor):
    """The front view (previews, material editing) follows the anchor the cache recorded, not a
    constant: the evaluation view at the smallest great-circle angle from the anchor direction."""
    settings = RaycacheSettings(
        views=2,
        resolution=16,
        eval_azimuths=8,
        eval_elevations_deg=(-30.0, 0.0, 30.0),
        eval_resolution=16,
        anchor_azimuth=anchor[0],
        anchor_elevation=anchor[1],
    )
    views = evaluation_views(settings)
    arrays, _ = trace_views(icosphere(2), views, EmbreeTracer(icosphere(2)))
    np.savez(tmp_path / "e.npz", **arrays)
    cache = RayCache(tmp_path / "e.npz")
    # spherical law of cosines, from the grid's angles (not from the cameras' positions)
    az0, el0 = anchor
    cos_angle = np.sin(el0) * np.sin(views.elevation) + np.cos(el0) * np.cos(views.elevation) * np.cos(views.azimuth - az0)
    assert cache.front_view() == int(np.argmax(cos_angle))
    # a cache written before the anchor was recorded says what to do
    old = {k: v for k, v in arrays.items() if not k.startswith("anchor_")}
    np.savez(tmp_path / "old.npz", **old)
    with pytest.raises(StageInputError, match="anchor"):
        RayCache(tmp_path / "old.npz").front_view()


def test_anchor_in_degrees_moves_the_pool_and_the_front_view_and_is_recorded(tmp_path):
    """``anchor_deg`` (per mesh, degrees) replaces the radian anchor: view 0 of the pool sits at
    it, the caches record it, the front view follows it, and the metadata says what set it."""
    import json
    import math

    from stages.core.errors import ConfigError
    from stages.geometry.meshio import save_ply

    s = RaycacheSettings(views=3, resolution=16, eval_resolution=16, metrics_resolution=16, anchor_deg=(-90.0, 20.0))
    az, el, source = s.anchor()
    assert (az, el) == pytest.approx((-math.pi / 2, math.radians(20.0))) and source == "raycache.anchor_deg"
    assert RaycacheSettings().anchor()[2].startswith("default")
    assert RaycacheSettings.from_dict({"anchor_deg": [90, 15]}).anchor_deg == (90, 15)  # a config's list
    assert "radians" in RaycacheSettings(anchor_azimuth=0.5).anchor()[2]
    save_ply(tmp_path / "m.ply", icosphere(2))
    raycache.run(tmp_path / "m.ply", tmp_path / "t.npz", tmp_path / "e.npz", tmp_path / "meta.json", s)
    train = RayCache(tmp_path / "t.npz")
    assert train.arrays["azimuth"][0] == pytest.approx(-math.pi / 2) and train.arrays["elevation"][0] == pytest.approx(
        math.radians(20)
    )
    # camera 0 looks from azimuth -90 deg: from -z (azimuth measured from +x towards +z)
    eye = train.arrays["c2w"][0][:3, 3]
    np.testing.assert_allclose(
        eye / np.linalg.norm(eye), [0.0, math.sin(math.radians(20)), -math.cos(math.radians(20))], atol=1e-9
    )
    meta = json.loads((tmp_path / "meta.json").read_text())
    assert meta["anchor"]["set_by"] == "raycache.anchor_deg" and meta["anchor"]["azimuth_deg"] == pytest.approx(-90.0)
    evalc = RayCache(tmp_path / "e.npz")
    front = evalc.arrays["c2w"][evalc.front_view()][:3, 3]
    assert front[2] < -0.5 * np.linalg.norm(front)  # the evaluation view on the -z side
    for bad in ((0.0, 90.0), (10.0,)):
        with pytest.raises(ConfigError, match="anchor_deg"):
            RaycacheSettings(anchor_deg=bad)
