"""Visibility of a fixed direction set from points on the mesh, traced once with Embree and stored
as bits: what casts the mesh's shadows on itself (issue 32; the shading that reads it is
:mod:`stages.render.visibility`).

Layout: for ``N`` points and a set of ``D`` unit directions (:func:`fibonacci_directions`, ``D`` a
multiple of 8), ``visible (N, D / 8) uint8``, numpy's :func:`numpy.packbits` of one bit per direction
in big-endian bit order: bit ``d`` is 1 when the ray from the point (moved off the surface along
its normal by ``offset``) in direction ``d`` leaves the mesh, and 0 when the mesh blocks it or when
``d`` lies below the point's surface (``n . d <= 0``: the surface itself blocks it, and the
shading's clamped cosine gives it no weight). At 512 directions that is 64 bytes per point.

The normal is oriented towards the side the point is seen from (a point inside an open vase sees
the inside's hemisphere), so the same face carries two visibilities when it is seen from both
sides; the caller decides which (:func:`viewer_side_normals`).
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..core.threads import cpu_threads
from .tracing import RAYS_PER_THREAD

#: rays per Embree call: bounds the working memory (about 100 bytes per ray) whatever N x D is,
#: and keeps one call's rays and results in a core's cache (a batch of 2^20 rays traced at half
#: the rate of one of 2^16: ``benchmarks/geometry/raycache.py``)
RAYS_PER_BATCH = 1 << 16


def fibonacci_directions(count: int) -> np.ndarray:
    """``count`` nearly uniform unit directions ``(count, 3) float64`` on a Fibonacci spiral
    (z from ``1 - 1/count`` to ``-1 + 1/count``, each owning ``4 pi / count`` sr). ``count`` >= 8, a
    multiple of 8 (whole bytes when packed)."""
    if count < 8 or count % 8:
        raise ValueError(f"the direction count must be a multiple of 8, at least 8; got {count}")
    i = np.arange(count, dtype=np.float64) + 0.5
    z = 1.0 - 2.0 * i / count
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, 1.0))
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def direction_spacing(count: int) -> float:
    """The angular spacing of :func:`fibonacci_directions`: ``sqrt(4 pi / count)`` radians (the
    side of a square of each direction's solid angle)."""
    return math.sqrt(4.0 * math.pi / count)


def viewer_side_normals(normals: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """Unit face ``normals (N, 3)`` turned to the side the ``rays (N, 3)`` (eye -> surface) came
    from: ``-n`` where ``n . ray > 0``."""
    flip = np.einsum("ij,ij->i", normals, rays) > 0.0
    return np.where(flip[:, None], -normals, normals)


def surface_offset(vertices: np.ndarray) -> float:
    """How far a shadow ray starts off the surface: 1e-4 of the mesh's bounding-box diagonal,
    about 800 float32 ulps at the unit sphere and far below any feature the cache resolves."""
    extent = np.ptp(np.asarray(vertices, np.float64), axis=0)
    return 1e-4 * float(np.linalg.norm(extent))


def trace_visibility(tracer, points: np.ndarray, normals: np.ndarray, directions: np.ndarray, offset: float) -> np.ndarray:
    """Visibility bits ``(N, ceil(D / 8)) uint8`` (the module's layout) of ``directions (D, 3)`` from
    ``points (N, 3)`` with oriented unit ``normals (N, 3)``, through ``tracer`` (an
    :class:`~stages.geometry.tracing.EmbreeTracer` of the mesh). Only the directions above each
    point's surface are traced (any-hit queries: :meth:`~stages.geometry.tracing.EmbreeTracer.occluded`),
    in batches of about :data:`RAYS_PER_BATCH` rays, each batch whole (its set-up, its rays and its
    bits) on one of :func:`~stages.core.threads.cpu_threads` threads where the tracer takes queries
    from several (Embree does; each ray is traced on its own, so the bits do not depend on the
    split)."""
    points = np.asarray(points, np.float64)
    normals = np.asarray(normals, np.float64)
    directions = np.asarray(directions, np.float64)
    n, d = len(points), len(directions)
    out = np.zeros((n, (d + 7) // 8), np.uint8)
    # threads where the tracer takes concurrent queries and the rays are worth them (as the
    # tracer's own split: a thread per RAYS_PER_THREAD rays at least)
    workers = min(cpu_threads(), max(1, n * d // RAYS_PER_THREAD)) if getattr(tracer, "concurrent", False) else 1
    per_batch = max(1, min(RAYS_PER_BATCH // d, math.ceil(n / workers)))
    # the rays' origins and directions as the tracer takes them (float32), made once per point and
    # direction rather than once per ray
    starts = (points + offset * normals).astype(np.float32)
    dirs32 = directions.astype(np.float32)

    def batch(lo: int) -> None:
        hi = min(n, lo + per_batch)
        above = normals[lo:hi] @ directions.T > 0.0  # (B, D)
        origins = np.repeat(starts[lo:hi], above.sum(1), axis=0)  # row-major, as the mask's True entries
        blocked = tracer.occluded(origins, np.take(dirs32, np.nonzero(above)[1], axis=0), threads=1)
        above[above] = ~blocked
        out[lo:hi] = np.packbits(above, axis=1)

    if workers == 1 or per_batch >= n:
        for lo in range(0, n, per_batch):
            batch(lo)
    else:
        with ThreadPoolExecutor(workers) as pool:
            list(pool.map(batch, range(0, n, per_batch)))
    return out


def unpack_visibility(bits: np.ndarray, count: int) -> np.ndarray:
    """``bits (N, D / 8) uint8`` -> ``(N, D) bool`` (1: visible)."""
    return np.unpackbits(bits, axis=1, count=count).astype(bool)


def blocked_share(bits: np.ndarray, normals: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Per point, the share of its hemisphere (the directions above its surface, each weighing the
    same solid angle) that the mesh blocks -> ``(N,) float64`` in [0, 1]: 0 on a convex mesh, 1
    inside a closed box."""
    visible = unpack_visibility(bits, len(directions))
    above = np.asarray(normals, np.float64) @ np.asarray(directions, np.float64).T > 0.0
    count = above.sum(1)
    return 1.0 - (visible & above).sum(1) / np.maximum(count, 1)


def self_occlusion(shares: np.ndarray, weights: np.ndarray | None = None) -> dict[str, float]:
    """The mesh's self-occlusion from per-point ``shares`` (:func:`blocked_share`), optionally
    weighted (by the surface each point stands for): the mean, median and 95th percentile."""
    shares = np.asarray(shares, np.float64)
    w = np.ones_like(shares) if weights is None else np.asarray(weights, np.float64)
    order = np.argsort(shares)
    cum = np.cumsum(w[order]) / w.sum()

    def quantile(q: float) -> float:
        return float(shares[order][min(np.searchsorted(cum, q), len(shares) - 1)])

    return {"mean": float((shares * w).sum() / w.sum()), "median": quantile(0.5), "p95": quantile(0.95)}


def sample_lobe_directions(axis: np.ndarray, sharpness: float, count: int, seed: int) -> np.ndarray:
    """``count`` directions ``(count, 3) float64`` drawn from the SG lobe ``exp(lam (axis . d - 1))``
    (a von Mises-Fisher distribution), seeded: the cosine to the axis by inverting its CDF,
    ``1 + log1p((1 - u) expm1(-2 lam)) / lam`` (exact for ``lam`` 1e-4 to 1e5), the azimuth
    uniform. The shadow rays of a lobe too sharp for the direction set (a sun)."""
    rng = np.random.default_rng(seed)
    u, phi = rng.random(count), rng.random(count) * 2.0 * math.pi
    lam = float(sharpness)
    cos = np.clip(1.0 + np.log1p((1.0 - u) * np.expm1(-2.0 * lam)) / lam, -1.0, 1.0)
    sin = np.sqrt(np.clip(1.0 - cos * cos, 0.0, 1.0))
    z = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return (sin * np.cos(phi))[:, None] * x + (sin * np.sin(phi))[:, None] * y + cos[:, None] * z


def trace_lobe_visibility(tracer, points: np.ndarray, normals: np.ndarray, directions: np.ndarray, offset: float) -> np.ndarray:
    """A lobe's visible share at each point from shadow rays along ``directions (S, 3)`` drawn from
    it (:func:`sample_lobe_directions`): ``sum_s v_s max(n . d_s, 0) / sum_s max(n . d_s, 0)`` ->
    ``(N,) float32`` (the quadrature's ratio with the lobe's own samples; 1 where every sample lies
    below the surface, where the lobe lights nothing)."""
    bits = trace_visibility(tracer, points, normals, directions, offset)
    visible = unpack_visibility(bits, len(directions))
    cos = np.clip(np.asarray(normals, np.float64) @ np.asarray(directions, np.float64).T, 0.0, None)
    whole = cos.sum(1)
    return np.where(whole > 0, (cos * visible).sum(1) / np.maximum(whole, 1e-300), 1.0).astype(np.float32)


def sample_surface(mesh, count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points drawn uniformly by area over ``mesh`` (seeded): ``points (count, 3) float64``
    and the ``face (count,) int64`` each lies on. The mesh must have a positive area."""
    rng = np.random.default_rng(seed)
    areas = mesh.face_areas
    face = rng.choice(len(areas), size=count, p=areas / areas.sum())
    u, v = rng.random((2, count))
    flip = u + v > 1.0
    u, v = np.where(flip, 1.0 - u, u), np.where(flip, 1.0 - v, v)
    tri = mesh.vertices[mesh.faces[face]]
    return tri[:, 0] + u[:, None] * (tri[:, 1] - tri[:, 0]) + v[:, None] * (tri[:, 2] - tri[:, 0]), face.astype(np.int64)


def ambient_occlusion(bits: np.ndarray, normals: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Ambient occlusion as glTF's ``occlusionTexture`` and UsdPreviewSurface's ``occlusion`` mean
    it, per point: the cosine-weighted visible share of the hemisphere about ``normals (N, 3)``,
    ``(1/pi) int V(w) max(n . w, 0) dw``, by quadrature over the stored ``directions (D, 3)`` (each
    the same solid angle): ``sum_d v_d max(n . d, 0) / sum_d max(n . d, 0)`` -> ``(N,) float64`` in
    [0, 1]. Exactly 1 where nothing blocks; 0 where everything does. The quadrature's error is that
    of the direction set (about ``direction_spacing`` on a shadow edge's share)."""
    visible = unpack_visibility(bits, len(directions))
    cos = np.clip(np.asarray(normals, np.float64) @ np.asarray(directions, np.float64).T, 0.0, None)
    whole = cos.sum(1)
    return np.where(whole > 0, (cos * visible).sum(1) / np.maximum(whole, 1e-300), 1.0)


class OcclusionSamples:
    """Ambient occlusion (:func:`ambient_occlusion`) of a whole mesh, traced at ``count`` points
    drawn by area (:func:`sample_surface`) and read anywhere on the surface by interpolation: the
    bake's occlusion map (issue 32).

    A face has one texel for both its sides, so each sample keeps its more open side's occlusion
    (the outside of a closed mesh, whose inside sees nothing; the outer side of an open sheet).
    :meth:`at` blends the ``neighbours`` nearest samples with Gaussian weights of width the
    samples' spacing ``sqrt(area / count)``, only those on faces within 60 degrees of the query's
    face normal (so neither the far wall of a thin part nor the other face of a sharp crease
    bleeds in); where none is, the nearest sample."""

    def __init__(self, mesh, tracer, directions: np.ndarray, count: int, seed: int = 0, neighbours: int = 8) -> None:
        from scipy.spatial import cKDTree

        points, face = sample_surface(mesh, count, seed)
        normals = mesh.face_normals[face]
        offset = surface_offset(mesh.vertices)
        sides = [trace_visibility(tracer, points, n, directions, offset) for n in (normals, -normals)]
        self.values = np.maximum(*(ambient_occlusion(b, n, directions) for b, n in zip(sides, (normals, -normals), strict=True)))
        self.normals = normals
        self.spacing = float(np.sqrt(mesh.face_areas.sum() / count))
        self.neighbours = min(int(neighbours), count)
        self.tree = cKDTree(points)
        self.directions = len(directions)

    def summary(self) -> dict:
        """What was traced and what it found: ``samples``, ``directions``, ``spacing`` and the
        samples' occlusion ``mean``, ``median`` and ``p05`` (its 5th percentile: the dark corners)."""
        v = self.values
        return {
            "samples": int(len(v)),
            "directions": self.directions,
            "spacing": self.spacing,
            "mean": float(v.mean()),
            "median": float(np.median(v)),
            "p05": float(np.percentile(v, 5)),
        }

    def at(self, points: np.ndarray, face_normals: np.ndarray) -> np.ndarray:
        """The occlusion at ``points (M, 3)`` on faces with unit ``face_normals (M, 3)`` -> ``(M,)``."""
        dist, idx = self.tree.query(np.asarray(points, np.float64), k=self.neighbours)
        dist, idx = dist.reshape(len(points), -1), idx.reshape(len(points), -1)
        agree = np.einsum("mkj,mj->mk", self.normals[idx], np.asarray(face_normals, np.float64)) > 0.5
        w = np.exp(-((dist / self.spacing) ** 2)) * agree
        whole = w.sum(1)
        blended = (w * self.values[idx]).sum(1) / np.maximum(whole, 1e-300)
        return np.where(whole > 1e-12, blended, self.values[idx[:, 0]])


#: surface samples and directions of :func:`measure_self_occlusion`: 20,000 points put the median's
#: and the 95th percentile's sampling error near 0.005, and 256 directions (128 above a point)
#: resolve a blocked share to 1/128; about 5 M rays, a second or two with Embree
SELF_OCCLUSION_POINTS = 20_000
SELF_OCCLUSION_DIRECTIONS = 256


def measure_self_occlusion(mesh, tracer, seed: int = 0) -> dict:
    """The mesh's self-occlusion over its surface: :data:`SELF_OCCLUSION_POINTS` points drawn
    uniformly by area (seeded), each side of each taken as a point of its own, and the sides from
    which no direction escapes left out (the inside of a closed mesh, which no viewer sees); per
    side the share of its hemisphere blocked (:func:`blocked_share`). Returns the mean, median and
    95th percentile, and the share of sides seen (1 for an open sheet, 0.5 for a closed mesh)."""
    if not mesh.face_areas.sum() > 0:
        return {"mean": 0.0, "median": 0.0, "p95": 0.0, "sides_seen": 0.0, "points": 0}
    points, face = sample_surface(mesh, SELF_OCCLUSION_POINTS, seed)
    normals = mesh.face_normals[face]
    points, normals = np.concatenate([points, points]), np.concatenate([normals, -normals])
    directions = fibonacci_directions(SELF_OCCLUSION_DIRECTIONS)
    share = blocked_share(
        trace_visibility(tracer, points, normals, directions, surface_offset(mesh.vertices)), normals, directions
    )
    seen = share < 1.0
    stats = self_occlusion(share[seen]) if seen.any() else {"mean": 1.0, "median": 1.0, "p95": 1.0}
    return {**stats, "sides_seen": float(seen.mean()), "points": int(seen.sum())}
