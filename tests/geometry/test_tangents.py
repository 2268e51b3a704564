"""MikkTSpace tangents against analytic answers (an affinely mapped plane, a cylinder's
circumference), mirrored UVs, welding by value, and the tangent-space round trip. Blender's own
MikkTSpace judges the exported frames in tests/reference/test_blender_assets.py."""

from __future__ import annotations

import numpy as np
import pytest

from stages.geometry.normals import NormalSpec, smooth_corner_normals
from stages.geometry.tangents import CornerFrames, from_tangent_space, mikktspace, to_tangent_space


def grid(n: int = 6):
    g = np.stack(np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n)), -1).reshape(-1, 2)
    f = []
    for r in range(n - 1):
        for c in range(n - 1):
            i = r * n + c
            f += [[i, i + 1, i + n + 1], [i, i + n + 1, i + n]]
    return g, np.array(f)


@pytest.mark.parametrize("mirror", [False, True])
def test_plane_with_an_affine_map_has_the_map_s_direction_and_handedness(mirror):
    st, f = grid()
    # positions: a sheared, scaled plane in 3D; st -> P is affine, so dP/ds is one vector
    a, b = np.array([2.0, 0.5, 0.0]), np.array([0.3, 1.0, 0.0])
    p2 = st @ np.stack([a, b])
    pos = p2[f]
    n = np.tile([0.0, 0.0, 1.0], (len(f), 3, 1))
    uv = st[f] * ([-1.0, 1.0] if mirror else [1.0, 1.0])
    t, w = mikktspace(pos, n, uv)
    # P = s a + t b, so dP/ds = a (and -a where s is mirrored), already in the plane of n
    want = a / np.linalg.norm(a) * (-1.0 if mirror else 1.0)
    np.testing.assert_allclose(t.reshape(-1, 3), np.tile(want, (3 * len(f), 1)), atol=1e-9)
    assert (w == (-1.0 if mirror else 1.0)).all()


def test_cylinder_tangents_run_around_it():
    seg, rings = 32, 3
    ang = 2 * np.pi * np.arange(seg + 1) / seg  # a seam: the first column is repeated at s = 1
    z = np.linspace(0, 1, rings + 1)
    v = np.array([[np.cos(t), np.sin(t), zz] for zz in z for t in ang])
    st = np.array([[k / seg, zz] for zz in z for k in range(seg + 1)])
    f = []
    for r in range(rings):
        for k in range(seg):
            i = r * (seg + 1) + k
            j = i + seg + 1
            f += [[i, i + 1, j + 1], [i, j + 1, j]]
    f = np.array(f)
    n = smooth_corner_normals(v, f, 60.0)
    t, w = mikktspace(v[f], n, st[f])
    p = v[f]
    want = np.stack([-p[..., 1], p[..., 0], np.zeros_like(p[..., 0])], -1)  # d/d(angle), unit
    np.testing.assert_allclose(t, want, atol=1e-9)
    assert (w == 1.0).all()


def test_faceted_input_welds_by_value_like_indexed_input(rng):
    from conftest import icosphere

    s = icosphere(2)
    # a UV map without seams inside: a planar projection (mirrored halves are avoided by z > 0)
    keep = s.vertices[s.faces][:, :, 2].min(1) > 0.05
    f = s.faces[keep]
    st = s.vertices[:, :2] * 0.5 + 0.5
    n = smooth_corner_normals(s.vertices, f, 60.0)
    t1, w1 = mikktspace(s.vertices[f], n, st[f])
    # the same corners in shuffled face order: results follow the faces
    perm = rng.permutation(len(f))
    t2, w2 = mikktspace(s.vertices[f][perm], n[perm], st[f][perm])
    np.testing.assert_allclose(t2, t1[perm], atol=1e-12)
    np.testing.assert_array_equal(w2, w1[perm])
    # a corner shared by faces gets one tangent (averaged), unlike each face's own dP/ds
    vid = f.reshape(-1)
    tv = t1.reshape(-1, 3)
    for v in np.unique(vid)[:50]:
        group = tv[vid == v]
        assert np.abs(group - group[0]).max() < 1e-9


def test_tangent_space_round_trip_in_a_skewed_frame(rng):
    t = rng.normal(size=(500, 3))
    n = rng.normal(size=(500, 3))
    b = rng.choice([-1.0, 1.0], (500, 1)) * np.cross(n, t)
    world = rng.normal(size=(500, 3))
    world /= np.linalg.norm(world, axis=1, keepdims=True)
    c = to_tangent_space(world, t, b, n)
    np.testing.assert_allclose(np.linalg.norm(c, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(from_tangent_space(c, t, b, n), world, atol=1e-9)


def test_frames_store_and_reload(rng):
    from conftest import icosphere

    s = icosphere(1)
    uv = rng.uniform(0, 1, (len(s.faces), 3, 2))
    fr = CornerFrames.build(s.vertices, s.faces, uv, NormalSpec("smooth"))
    back = CornerFrames.from_arrays(fr.arrays())
    for a, b in zip(
        (fr.normals, fr.tangents, fr.handedness, fr.face_normals),
        (back.normals, back.tangents, back.handedness, back.face_normals),
        strict=True,
    ):
        np.testing.assert_allclose(a, b, atol=1e-6)
    t, b, n = fr.at(np.array([0, 3]), np.array([[0.2, 0.3], [0.0, 0.0]]))
    np.testing.assert_allclose(n[1], fr.normals[3, 0])
    np.testing.assert_allclose(t[1], fr.tangents[3, 0])
