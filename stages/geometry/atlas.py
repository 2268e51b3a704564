"""Texture atlases: xatlas charts, the atlas rasterised in UV space (face and barycentrics per
texel), per-face tangent frames, dilation of filled texels, and bilinear lookups.

Conventions. Image row 0 is the top; texel ``(row, col)`` has centre ``u = (col + 0.5) / S``,
``v = (row + 0.5) / S`` (glTF's texture coordinates). USD's ``st = (u, 1 - v)``. The tangent
frame is per face, computed from positions and ``st`` (``T = dP/ds``, ``B = dP/dt``),
Gram-Schmidt-orthonormalised against the flat face normal, with handedness
``w = sign((N x T) . B)`` and bitangent ``w (N x T)``: the frame that MikkTSpace produces on a mesh
whose faces do not share vertices.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .meshio import TriMesh
from .tracing import EmbreeTracer


@dataclass
class Atlas:
    """``uv (F, 3, 2)`` per-corner texture coordinates (glTF convention), ``size`` in texels."""

    uv: np.ndarray
    size: int
    charts: int
    utilization: float


def unwrap(mesh: TriMesh, size: int, padding: int, max_chart_share: float | None = None) -> Atlas:
    """xatlas parametrisation packed for a ``size x size`` texture. ``max_chart_share`` bounds
    each chart's area to that share of the surface (xatlas's ``max_chart_area``); ``None``:
    xatlas's unbounded charts. Bounded charts are far cheaper to parametrise and pack on
    large smooth meshes, at the price of more seams (measured in ``benchmarks/assets/bake_charts.py``)."""
    try:
        import xatlas
    except ImportError as exc:  # pragma: no cover
        raise ImportError("the bake stage needs xatlas: pip install xatlas") from exc
    atlas = xatlas.Atlas()
    atlas.add_mesh(mesh.vertices.astype(np.float32), mesh.faces.astype(np.uint32))
    pack = xatlas.PackOptions()
    pack.resolution = size
    pack.padding = padding
    pack.bilinear = True
    charts = xatlas.ChartOptions()
    if max_chart_share is not None:
        charts.max_chart_area = float(max_chart_share * mesh.face_areas.sum())
    atlas.generate(charts, pack)
    vmapping, indices, uvs = atlas[0]
    if not np.array_equal(vmapping[indices], mesh.faces):
        raise RuntimeError("xatlas changed the face order; cannot map faces to the atlas")
    # xatlas packs into its own width x height; rescale to the square texture
    uv = uvs[indices].astype(np.float64)
    scale = max(atlas.width, atlas.height)
    uv = uv * np.array([atlas.width, atlas.height]) / scale
    return Atlas(uv, size, int(atlas.chart_count), float(atlas.utilization))


def rasterize_atlas(uv: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Face id ``(S, S) int32`` (-1 = empty) and barycentrics ``(S, S, 2) float32`` (Embree's
    ``(u, v)``: point = (1-u-v) p0 + u p1 + v p2) of every texel centre, by casting one ray per
    texel at the UV-space triangles."""
    tri2d = np.concatenate([uv * size, np.zeros(uv.shape[:2] + (1,))], axis=-1)  # (F, 3, 3)
    flat = TriMesh(tri2d.reshape(-1, 3), np.arange(3 * len(uv)).reshape(-1, 3))
    tracer = EmbreeTracer(flat)
    c = np.arange(size) + 0.5
    cols, rows = np.meshgrid(c, c)  # texel (row, col) -> (u, v) = (col, row) / S
    origins = np.stack([cols.ravel(), rows.ravel(), np.ones(size * size)], axis=1)
    dirs = np.broadcast_to(np.array([0.0, 0.0, -1.0]), origins.shape)
    hits = tracer.trace(origins, dirs)
    return hits.face.reshape(size, size), hits.bary.reshape(size, size, 2)


def dilate(values: np.ndarray, filled: np.ndarray, passes: int) -> np.ndarray:
    """Grow ``values (S, S, C)`` from ``filled (S, S) bool`` texels into empty neighbours
    (8-neighbourhood mean), ``passes`` times; remaining empty texels take the filled mean."""
    v = values.copy()
    f = filled.copy()
    for _ in range(passes):
        acc = np.zeros_like(v)
        cnt = np.zeros(f.shape, np.float64)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                if dy == dx == 0:
                    continue
                sv = np.roll(np.roll(v, dy, 0), dx, 1)
                sf = np.roll(np.roll(f, dy, 0), dx, 1)
                acc += sv * sf[..., None]
                cnt += sf
        grow = ~f & (cnt > 0)
        if not grow.any():
            break
        v[grow] = acc[grow] / cnt[grow][:, None]
        f |= grow
    if (~f).any() and filled.any():
        v[~f] = values[filled].mean(0)
    return v


def sample_bilinear(img: np.ndarray, uv: np.ndarray, wrap: bool = False) -> np.ndarray:
    """Bilinear lookup of ``img (S, S, C)`` at glTF-convention ``uv (N, 2)``: clamped at the edges
    (glTF's ``CLAMP_TO_EDGE``), or with ``wrap`` repeating (glTF's default ``REPEAT``)."""
    s = img.shape[0]
    if wrap:
        x = np.mod(uv[:, 0] * s - 0.5, s)
        y = np.mod(uv[:, 1] * s - 0.5, s)
        x0, y0 = np.floor(x).astype(int) % s, np.floor(y).astype(int) % s
        x1, y1 = (x0 + 1) % s, (y0 + 1) % s
    else:
        x = np.clip(uv[:, 0] * s - 0.5, 0, s - 1)
        y = np.clip(uv[:, 1] * s - 0.5, 0, s - 1)
        x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
        x1, y1 = np.minimum(x0 + 1, s - 1), np.minimum(y0 + 1, s - 1)
    fx, fy = (x - np.floor(x))[:, None], (y - np.floor(y))[:, None]
    im = img.astype(np.float64)
    return im[y0, x0] * (1 - fx) * (1 - fy) + im[y0, x1] * fx * (1 - fy) + im[y1, x0] * (1 - fx) * fy + im[y1, x1] * fx * fy
