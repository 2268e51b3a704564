"""A second UV set beside the input's own: the vertices a new per-corner layout needs.

A glTF primitive stores one texture coordinate per vertex and set (``TEXCOORD_0``,
``TEXCOORD_1``, ...; glTF 2.0 specification, section 3.7.2.1, "Meshes: Overview"; a texture
reads one set by its ``texCoord``, section 5.33, "textureInfo"). A layout made for baking gives
each triangle corner its own coordinate, and where a vertex's corners lie on different sides of
one of the new layout's seams it needs one vertex per side. :func:`second_uv_set` adds exactly
those: every input vertex keeps its index (so the input's indices, skins, morph targets and every
other attribute stay as they are for it), each further side of a seam is a new vertex appended
after the input's, copying the attributes of the vertex it splits (``source``), and only the
corners that lie on such a further side have their index rewritten.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SecondUvSet:
    """The vertices of a second UV set (:func:`second_uv_set`): ``indices`` the triangles' vertex
    indices (the input's shape, int64), ``uv (V + A, 2) float32`` the new set's coordinate of every
    vertex (zeros where no triangle reads a vertex), ``source (V + A,)`` the input vertex each
    vertex copies its other attributes from (the first ``V`` are ``0 .. V - 1``) and ``appended``
    the count ``A`` of vertices added after the input's."""

    indices: np.ndarray
    uv: np.ndarray
    source: np.ndarray
    appended: int

    @property
    def rewritten(self) -> int:
        """The corners whose index changed (each now reads an appended vertex)."""
        return int((self.indices >= len(self.source) - self.appended).sum())


def second_uv_set(indices: np.ndarray, corner_uv: np.ndarray, vertices: int) -> SecondUvSet:
    """The fewest vertices that give each corner of ``indices (..., 3)`` (into ``vertices`` input
    vertices) its coordinate of ``corner_uv (..., 3, 2)`` (float32; equal corners of one vertex are
    the same coordinate bit for bit, -0 as 0): one vertex per distinct (vertex, coordinate) pair.
    A vertex keeps the coordinate its first corner (in triangle order) has, and its index; each
    other coordinate of it is a vertex appended after the input's, in the order of its first
    corner. Exact: ``uv[out.indices] == corner_uv`` and ``source[out.indices] == indices``.

    Raises:
        ValueError: shapes that do not match, an index outside ``0 .. vertices - 1``, or a
            coordinate that is not finite."""
    idx = np.asarray(indices)
    uv = np.asarray(corner_uv, np.float32)
    if idx.ndim < 1 or idx.shape[-1] != 3 or uv.shape != (*idx.shape, 2):
        raise ValueError(f"indices {idx.shape} and corner UVs {uv.shape}: want (..., 3) and (..., 3, 2)")
    flat = idx.reshape(-1).astype(np.int64)
    if len(flat) and (flat.min() < 0 or flat.max() >= vertices):
        raise ValueError(f"vertex indices {flat.min()}..{flat.max()} outside the {vertices:,} vertices")
    coords = uv.reshape(-1, 2) + np.float32(0.0)  # -0 as 0
    if not np.isfinite(coords).all():
        raise ValueError(f"{int((~np.isfinite(coords)).any(axis=1).sum()):,} corners have a UV that is not finite")
    bits = coords.view(np.uint32).astype(np.int64)
    keys = np.stack([flat, bits[:, 0], bits[:, 1]], axis=1)
    pairs, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    by_vertex = np.lexsort((first, pairs[:, 0]))  # each vertex's pairs in the order of their first corner
    vertex = pairs[by_vertex, 0]
    keeps = np.empty(len(pairs), bool)
    keeps[by_vertex] = np.r_[True, vertex[1:] != vertex[:-1]] if len(pairs) else np.zeros(0, bool)
    extra = np.flatnonzero(~keeps)
    extra = extra[np.argsort(first[extra], kind="stable")]
    number = np.empty(len(pairs), np.int64)
    number[keeps] = pairs[keeps, 0]
    number[extra] = vertices + np.arange(len(extra))
    source = np.concatenate([np.arange(vertices, dtype=np.int64), pairs[extra, 0]])
    out_uv = np.zeros((len(source), 2), np.float32)
    out_uv[number] = coords[first]
    return SecondUvSet(number[inverse].reshape(idx.shape), out_uv, source, len(extra))


__all__ = ["SecondUvSet", "second_uv_set"]
