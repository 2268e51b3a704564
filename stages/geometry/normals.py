"""Shading normals: flat face normals, or vertex normals interpolated across each face with creases
kept (``optimize.shading_normals``).

Smooth normals are computed per face *corner*, the way Blender's "smooth by angle" and glTF
exporters split them:

1. Vertices at the same position are welded (meshes are often split at UV seams or material
   boundaries, and a seam must not show as a crease): those closer than ``WELD_TOLERANCE`` of the
   bounding-box diagonal (:func:`weld_positions`, which the decimation's welding uses too).
2. An edge shared by exactly two faces is *smooth* when the angle between their face normals is at
   most ``crease_angle_deg``; boundary edges, non-manifold edges (three or more faces) and edges
   between inconsistently oriented faces (normals at more than the crease angle) are sharp.
3. Around each vertex, the corners connected through smooth edges form one *fan*. Every corner of
   a fan gets the fan's normal: the sum of its faces' unit normals weighted by the corner angle
   (Thürmer & Wüthrich 1998, "Computing vertex normals from polygonal facets"; Blender's default)
   or by the face area (Gouraud's plain average weighted by area), normalised.

A hit's shading normal is the corner normals interpolated with its barycentrics and normalised
(Phong 1975). Degenerate faces (zero area) have a zero face normal and weight, so they change no
fan's normal; a corner or hit whose normal cancels to zero falls back to its face normal.

Crease angle 0 keeps only exactly coplanar neighbours smooth (the flat normals, up to welding);
180 smooths across every manifold edge.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config.sections import NORMAL_WEIGHTINGS, SHADING_NORMALS

#: positions closer than this fraction of the bounding-box diagonal are one vertex
WELD_TOLERANCE = 1e-7


@dataclass(frozen=True)
class NormalSpec:
    """Which shading normals to use: ``mode`` (:data:`SHADING_NORMALS`), the crease angle in degrees
    (smooth only) and the corner weighting (:data:`NORMAL_WEIGHTINGS`)."""

    mode: str = "flat"
    crease_angle_deg: float = 60.0
    weighting: str = "angle"

    def __post_init__(self) -> None:
        if self.mode not in SHADING_NORMALS:
            raise ValueError(f"shading normals must be one of {SHADING_NORMALS}, got {self.mode!r}")
        if self.weighting not in NORMAL_WEIGHTINGS:
            raise ValueError(f"normal weighting must be one of {NORMAL_WEIGHTINGS}, got {self.weighting!r}")
        if not 0.0 <= self.crease_angle_deg <= 180.0:
            raise ValueError(f"crease angle must be in [0, 180] degrees, got {self.crease_angle_deg}")

    @classmethod
    def of(cls, settings) -> NormalSpec:
        """From any settings object with ``shading_normals``, ``crease_angle_deg`` and
        ``normal_weighting`` (the optimize stage's, the field's)."""
        return cls(settings.shading_normals, settings.crease_angle_deg, settings.normal_weighting)

    def describe(self) -> str:
        if self.mode == "flat":
            return "flat face normals"
        return f"smooth vertex normals ({self.weighting}-weighted, creases above {self.crease_angle_deg:g} deg kept)"

    def corner_normals(self, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
        """``(F, 3, 3) float64`` unit normals per face corner (for ``flat``: the face normal, three
        times)."""
        if self.mode == "flat":
            return np.repeat(unit_face_normals(vertices, faces)[:, None, :], 3, axis=1)
        return smooth_corner_normals(vertices, faces, self.crease_angle_deg, self.weighting)


def unit_face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``(F, 3) float64`` unit normals by the right-hand rule; zero for degenerate faces."""
    tri = np.asarray(vertices, np.float64)[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)


def weld_positions(vertices: np.ndarray, relative_tolerance: float = WELD_TOLERANCE) -> tuple[np.ndarray, np.ndarray, int]:
    """Coincident vertices: exact duplicates, then vertices closer than ``relative_tolerance`` times
    the bounding-box diagonal (transitively, at the position of the member that comes first).
    Returns the distinct positions ``(U, 3)`` in the input's order of first use, each input
    vertex's id ``(V,) int64`` among them, and how many were exact duplicates."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    vertices = np.asarray(vertices, np.float64)
    if len(vertices) == 0:
        return vertices.reshape(0, 3), np.zeros(0, np.int64), 0
    diagonal = float(np.linalg.norm(np.ptp(vertices, axis=0)))
    tolerance = float(relative_tolerance) * diagonal
    unique, first, inverse = np.unique(vertices, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)  # keep the input's vertex order: a mesh without duplicates comes back unchanged
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    unique, inverse = unique[order], rank[inverse.reshape(-1)]
    exact_merged = len(vertices) - len(unique)
    if tolerance > 0 and len(unique) > 1:
        pairs = cKDTree(unique).query_pairs(tolerance, output_type="ndarray")
        if len(pairs):
            n = len(unique)
            graph = coo_matrix((np.ones(len(pairs), np.int8), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
            count, labels = connected_components(graph, directed=False)
            first = np.full(count, n, np.int64)
            np.minimum.at(first, labels, np.arange(n))
            unique, inverse = unique[first], labels[inverse]
    return unique, inverse.astype(np.int64), int(exact_merged)


def corner_angles(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``(F, 3)`` interior angle of each face at each corner (radians; 0 at degenerate corners)."""
    tri = np.asarray(vertices, np.float64)[faces]
    out = np.zeros(faces.shape, np.float64)
    for k in range(3):
        a = tri[:, (k + 1) % 3] - tri[:, k]
        b = tri[:, (k + 2) % 3] - tri[:, k]
        # atan2(|a x b|, a . b): accurate for tiny and nearly flat angles, 0 for a zero edge
        out[:, k] = np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), (a * b).sum(1))
    return out


def corner_groups(ids: np.ndarray, join) -> np.ndarray:
    """Group face corners around shared vertices: ``ids (F, 3)`` vertex id of each corner; two
    faces that share an edge (both end ids, in either direction; edges used by more than two
    corners' faces are never joined) and for which ``join(f1, f2)`` (vectorised, ``(E,) bool``)
    holds have their corners at each end of that edge joined. Returns ``(F, 3) int64`` group ids
    (connected components)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    ids = np.asarray(ids, np.int64)
    nf = len(ids)
    # half-edges: corner k of face f runs from ids[f, k] to ids[f, k+1]
    a = ids.reshape(-1)
    b = ids[:, [1, 2, 0]].reshape(-1)
    face_of = np.repeat(np.arange(nf), 3)
    corner_a = np.arange(3 * nf)  # corner id of the half-edge's start ...
    corner_b = (np.arange(nf)[:, None] * 3 + np.array([1, 2, 0])).reshape(-1)  # ... and of its end
    real = a != b  # a collapsed edge (two corners at one vertex) joins nothing
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    key = lo * (int(ids.max(initial=0)) + 1) + hi
    idx = np.flatnonzero(real)[np.argsort(key[real], kind="stable")]
    k_sorted = key[idx]
    starts = np.flatnonzero(np.r_[True, k_sorted[1:] != k_sorted[:-1]])
    counts = np.diff(np.r_[starts, len(idx)])
    pairs = starts[counts == 2]  # manifold edges: exactly two half-edges
    h1, h2 = idx[pairs], idx[pairs + 1]
    keep = np.asarray(join(face_of[h1], face_of[h2]), bool)
    h1, h2 = h1[keep], h2[keep]
    # the corners at each end: opposite directions (consistent winding) pair start with end
    same_dir = a[h1] == a[h2]
    rows = np.r_[corner_a[h1], corner_b[h1]]
    cols = np.r_[np.where(same_dir, corner_a[h2], corner_b[h2]), np.where(same_dir, corner_b[h2], corner_a[h2])]
    graph = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(3 * nf, 3 * nf))
    _, labels = connected_components(graph, directed=False)
    return labels.reshape(nf, 3).astype(np.int64)


def corner_fans(vertices: np.ndarray, faces: np.ndarray, crease_angle_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """The fans of the module docstring: ``fan (F, 3) int64`` (corners with equal ids share a
    normal) and the welded vertex id of each corner ``(F, 3) int64``."""
    faces = np.asarray(faces, np.int64)
    weld = weld_positions(vertices)[1][faces]
    n = unit_face_normals(vertices, faces)
    cos_crease = np.cos(np.radians(crease_angle_deg))

    def smooth(f1, f2):
        # a degenerate face has no normal to compare: its edges are smooth (it changes no fan's normal)
        degenerate = (np.abs(n[f1]).sum(1) == 0) | (np.abs(n[f2]).sum(1) == 0)
        return degenerate | ((n[f1] * n[f2]).sum(1) >= cos_crease - 1e-12)

    return corner_groups(weld, smooth), weld


def smooth_corner_normals(
    vertices: np.ndarray, faces: np.ndarray, crease_angle_deg: float, weighting: str = "angle"
) -> np.ndarray:
    """``(F, 3, 3) float64`` unit corner normals (module docstring)."""
    faces = np.asarray(faces, np.int64)
    n = unit_face_normals(vertices, faces)
    if weighting == "angle":
        w = corner_angles(vertices, faces)
    elif weighting == "area":
        tri = np.asarray(vertices, np.float64)[faces]
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        w = np.repeat(area[:, None], 3, axis=1)
    else:
        raise ValueError(f"normal weighting must be one of {NORMAL_WEIGHTINGS}, got {weighting!r}")
    fan, _ = corner_fans(vertices, faces, crease_angle_deg)
    flat_fan = fan.reshape(-1)
    contrib = (w[..., None] * n[:, None, :]).reshape(-1, 3)
    total = np.zeros((int(flat_fan.max(initial=-1)) + 1, 3))
    np.add.at(total, flat_fan, contrib)
    out = total[flat_fan].reshape(-1, 3, 3)
    return _unit_or(out, np.repeat(n[:, None, :], 3, axis=1))


def interpolate_normals(corner: np.ndarray, face: np.ndarray, bary: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """Unit shading normals ``(N, 3)`` at hits: ``corner (F, 3, 3)`` interpolated at faces
    ``face (N,)`` with Embree's ``bary (N, 2)`` (``(1-u-v) c0 + u c1 + v c2``), normalised; where
    that cancels to zero, ``fallback (N, 3)`` (the flat face normal)."""
    c = corner[face]
    u, v = bary[:, :1], bary[:, 1:2]
    mixed = (1.0 - u - v) * c[:, 0] + u * c[:, 1] + v * c[:, 2]
    return _unit_or(mixed, fallback)


def perpendicular(n: np.ndarray) -> np.ndarray:
    """An arbitrary vector ``(N, 3)`` orthogonal to each unit ``n (N, 3)`` (not normalised): +x, or
    +y where ``n`` is within about 25 degrees of the x axis, made orthogonal to ``n``. The frame of
    a face or corner whose texture derivatives are degenerate."""
    axis = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    return axis - n * (n * axis).sum(-1, keepdims=True)


def _unit_or(x: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(x, axis=-1, keepdims=True)
    tiny = norm <= 1e-12
    return np.where(tiny, fallback, x / np.where(tiny, 1.0, norm))
