"""Shading normals against analytic answers: the sphere's radial normal, the cube's corner diagonal
and face normals, the cylinder's radial sides and flat caps; seams, degenerate faces, winding and
scale/offset extremes."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import icosphere

from stages.geometry.normals import (
    NormalSpec,
    interpolate_normals,
    smooth_corner_normals,
    unit_face_normals,
)

# the unit cube: 8 vertices, 12 outward triangles (each square split along one diagonal)
CUBE_V = np.array([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)])
CUBE_F = np.array(
    [
        [0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5],  # x = -1, x = +1
        [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],  # y = -1, y = +1
        [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3],  # z = -1, z = +1
    ]
)  # fmt: skip


def split_faces(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every face with its own three vertices (a mesh split at every edge, like a faceted export)."""
    return v[f].reshape(-1, 3), np.arange(3 * len(f)).reshape(-1, 3)


def cylinder(segments: int = 48, rings: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Radius 1, z in [-1, 1], side rings and two fan caps, outward faces (built here, by hand)."""
    a = 2 * np.pi * np.arange(segments) / segments
    zs = np.linspace(-1, 1, rings + 1)
    side = np.array([[np.cos(t), np.sin(t), z] for z in zs for t in a])
    v = np.vstack([side, [[0, 0, -1], [0, 0, 1]]])
    bottom, top = len(side), len(side) + 1
    f = []
    for r in range(rings):
        for s in range(segments):
            i0, i1 = r * segments + s, r * segments + (s + 1) % segments
            j0, j1 = i0 + segments, i1 + segments
            f += [[i0, i1, j1], [i0, j1, j0]]
    for s in range(segments):
        f.append([bottom, (s + 1) % segments, s])
        last = rings * segments
        f.append([top, last + s, last + (s + 1) % segments])
    return v, np.array(f)


def test_face_normals_follow_the_right_hand_rule_and_are_zero_when_degenerate():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0]], float)
    n = unit_face_normals(v, np.array([[0, 1, 2], [0, 2, 1], [0, 1, 3]]))
    np.testing.assert_allclose(n, [[0, 0, 1], [0, 0, -1], [0, 0, 0]])


def test_sphere_corner_normals_are_radial_and_beat_flat_at_hits(rng):
    s = icosphere(3)
    corner = smooth_corner_normals(s.vertices, s.faces, 60.0)
    radial = s.vertices[s.faces]  # unit vectors: the sphere's exact normal at each vertex
    err = np.degrees(np.arccos(np.clip((corner * radial).sum(-1), -1, 1)))
    assert err.max() < 0.5  # a symmetric fan: only the icosphere's irregularity tilts it
    # at random points inside faces, the exact normal is the direction of the point's projection
    face = rng.integers(0, len(s.faces), 5000)
    uv = rng.dirichlet(np.ones(3), 5000)[:, 1:]
    tri = s.vertices[s.faces[face]]
    p = tri[:, 0] + uv[:, :1] * (tri[:, 1] - tri[:, 0]) + uv[:, 1:] * (tri[:, 2] - tri[:, 0])
    exact = p / np.linalg.norm(p, axis=1, keepdims=True)
    flat = unit_face_normals(s.vertices, s.faces)[face]
    smooth = interpolate_normals(corner, face, uv, flat)
    e_s = np.degrees(np.arccos(np.clip((smooth * exact).sum(1), -1, 1)))
    e_f = np.degrees(np.arccos(np.clip((flat * exact).sum(1), -1, 1)))
    assert e_s.max() < 0.6 and e_f.max() > 4.0 and e_s.mean() < 0.2 * e_f.mean()
    np.testing.assert_allclose(np.linalg.norm(smooth, axis=1), 1.0, atol=1e-12)


def test_a_seam_split_mesh_is_as_smooth_as_the_welded_one():
    s = icosphere(2)
    welded = smooth_corner_normals(s.vertices, s.faces, 60.0)
    v, f = split_faces(s.vertices, s.faces)
    split = smooth_corner_normals(v, f, 60.0)
    np.testing.assert_allclose(split, welded, atol=1e-9)


def test_cube_keeps_its_faces_below_90_degrees_and_angle_weights_give_the_diagonal():
    faces_n = unit_face_normals(CUBE_V, CUBE_F)
    for crease in (0.0, 30.0, 60.0, 89.0):
        c = smooth_corner_normals(CUBE_V, CUBE_F, crease)
        np.testing.assert_allclose(c, np.repeat(faces_n[:, None], 3, axis=1), atol=1e-12)
    # 90 degrees and more: one fan per corner; the three faces meet at right angles, so the
    # corner-angle weights are equal (pi/2 per face, however it is split) and the normal is the diagonal
    c = smooth_corner_normals(CUBE_V, CUBE_F, 90.0)
    diagonal = CUBE_V[CUBE_F] / np.sqrt(3.0)
    np.testing.assert_allclose(c, diagonal, atol=1e-12)
    # area weights see one or two triangles per square at a corner: not the diagonal
    a = smooth_corner_normals(CUBE_V, CUBE_F, 90.0, weighting="area")
    assert np.abs(a - diagonal).max() > 0.05


def test_cylinder_sides_are_radial_and_caps_flat_with_a_crease_and_blend_without():
    v, f = cylinder()
    c = smooth_corner_normals(v, f, 60.0)
    corners = v[f]
    side = np.abs(f).max(1) < len(v) - 2  # faces of the side (no cap centre)
    on_side = side[:, None] & np.ones((1, 3), bool)
    # side corners: the exact radial normal (x, y, 0), rim corners included
    radial = corners * np.array([1.0, 1.0, 0.0])
    np.testing.assert_allclose(c[on_side], radial[on_side], atol=1e-9)
    # cap corners: +-z exactly
    cap = ~side
    np.testing.assert_allclose(np.abs(c[cap][..., 2]), 1.0, atol=1e-12)
    # crease 100 degrees: the 90-degree rim is smooth, so rim corners lean between side and cap
    c2 = smooth_corner_normals(v, f, 100.0)
    rim = on_side & (np.abs(corners[..., 2]) == 1.0)
    assert (np.abs(c2[rim][:, 2]) > 0.3).all() and (np.abs(c2[rim][:, 2]) < 0.95).all()


def test_crease_zero_on_a_plane_and_flat_mode_are_the_face_normals(rng):
    g = np.stack(np.meshgrid(np.arange(5.0), np.arange(5.0)), -1).reshape(-1, 2)
    v = np.c_[g, np.zeros(len(g))]
    f = np.array(
        [[i, i + 1, i + 6] for i in range(24) if i % 5 < 4 and i < 19] + [[i, i + 6, i + 5] for i in range(19) if i % 5 < 4]
    )
    c = smooth_corner_normals(v, f, 0.0)
    np.testing.assert_allclose(c, np.tile([0.0, 0.0, 1.0], (len(f), 3, 1)), atol=1e-12)
    s = icosphere(1)
    flat = NormalSpec("flat").corner_normals(s.vertices, s.faces)
    np.testing.assert_allclose(flat, np.repeat(unit_face_normals(s.vertices, s.faces)[:, None], 3, 1))


def test_degenerate_faces_change_nothing_and_stay_finite():
    s = icosphere(2)
    ref = smooth_corner_normals(s.vertices, s.faces, 60.0)
    # a zero-area sliver on an existing edge and a face collapsed to one point
    f = np.vstack([s.faces, [s.faces[0, 0], s.faces[0, 1], s.faces[0, 1]], [s.faces[5, 2]] * 3])
    c = smooth_corner_normals(s.vertices, f, 60.0)
    assert np.isfinite(c).all()
    np.testing.assert_allclose(c[: len(s.faces)], ref, atol=1e-12)
    flat = unit_face_normals(s.vertices, f)
    hit = interpolate_normals(c, np.array([len(f) - 1, len(f) - 2]), np.array([[0.3, 0.3], [0.5, 0.2]]), flat[-2:])
    assert np.isfinite(hit).all()


@pytest.mark.parametrize("scale, offset", [(1e-6, 0.0), (1e6, 0.0), (1.0, 1e4), (1e-3, -50.0)])
def test_tiny_huge_and_off_centre_meshes_give_the_unit_mesh_normals(scale, offset):
    s = icosphere(2)
    ref = smooth_corner_normals(s.vertices, s.faces, 60.0)
    c = smooth_corner_normals(s.vertices * scale + offset, s.faces, 60.0)
    np.testing.assert_allclose(c, ref, atol=1e-6)


def test_inconsistent_winding_is_a_crease_and_the_rest_stays_smooth():
    s = icosphere(2)
    f = s.faces.copy()
    f[7] = f[7, ::-1]  # one face wound the other way: its normal points inwards
    c = smooth_corner_normals(s.vertices, f, 60.0)
    flat = unit_face_normals(s.vertices, f)
    np.testing.assert_allclose(c[7], np.repeat(flat[7][None], 3, 0), atol=1e-12)
    assert (np.einsum("fkc,fkc->fk", c, s.vertices[f])[np.arange(len(f)) != 7] > 0.99).all()


def test_interpolation_falls_back_to_the_face_normal_where_corners_cancel():
    corner = np.array([[[0, 0, 1.0], [0, 0, -1.0], [0, 0, 1.0]]])
    n = interpolate_normals(corner, np.array([0]), np.array([[0.5, 0.0]]), np.array([[1.0, 0, 0]]))
    np.testing.assert_allclose(n, [[1.0, 0, 0]])


def test_spec_validates_and_describes():
    assert "smooth" in NormalSpec("smooth", 45.0).describe() and "45" in NormalSpec("smooth", 45.0).describe()
    for bad in ({"mode": "phong"}, {"crease_angle_deg": 190.0}, {"weighting": "uniform"}):
        with pytest.raises(ValueError):
            NormalSpec(**bad)
