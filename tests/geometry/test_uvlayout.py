"""The input's own surface read back (OBJ and glTF) and its UV layout measured: against arrays written
by hand, brute-force coverage counts and a rotation library's matrices."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stages.core.errors import StageInputError
from stages.geometry.atlas import sample_bilinear
from stages.geometry.meshio import TriMesh, load_mesh
from stages.geometry.sourcemesh import node_matrix, read_source
from stages.geometry.uvlayout import (
    CENTRE_JITTER,
    TILE_MARGIN,
    check_layout,
    face_tiles,
    match_faces,
    overlap_faces,
    seams_and_islands,
)

OBJ = """# two quads sharing an edge, a seam between them, and a triangle without texture coordinates
mtllib lost.mtl
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
v 2 0 0
v 2 1 0
vt 0 0
vt 0.5 0
vt 0.5 1
vt 0 1
vt 0.6 0
vt 1 0
vt 1 1
vt 0.6 1
vn 0 0 1
usemtl Wood
f 1/1/1 2/2/1 3/3/1 4/4/1
usemtl Metal
f -5/5/1 -2/6/1 -1/7/1 -4/8/1
f 1 2 \\
4
"""


def write(tmp_path: Path, text: str, name: str = "m.obj") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_obj_corners_become_vertices_in_first_use_order(tmp_path):
    s = read_source(write(tmp_path, OBJ))
    # distinct (v, vt, vn) corners in the order the faces first use them; the last face has no vt/vn
    want_keys = [
        (0, 0, 0),
        (1, 1, 0),
        (2, 2, 0),
        (3, 3, 0),
        (1, 4, 0),
        (4, 5, 0),
        (5, 6, 0),
        (2, 7, 0),
        (0, -1, -1),
        (1, -1, -1),
        (3, -1, -1),
    ]
    positions = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0], [2, 1, 0]], float)
    np.testing.assert_array_equal(s.positions, positions[[k[0] for k in want_keys]])
    # fans (0, i, i + 1) of each polygon, in file order
    np.testing.assert_array_equal(s.triangles, [[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7], [8, 9, 10]])
    assert s.slot_names == ("Wood", "Metal") and s.slot.tolist() == [0, 0, 1, 1, 1]
    # glTF's v is 1 - the OBJ's
    np.testing.assert_allclose(s.uv[2], [0.5, 0.0])
    np.testing.assert_allclose(s.uv[7], [0.6, 0.0])
    assert np.isnan(s.uv[8:]).all() and s.mapped.tolist() == [True, True, True, True, False]
    np.testing.assert_allclose(s.normals[:8], np.tile([0.0, 0.0, 1.0], (8, 1)))
    assert np.isnan(s.normals[8:]).all()
    # where the file has no normal, an OBJ's consumers smooth: here the flat +z of its faces
    np.testing.assert_allclose(s.corner_normals()[4], np.tile([0.0, 0.0, 1.0], (3, 1)))


def test_obj_the_traced_reader_sees_the_same_triangles(tmp_path):
    path = write(tmp_path, OBJ)
    s, m = read_source(path), load_mesh(path)
    assert (match_faces(s.positions[s.triangles], m) >= 0).all()


@pytest.mark.parametrize(
    ("line", "words"),
    [("f 1/1/1 2/1/1", "3 or more corners"), ("f 1/1/1 2/2/1 9/1/1", "does not exist"), ("v 1 x 0", "could not convert")],
)
def test_obj_bad_lines_name_the_line(tmp_path, line, words):
    text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvn 0 0 1\n" + line + "\n"
    with pytest.raises(StageInputError, match=f"line 6 .*{words}"):
        read_source(write(tmp_path, text))


def test_other_formats_hold_no_layout(tmp_path):
    with pytest.raises(StageInputError, match="no UV layout"):
        read_source(write(tmp_path, "ply\n", "m.ply"))


def test_gltf_node_transforms_against_a_rotation_library():
    class Node:
        matrix = None
        translation = [1.0, -2.0, 3.0]
        rotation = list(Rotation.from_euler("xyz", [0.3, -1.1, 2.0]).as_quat())  # (x, y, z, w), glTF's order
        scale = [2.0, 0.5, -1.5]

    want = np.eye(4)
    want[:3, :3] = Rotation.from_quat(Node.rotation).as_matrix() @ np.diag(Node.scale)
    want[:3, 3] = Node.translation
    np.testing.assert_allclose(node_matrix(Node()), want, atol=1e-12)

    class Matrix:
        matrix = list(np.arange(16.0))  # column-major
        translation = rotation = scale = None

    np.testing.assert_array_equal(node_matrix(Matrix()), np.arange(16.0).reshape(4, 4).T)


def test_gltf_skinned_document_read_as_written(tmp_path):
    import uvmeshes

    info = uvmeshes.skinned_glb(tmp_path / "skin.glb")
    s = read_source(tmp_path / "skin.glb")
    # two primitives share one vertex set: one block of vertices, both primitives' triangles into it
    n = len(info["positions"])
    assert len(s.positions) == n
    np.testing.assert_array_equal(s.positions, info["positions"])
    np.testing.assert_allclose(s.uv, info["uv"], atol=1e-7)
    assert s.slot_names == ("Body", "Rim") and len(s.parts) == 2
    assert sorted(map(tuple, np.sort(s.triangles, axis=1))) == sorted(map(tuple, np.sort(info["faces"], axis=1)))
    m = load_mesh(tmp_path / "skin.glb")
    assert (match_faces(s.positions[s.triangles], m) >= 0).all()


# ------------------------------------------------------------------------------- layout measures
def quad(u0: float, v0: float, size: float = 0.25) -> np.ndarray:
    """Two UV triangles of a square at (u0, v0)."""
    a, b, c, d = (u0, v0), (u0 + size, v0), (u0 + size, v0 + size), (u0, v0 + size)
    return np.array([[a, b, c], [a, c, d]], float)


def grid_positions(n_quads: int) -> tuple[np.ndarray, np.ndarray]:
    """``n_quads`` unit squares side by side in 3D, faces not shared (each quad its own corners)."""
    pos, faces = [], []
    for k in range(n_quads):
        base = len(pos)
        pos += [(k, 0, 0), (k + 1, 0, 0), (k + 1, 1, 0), (k, 1, 0)]
        faces += [(base, base + 1, base + 2), (base, base + 2, base + 3)]
    return np.array(pos, float), np.array(faces)


def covered_by_brute_force(uv: np.ndarray, size: int) -> np.ndarray:
    """Per face: whether one of its texel centres lies strictly inside another face (barycentric
    coordinates from the textbook formula)."""
    c = np.arange(size) + 0.5
    u, v = np.meshgrid(c + CENTRE_JITTER[0], c + CENTRE_JITTER[1])
    p = np.stack([u.ravel(), v.ravel()], 1) / size
    inside = []
    for t in uv:
        a, b, cc = t
        den = (b[1] - cc[1]) * (a[0] - cc[0]) + (cc[0] - b[0]) * (a[1] - cc[1])
        l1 = ((b[1] - cc[1]) * (p[:, 0] - cc[0]) + (cc[0] - b[0]) * (p[:, 1] - cc[1])) / den
        l2 = ((cc[1] - a[1]) * (p[:, 0] - cc[0]) + (a[0] - cc[0]) * (p[:, 1] - cc[1])) / den
        inside.append((l1 > 1e-9) & (l2 > 1e-9) & (1 - l1 - l2 > 1e-9))
    inside = np.array(inside)
    count = inside.sum(0)
    return (inside & (count >= 2)).any(axis=1)


def test_overlap_found_as_brute_force_finds_it():
    rng = np.random.default_rng(3)
    uv = rng.uniform(0.05, 0.95, size=(40, 3, 2))
    got = overlap_faces(uv, 64)
    want = covered_by_brute_force(uv, 64)
    np.testing.assert_array_equal(got, want)
    assert want.any() and not want.all()  # the test can tell


def test_stacked_and_mirrored_islands_are_not_overlap():
    pos, faces = grid_positions(3)
    uv = np.concatenate([quad(0.1, 0.1), quad(0.1, 0.1), quad(0.6, 0.6)])
    uv[2:4] = uv[2:4][:, ::-1]  # the same triangles, mirrored (corners reversed)
    c = check_layout(pos, faces, uv, 128)
    assert (c.stacked, c.overlapping) == (4, 0) and c.problems(0.0) == []
    shifted = uv.copy()
    shifted[2:4] += 0.05  # a copy that only partly covers the first: overlap, not stacking
    c = check_layout(pos, faces, shifted, 128)
    assert (c.stacked, c.overlapping) == (0, 4)
    assert c.problems(0.7) == [] and "4 of the 6 faces (66.7%) overlap other faces" in c.problems(0.01)[0]


def test_unmapped_degenerate_tiles_and_outside_are_problems():
    pos, faces = grid_positions(4)
    uv = np.concatenate([quad(0.1, 0.1), quad(0.5, 0.5), quad(1.2, 0.2), quad(0.4, 0.1)])
    uv[6] = [(0.4, 0.1), (0.4, 0.1), (0.5, 0.1)]  # zero UV area, non-zero 3D area
    uv[7] = np.nan  # no texture coordinates
    c = check_layout(pos, faces, uv, 64)
    assert (c.unmapped, c.degenerate) == (1, 1)
    assert c.tiles == (1001, 1002)
    text = " | ".join(c.problems(1.0))
    assert "1 of the 8 faces (12.5%) have no texture coordinates" in text
    assert "degenerate" in text and "the UVs span 2 tiles, which a glTF sampler repeats" in text
    assert not any("tiles" in p for p in c.problems(1.0, udim=True))  # an OBJ's UDIM tiles: one texture set each
    below = uv.copy()
    below[:2] -= [1.0, 0.0]  # one tile left of the first: no UDIM tile
    assert any("UDIM tiles outside 1001-1100" in p for p in check_layout(pos, faces, below, 64).problems(1.0, udim=True))
    assert not any("1001-1100" in p for p in check_layout(pos, faces, below, 64).problems(1.0))


def test_tiles_and_the_margin_past_an_edge():
    wide = np.array([[(0.5, 0.5), (0.5 + 0.5 + 2 * TILE_MARGIN, 0.5), (0.5, 0.6)]])  # reaches past the margin
    uv = np.concatenate([quad(-0.1, 0.2), quad(0.95, 0.2, 0.1), quad(0.2, -0.3), wide])
    tiles = face_tiles(uv)
    # within the margin a face counts to the unit square; past it, to the tile of its centroid
    assert tiles.tolist() == [[0, 0]] * 4 + [[0, -1], [0, -1]] + [[0, 0]]
    pos, faces = grid_positions(4)
    c = check_layout(pos, faces[:7], uv, 64)
    assert c.outside == 1 and c.tiles == (1001, 1011)
    assert any("1 of the 7 faces (14.3%) reach more than" in p for p in c.problems(1.0))


def test_seams_and_islands_of_a_strip():
    # two quads of one strip: quad 0's right edge is quad 1's left edge in 3D
    pos = np.array([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (2, 0, 0), (2, 1, 0)], float)
    faces = np.array([(0, 1, 2), (0, 2, 3), (1, 4, 5), (1, 5, 2)])
    joined = np.concatenate([quad(0.0, 0.0), quad(0.25, 0.0)])
    assert seams_and_islands(pos, faces, joined) == (0, 1)
    split = np.concatenate([quad(0.0, 0.0), quad(0.5, 0.0)])
    assert seams_and_islands(pos, faces, split) == (1, 2)


def test_match_faces_recovers_a_shuffle():
    rng = np.random.default_rng(0)
    v = rng.normal(size=(30, 3))
    f = rng.integers(0, 30, size=(50, 3))
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    mesh = TriMesh(v, f)
    perm = rng.permutation(len(f))
    rolled = np.roll(v[f[perm]], 1, axis=1)  # corners rotated: the same triangle
    np.testing.assert_array_equal(match_faces(rolled, mesh), perm)
    moved = rolled.copy()
    moved[0] += 0.1
    got = match_faces(moved, mesh)
    assert got[0] == -1 and (got[1:] == perm[1:]).all()


def test_repeating_lookup_against_the_formula():
    rng = np.random.default_rng(1)
    img = rng.uniform(size=(8, 8, 3))
    uv = rng.uniform(-1.5, 2.5, size=(200, 2))
    got = sample_bilinear(img, uv, wrap=True)
    s = 8
    want = []
    for u, v in uv:
        x, y = u * s - 0.5, v * s - 0.5
        x0, y0 = int(np.floor(x)), int(np.floor(y))
        fx, fy = x - x0, y - y0
        texel = lambda r, c: img[r % s, c % s]  # noqa: E731 - the textbook repeat
        want.append(
            (1 - fx) * (1 - fy) * texel(y0, x0)
            + fx * (1 - fy) * texel(y0, x0 + 1)
            + (1 - fx) * fy * texel(y0 + 1, x0)
            + fx * fy * texel(y0 + 1, x0 + 1)
        )
    np.testing.assert_allclose(got, np.array(want), atol=1e-12)
    # clamping (the atlas's sampler) differs from repeating at the edges only
    inner = (uv > 0.1).all(1) & (uv < 0.9).all(1)
    np.testing.assert_allclose(sample_bilinear(img, uv[inner]), got[inner], atol=1e-12)


def test_mirrored_halves_glued_along_their_line_are_stacked_not_overlap():
    """Two halves of a symmetric strip share the UVs of their common edge (one island) and lie
    over each other mirrored, with different triangulations: two charts over the same texels,
    baked once. A third quad half over one half is a partial overlap."""
    # 3D: a strip of two squares, (0..1) and (1..2) in x; UV: both squares onto [0.2, 0.7]^2, the
    # second mirrored about the shared edge x = 1 (u = 0.7 there) and split along the other diagonal
    pos = np.array([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (2, 0, 0), (2, 1, 0)], float)
    faces = np.array([(0, 1, 2), (0, 2, 3), (1, 4, 5), (1, 5, 2)])
    lo, hi = 0.2, 0.7
    uv = np.array(
        [
            [(lo, lo), (hi, lo), (hi, hi)],
            [(lo, lo), (hi, hi), (lo, hi)],
            [(hi, lo), (lo, lo), (lo, hi)],  # the mirror: x = 2 maps back to u = lo
            [(hi, lo), (lo, hi), (hi, hi)],
        ]
    )
    c = check_layout(pos, faces, uv, 64)
    assert c.islands == 1 and (c.stacked, c.overlapping) == (4, 0)
    # half a square more, over the left half only: partial
    pos2 = np.concatenate([pos, [(5, 0, 0), (6, 0, 0), (6, 1, 0)]])
    faces2 = np.concatenate([faces, [(6, 7, 8)]])
    uv2 = np.concatenate([uv, [[(lo, lo), (0.45, lo), (0.45, 0.45)]]])
    c = check_layout(pos2, faces2, uv2, 64)
    assert c.overlapping >= 1 and c.stacked <= 4
