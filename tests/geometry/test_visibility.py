"""Visibility bits traced with Embree against analytic answers: a sphere hanging over a floor
blocks a cone of the floor's hemisphere, a closed box blocks all of it from inside, a convex
mesh none of it from outside; lobe samples against the SG's own distribution."""

import math

import numpy as np
import pytest
import trimesh
from conftest import floor_and_ball, trimesh_parts

from stages.geometry.meshio import TriMesh
from stages.geometry.tracing import EmbreeTracer
from stages.geometry.visibility import (
    blocked_share,
    direction_spacing,
    fibonacci_directions,
    measure_self_occlusion,
    sample_lobe_directions,
    self_occlusion,
    surface_offset,
    trace_lobe_visibility,
    trace_visibility,
    unpack_visibility,
    viewer_side_normals,
)


def test_directions_cover_the_sphere_evenly():
    d = fibonacci_directions(1024)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    # every octant's share and the mean: a uniform set
    assert abs(d.mean(0)).max() < 2e-3
    assert abs((d[:, 2] > 0).mean() - 0.5) < 1e-9
    assert math.isclose(direction_spacing(1024), math.sqrt(4 * math.pi / 1024))
    with pytest.raises(ValueError, match="multiple of 8"):
        fibonacci_directions(12)


@pytest.mark.parametrize("height,radius", [(2.0, 1.0), (3.0, 0.5), (1.2, 1.0)])
def test_a_ball_over_a_floor_blocks_its_cone(height, radius):
    """A point on a floor under a ball of radius r at height H: the blocked directions are the
    cone of half-angle asin(r / H), 1 - cos of it the share of the hemisphere (uniform measure)."""
    mesh = floor_and_ball(height, radius)
    dirs = fibonacci_directions(4096)
    pts = np.array([[0.0, 0.0, 0.0], [15.0, 15.0, 0.0]])
    nrm = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    bits = trace_visibility(EmbreeTracer(mesh), pts, nrm, dirs, surface_offset(mesh.vertices))
    share = blocked_share(bits, nrm, dirs)
    expected = 1.0 - math.cos(math.asin(radius / height))
    # the icosphere is inscribed in the sphere (its cone a little narrower) and 2048 directions
    # above the floor resolve the cone's rim to about one spacing
    assert share[0] == pytest.approx(expected, abs=0.012), (share[0], expected)
    # far from the ball: the ball's cone from there, still tiny, and nothing else
    far = 1.0 - math.cos(math.asin(radius / math.sqrt(2 * 15.0**2 + height**2)))
    assert share[1] == pytest.approx(far, abs=0.003)
    # bits below the surface are 0, and the layout is numpy's packbits of the visible set
    visible = unpack_visibility(bits, len(dirs))
    assert not visible[:, dirs[:, 2] <= 0].any()
    assert (np.packbits(visible, axis=1) == bits).all()


def test_inside_a_closed_box_everything_is_blocked_and_outside_a_convex_mesh_nothing():
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    mesh = trimesh_parts(box)
    dirs = fibonacci_directions(512)
    tracer = EmbreeTracer(mesh)
    offset = surface_offset(mesh.vertices)
    # the inside of the bottom face (seen from inside: normal +z) and the outside of the top face
    pts = np.array([[0.1, -0.2, -0.5], [0.2, 0.3, 0.5], [0.5, 0.0, 0.0]])
    nrm = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    share = blocked_share(trace_visibility(tracer, pts, nrm, dirs, offset), nrm, dirs)
    np.testing.assert_array_equal(share, [1.0, 0.0, 0.0])


def test_the_bits_do_not_depend_on_the_batches_or_the_threads(monkeypatch):
    """Batches traced whole on several threads (Embree) give the bits of one thread, of a tracer
    that takes no concurrent queries (trimesh's reference, traced in order), and of any batch size
    (a batch smaller than a point's directions, and one point per batch)."""
    from stages.core.threads import set_cpu_threads
    from stages.geometry import visibility
    from stages.geometry.tracing import TrimeshTracer

    mesh = floor_and_ball(2.0, 1.0)
    dirs = fibonacci_directions(64)
    rng = np.random.default_rng(3)
    pts = np.c_[rng.uniform(-2, 2, (40, 2)), np.zeros(40)]
    nrm = np.tile([0.0, 0.0, 1.0], (40, 1))
    offset = surface_offset(mesh.vertices)
    embree = EmbreeTracer(mesh)
    results = []
    try:
        for threads, batch in ((1, 1 << 16), (3, 1 << 16), (2, 100), (3, 8)):
            set_cpu_threads(threads)
            monkeypatch.setattr(visibility, "RAYS_PER_BATCH", batch)
            results.append(trace_visibility(embree, pts, nrm, dirs, offset))
        results.append(trace_visibility(TrimeshTracer(mesh), pts, nrm, dirs, offset))
    finally:
        set_cpu_threads(None)
    assert blocked_share(results[0], nrm, dirs).max() > 0.05  # some points under the ball
    for bits in results[1:]:
        np.testing.assert_array_equal(bits, results[0])


def test_viewer_side_normals_turn_to_the_eye():
    n = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    rays = np.array([[0.0, 0.0, -1.0], [0.0, 0.3, 1.0]])  # from above, from below
    np.testing.assert_array_equal(viewer_side_normals(n, rays), [[0, 0, 1], [0, 0, -1]])


def test_self_occlusion_statistics():
    shares = np.array([0.0, 0.1, 0.2, 0.3, 1.0])
    stats = self_occlusion(shares)
    assert stats["median"] == 0.2 and stats["p95"] == 1.0 and stats["mean"] == pytest.approx(0.32)
    # weights: a point standing for more surface counts more
    weighted = self_occlusion(shares, np.array([10.0, 1.0, 1.0, 1.0, 1.0]))
    assert weighted["median"] == 0.0 and weighted["mean"] == pytest.approx(1.6 / 14)


@pytest.mark.parametrize("sharpness", [1e-4, 1.0, 30.0, 1e3, 1e5])
def test_lobe_samples_follow_the_lobe(sharpness):
    """The samples' mean cosine to the axis against the vMF's, coth(lam) - 1/lam, written from the
    density exp(lam (c - 1)) on [-1, 1] (integrated by parts here, not through the sampler)."""
    axis = np.array([0.3, -0.4, 0.5])
    d = sample_lobe_directions(axis, sharpness, 200_000, seed=1)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-9)
    c = d @ (axis / np.linalg.norm(axis))
    lam = sharpness
    expected = 1.0 / math.tanh(lam) - 1.0 / lam if lam > 1e-3 else lam / 3.0
    spread = math.sqrt(max(np.var(c), 1e-30) / len(c))
    assert abs(c.mean() - expected) < 5 * spread + 1e-12
    # the azimuth is uniform: the component off the axis averages to zero
    off = d - c[:, None] * axis / np.linalg.norm(axis)
    assert np.linalg.norm(off.mean(0)) < 5 * math.sqrt(max((1 - c * c).mean(), 1e-30) / len(c)) + 1e-12


def test_traced_lobe_visibility_against_the_cone():
    """A broad-enough lobe pointing at the ball: the share of its cosine-weighted mass outside the
    ball's cone, by rays drawn from the lobe, against the same integral by quadrature in the test."""
    height, radius, lam = 2.0, 1.0, 8.0
    mesh = floor_and_ball(height, radius)
    axis = np.array([0.0, 0.0, 1.0])
    dirs = sample_lobe_directions(axis, lam, 4096, seed=3)
    pts, nrm = np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]])
    traced = trace_lobe_visibility(EmbreeTracer(mesh), pts, nrm, dirs, surface_offset(mesh.vertices))
    # quadrature over the polar angle: exp(lam (cos t - 1)) cos t sin t, blocked below asin(r / H)
    t = np.linspace(0.0, math.pi / 2, 200_001)
    f = np.exp(lam * (np.cos(t) - 1.0)) * np.cos(t) * np.sin(t)
    cone = math.asin(radius / height)
    expected = np.trapezoid(np.where(t > cone, f, 0.0), t) / np.trapezoid(f, t)
    assert traced[0] == pytest.approx(expected, abs=0.03), (traced[0], expected)


def test_self_occlusion_of_a_sheet_a_cup_and_a_ball():
    """An open square sheet: both sides seen, nothing blocked. A ball: only its outside seen,
    nothing blocked. A closed box with an open top (a cup, 1 x 1 x 1): the inside of its floor
    sees the opening's solid angle, so the median side (half of its area is inside) is blocked
    by more than the outside's 0, and the 95th percentile (the inside's corners) by most of it."""
    square = TriMesh(np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]), np.array([[0, 1, 2], [0, 2, 3]]))
    occ = measure_self_occlusion(square, EmbreeTracer(square))
    assert occ["sides_seen"] == 1.0 and occ["p95"] == 0.0
    ball = trimesh_parts(trimesh.creation.icosphere(subdivisions=3))
    occ = measure_self_occlusion(ball, EmbreeTracer(ball))
    assert occ["sides_seen"] == pytest.approx(0.5, abs=0.01) and occ["p95"] == 0.0
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    top = np.abs(box.triangles_center[:, 2] - 0.5) < 1e-9
    cup = TriMesh(np.asarray(box.vertices, np.float64), np.asarray(box.faces, np.int64)[~top])
    occ = measure_self_occlusion(cup, EmbreeTracer(cup))
    # 5 faces, both sides seen everywhere (the inside through the opening)
    assert occ["sides_seen"] == pytest.approx(1.0, abs=0.01)
    # half the seen sides are inside, where the walls block most of the hemisphere (the floor's
    # centre sees the opening as a square of solid angle 4 asin(1/5) = 0.81 sr, 13% of its hemisphere's
    # uniform measure); outside nothing is blocked
    assert occ["median"] < 0.35 and 0.6 < occ["p95"] < 1.0 and 0.25 < occ["mean"] < 0.5
