"""A second UV set (:func:`stages.geometry.uvsets.second_uv_set`): the vertices a per-corner
layout needs, every input vertex kept at its index. Checked against a cube's known unwrap and
against a brute force over (vertex, coordinate) pairs written here."""

from __future__ import annotations

import numpy as np
import pytest

from stages.geometry.uvsets import second_uv_set

#: a unit cube's 8 corners and its 6 faces as quads (each face's corners counter-clockwise)
CUBE_QUADS = np.array([[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]])
SQUARE = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], np.float32)


def _cube_by_faces() -> tuple[np.ndarray, np.ndarray]:
    """The cube's 12 triangles and a layout that gives each face its own square of a 3 x 2 grid."""
    tris, uv = [], []
    for f, quad in enumerate(CUBE_QUADS):
        corners = SQUARE / 4 + np.array([(f % 3) / 3, (f // 3) / 2], np.float32)
        for a, b, c in ((0, 1, 2), (0, 2, 3)):
            tris.append(quad[[a, b, c]])
            uv.append(corners[[a, b, c]])
    return np.array(tris), np.array(uv, np.float32)


def _brute(indices: np.ndarray, corner_uv: np.ndarray) -> dict:
    """Each vertex's coordinates in the order of their first corner (a dict, written plainly)."""
    seen: dict[int, list] = {}
    for v, (a, b) in zip(indices.reshape(-1).tolist(), corner_uv.reshape(-1, 2).tolist(), strict=True):
        key = (float(np.float32(a) + np.float32(0)), float(np.float32(b) + np.float32(0)))
        seen.setdefault(v, [])
        if key not in seen[v]:
            seen[v].append(key)
    return seen


def test_a_cube_unwrapped_face_by_face_needs_its_24_corners():
    """Each of the cube's 8 vertices lies on three faces, each its own island: 16 appended (the
    24 vertices of any face-by-face unwrap), every input vertex keeps its index and its first
    face's coordinate, and the corners of each vertex's first face keep their indices."""
    tris, uv = _cube_by_faces()
    out = second_uv_set(tris, uv, 8)
    assert out.appended == 16 and len(out.source) == 24 and out.uv.shape == (24, 2)
    np.testing.assert_array_equal(out.source[:8], np.arange(8))
    np.testing.assert_array_equal(out.uv[out.indices], uv)
    np.testing.assert_array_equal(out.source[out.indices], tris)
    assert sorted(np.bincount(out.source).tolist()) == [3] * 8  # three copies of every corner
    first_face = out.indices[:2]  # face 0 is read first: its corners keep their vertices
    np.testing.assert_array_equal(first_face, tris[:2])
    assert out.rewritten == int((out.indices >= 8).sum()) > 0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_layouts_against_a_brute_force(seed):
    """Random triangles over 50 vertices, each vertex given 1-3 coordinates: one vertex per
    distinct pair, the kept one the first corner's, appended ones in the order of their first
    corner, only the corners on a further coordinate rewritten; every other attribute follows
    ``source`` (a vertex's position, normal, joints and a morph target's delta stay the corner's)."""
    rng = np.random.default_rng(seed)
    vertices = 50
    choices = rng.uniform(0, 1, (vertices, 3, 2)).astype(np.float32)
    indices = rng.integers(0, vertices - 5, (200, 3))  # the last five vertices unread
    pick = rng.integers(0, rng.integers(1, 4, vertices)[indices])
    corner_uv = choices[indices, pick]
    out = second_uv_set(indices, corner_uv, vertices)
    brute = _brute(indices, corner_uv)
    assert len(out.source) == vertices + sum(len(c) - 1 for c in brute.values())
    for v, coords in brute.items():
        assert tuple(out.uv[v].tolist()) == coords[0]  # kept: the first corner's coordinate
    appended = [(v, c) for v, c in ((out.source[i], tuple(out.uv[i].tolist())) for i in range(vertices, len(out.source)))]
    order = []
    for v, (a, b) in zip(indices.reshape(-1).tolist(), corner_uv.reshape(-1, 2).tolist(), strict=True):
        if (a, b) != brute[v][0] and (v, (a, b)) not in order:
            order.append((v, (a, b)))
    assert appended == order
    np.testing.assert_array_equal(out.uv[out.indices], corner_uv)
    same = (corner_uv == out.uv[indices]).all(-1)  # corners on the vertex's kept coordinate
    np.testing.assert_array_equal(out.indices[same], indices[same])
    assert (out.indices[~same] >= vertices).all() and out.rewritten == int((~same).sum())
    attrs = {
        "POSITION": rng.normal(size=(vertices, 3)),
        "JOINTS_0": rng.integers(0, 9, (vertices, 4)),
        "target0:POSITION": rng.normal(size=(vertices, 3)),
    }
    for name, a in attrs.items():
        np.testing.assert_array_equal(a[out.source][out.indices], a[indices], err_msg=name)
    np.testing.assert_array_equal(out.uv[vertices - 5 : vertices], np.zeros((5, 2)))  # unread: zeros


def test_signed_zeros_degenerate_triangles_and_empty_input():
    """-0 and 0 are one coordinate; a triangle whose three corners are one vertex with three
    coordinates splits it twice; no triangles, no change."""
    idx = np.array([[0, 1, 2], [0, 1, 3]])
    uv = np.array([[[0.0, 0.5], [1, 1], [0, 1]], [[-0.0, 0.5], [1, 1], [0, 0]]], np.float32)
    assert second_uv_set(idx, uv, 4).appended == 0
    out = second_uv_set(np.array([[2, 2, 2]]), np.array([[[0, 0], [1, 0], [0, 1]]], np.float32), 3)
    assert out.appended == 2 and out.indices.tolist() == [[2, 3, 4]] and out.source.tolist() == [0, 1, 2, 2, 2]
    empty = second_uv_set(np.zeros((0, 3), np.int64), np.zeros((0, 3, 2), np.float32), 4)
    assert empty.appended == 0 and empty.uv.shape == (4, 2) and empty.indices.shape == (0, 3)


def test_bad_input_says_what_is_wrong():
    good = np.zeros((1, 3, 2), np.float32)
    with pytest.raises(ValueError, match="want"):
        second_uv_set(np.array([[0, 1, 2]]), np.zeros((1, 3, 3)), 3)
    with pytest.raises(ValueError, match="outside the 3 vertices"):
        second_uv_set(np.array([[0, 1, 3]]), good, 3)
    bad = good.copy()
    bad[0, 1, 0] = np.nan
    with pytest.raises(ValueError, match="1 corners have a UV that is not finite"):
        second_uv_set(np.array([[0, 1, 2]]), bad, 3)
