"""The ray-cache format: cameras of a view set, one primary ray per pixel traced once, and the
hits kept per view (written by the raycache stage, read by every torch stage).

Cache layout (one ``.npz`` per view set, ``train`` = the sampled pool, ``eval`` = fixed grid):

========================  ===========  ========================================================
array                     dtype        meaning
========================  ===========  ========================================================
``pixel (N,)``            uint32       pixel index ``row * W + col`` of each hit, row 0 on top
``face (N,)``             int32        id of the first face hit
``bary (N, 2)``           uint16       Embree's ``(u, v)`` in units of 1/65535:
                                       hit = (1-u-v) v0 + u v1 + v v2
``offsets (V+1,)``        int64        hits of view ``i`` are ``offsets[i]:offsets[i+1]``
``c2w (V, 4, 4)``         float64      camera-to-world (OpenGL: looks along -z, +y up)
``azimuth, elevation``    float64      radians, ``(V,)`` each; ``radius (V,)``
``anchor_azimuth``,       scalars      the anchor (front) view of the experiment, radians
``anchor_elevation``
``fov_deg, width``        scalars      full field of view (degrees), image width = height
``vertices, faces``       f4, i4       the traced mesh, so points are ``bary`` on ``faces``
``face_normals (F, 3)``   float32      flat face normals (right-hand rule, not flipped)
``visibility (N, D/8)``   uint8        optional (``raycache.visibility``): per hit, the
                                       visibility bits of ``visibility_directions`` directions
                                       (:mod:`stages.geometry.visibility`), for shadows
========================  ===========  ========================================================

Per hit that is 12 bytes (4 + 4 + 2 * 2); the hit point (to 1/65535 of a triangle edge, far
below float32's resolution of the unit sphere for meshes up to millions of faces) and the flat
face normal (exactly) are recovered from the face id and barycentrics by :class:`RayCache`.
Normals are *not* flipped towards the camera: a hit on a back face (inside an open vase) has
``dot(normal, ray) > 0``, and the renderer decides what to do with it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..config.sections import RaycacheSettings
from ..core.errors import StageInputError
from ..core.safefiles import DATA_LIMIT, atomic_stream, open_read
from .cameras import (
    camera_positions,
    camera_space_directions,
    grid_views,
    look_at,
    sample_views,
    world_rays,
)
from .meshio import TriMesh
from .normals import NormalSpec, interpolate_normals
from .tracing import EmbreeTracer
from .visibility import fibonacci_directions, surface_offset, trace_visibility, viewer_side_normals

#: bytes stored per hit: pixel index (uint32), face id (int32), barycentrics (2 x uint16)
BYTES_PER_HIT = 4 + 4 + 2 * 2
BARY_SCALE = 65535.0


@dataclass
class ViewSet:
    """Cameras of one view set: ``azimuth, elevation, radius (V,)`` float64, scalars fov/width and
    the anchor direction."""

    azimuth: np.ndarray
    elevation: np.ndarray
    radius: np.ndarray
    fov_deg: float
    width: int
    #: the anchor (front) direction, radians: every view set records it for "the front view"
    anchor_azimuth: float
    anchor_elevation: float

    @property
    def c2w(self) -> np.ndarray:
        return look_at(camera_positions(self.azimuth, self.elevation, self.radius))

    def __len__(self) -> int:
        return len(self.azimuth)


def training_views(s: RaycacheSettings) -> ViewSet:
    rng = np.random.default_rng(s.seed)
    anchor_az, anchor_el, _ = s.anchor()
    az, el = sample_views(s.views, anchor_azimuth=anchor_az, anchor_elevation=anchor_el, std=s.std, rng=rng)
    return ViewSet(az, el, np.full(len(az), s.radius), s.fov_deg, s.resolution, anchor_az, anchor_el)


def evaluation_views(s: RaycacheSettings) -> ViewSet:
    az, el = grid_views(s.eval_azimuths, s.eval_elevations_deg)
    return ViewSet(az, el, np.full(len(az), s.eval_radius), s.eval_fov_deg, s.eval_resolution, *s.anchor()[:2])


def metric_views(s: RaycacheSettings) -> ViewSet:
    az, el = grid_views(s.metrics_azimuths, s.metrics_elevations_deg)
    return ViewSet(
        az,
        el,
        np.full(len(az), s.metrics_radius),
        s.metrics_fov_deg,
        s.metrics_resolution,
        *s.anchor()[:2],
    )


def quantize_bary(bary: np.ndarray) -> np.ndarray:
    """``(N, 2)`` float barycentrics in [0, 1] -> uint16 fixed point (error <= 0.5 / 65535)."""
    return np.rint(np.clip(bary, 0.0, 1.0) * BARY_SCALE).astype(np.uint16)


def dequantize_bary(q: np.ndarray) -> np.ndarray:
    return q.astype(np.float32) * np.float32(1.0 / BARY_SCALE)


@dataclass
class TraceStats:
    rays: int = 0
    hits: int = 0
    trace_seconds: float = 0.0
    total_seconds: float = 0.0
    hits_per_view: list[int] = field(default_factory=list)


def trace_views(mesh: TriMesh, views: ViewSet, tracer=None) -> tuple[dict[str, np.ndarray], TraceStats]:
    """Trace every pixel of every view; return the cache arrays (see the module docstring)."""
    tracer = tracer or EmbreeTracer(mesh)
    t_start = time.perf_counter()
    cam_dirs = camera_space_directions(views.width, views.fov_deg)
    c2w = views.c2w
    pixels, faces, barys = [], [], []
    stats = TraceStats()
    offsets = np.zeros(len(views) + 1, np.int64)
    for i in range(len(views)):
        origins, dirs = world_rays(c2w[i], cam_dirs)
        t0 = time.perf_counter()
        hits = tracer.trace(origins, dirs)
        stats.trace_seconds += time.perf_counter() - t0
        hit = np.flatnonzero(hits.face >= 0)
        pixels.append(hit.astype(np.uint32))
        faces.append(hits.face[hit])
        barys.append(quantize_bary(hits.bary[hit]))
        offsets[i + 1] = offsets[i] + len(hit)
        stats.hits_per_view.append(int(len(hit)))
    stats.rays = len(views) * views.width**2
    stats.hits = int(offsets[-1])
    stats.total_seconds = time.perf_counter() - t_start
    arrays = {
        "pixel": np.concatenate(pixels),
        "face": np.concatenate(faces).astype(np.int32),
        "bary": np.concatenate(barys).reshape(-1, 2),
        "offsets": offsets,
        "c2w": c2w,
        "azimuth": views.azimuth,
        "elevation": views.elevation,
        "radius": views.radius,
        "fov_deg": np.float64(views.fov_deg),
        "width": np.int64(views.width),
        "anchor_azimuth": np.float64(views.anchor_azimuth),
        "anchor_elevation": np.float64(views.anchor_elevation),
        "vertices": mesh.vertices.astype(np.float32),
        "faces": mesh.faces.astype(np.int32),
        "face_normals": mesh.face_normals.astype(np.float32),
    }
    return arrays, stats


@dataclass(frozen=True)
class ViewHits:
    """Hits of one cached view: ``pixel (N,) int64``, ``face (N,) int64``, ``point (N, 3)``,
    ``normal (N, 3)`` (the shading normals asked for: flat face normals by default),
    ``face_normal (N, 3)`` (flat, which side the viewer sees), ``direction (N, 3)`` unit ray
    directions, all float32; none flipped towards the camera."""

    pixel: np.ndarray
    face: np.ndarray
    point: np.ndarray
    normal: np.ndarray
    direction: np.ndarray
    c2w: np.ndarray
    width: int
    face_normal: np.ndarray


class RayCache:
    """Read access to one cache file written by the raycache stage."""

    def __init__(self, path: str | Path, arrays: dict[str, np.ndarray] | None = None) -> None:
        """The cache file at ``path``, or (``arrays`` given, as :func:`trace_views` returns them) a
        cache held in memory, ``path`` naming where it came from."""
        self.path = Path(path)
        if arrays is None:
            if not self.path.exists() and not self.path.is_symlink():
                raise StageInputError(self.path, "ray cache not found", "Run the raycache stage first (snakemake runs it).")
            with open_read(self.path, DATA_LIMIT, remedy="Run the raycache stage again.") as fh, np.load(fh) as z:
                arrays = {k: z[k] for k in z.files}
        self.arrays = arrays
        self.width = int(self.arrays["width"])
        self.fov_deg = float(self.arrays["fov_deg"])
        self._corners: dict[NormalSpec, np.ndarray] = {}

    def view_set(self) -> ViewSet:
        """The cameras the cache was traced from (to trace another mesh from the same views)."""
        a = self.arrays
        return ViewSet(
            a["azimuth"],
            a["elevation"],
            a["radius"],
            self.fov_deg,
            self.width,
            float(a["anchor_azimuth"]),
            float(a["anchor_elevation"]),
        )

    def __len__(self) -> int:
        return len(self.arrays["offsets"]) - 1

    def corner_normals(self, spec: NormalSpec) -> np.ndarray:
        """``(F, 3, 3) float32`` shading normals per face corner of the cached mesh (computed once
        per ``spec``)."""
        if spec not in self._corners:
            a = self.arrays
            self._corners[spec] = spec.corner_normals(a["vertices"].astype(np.float64), a["faces"]).astype(np.float32)
        return self._corners[spec]

    def view(self, i: int, normals: NormalSpec | None = None) -> ViewHits:
        """Hits of view ``i`` with the shading ``normals`` of ``spec`` (flat when None)."""
        a = self.arrays
        lo, hi = a["offsets"][i], a["offsets"][i + 1]
        pixel = a["pixel"][lo:hi].astype(np.int64)
        face = a["face"][lo:hi].astype(np.int64)
        uv = dequantize_bary(a["bary"][lo:hi])
        tri = a["vertices"][a["faces"][face]]
        point = tri[:, 0] + uv[:, :1] * (tri[:, 1] - tri[:, 0]) + uv[:, 1:] * (tri[:, 2] - tri[:, 0])
        cam = camera_space_directions(self.width, self.fov_deg)[pixel]
        direction = (cam @ a["c2w"][i][:3, :3].T).astype(np.float32)
        flat = a["face_normals"][face]
        shading = flat
        if normals is not None and normals.mode != "flat":
            shading = interpolate_normals(self.corner_normals(normals), face, uv, flat).astype(np.float32)
        return ViewHits(pixel, face, point.astype(np.float32), shading, direction, a["c2w"][i], self.width, flat)

    def mesh(self) -> TriMesh:
        """The mesh its rays were traced against (float64)."""
        return TriMesh(self.arrays["vertices"].astype(np.float64), self.arrays["faces"].astype(np.int64))

    @property
    def visibility_directions(self) -> int:
        """How many directions each hit's visibility holds (0: the cache has no visibility)."""
        return int(self.arrays["visibility_directions"]) if "visibility" in self.arrays else 0

    def visibility(self, i: int) -> np.ndarray | None:
        """View ``i``'s visibility bits ``(N, D / 8) uint8`` in its hits' order, or None."""
        if "visibility" not in self.arrays:
            return None
        lo, hi = self.arrays["offsets"][i], self.arrays["offsets"][i + 1]
        return self.arrays["visibility"][lo:hi]

    def mask(self, i: int) -> np.ndarray:
        """``(W, W) bool`` coverage of view ``i``."""
        m = np.zeros(self.width * self.width, bool)
        lo, hi = self.arrays["offsets"][i], self.arrays["offsets"][i + 1]
        m[self.arrays["pixel"][lo:hi]] = True
        return m.reshape(self.width, self.width)

    def front_view(self) -> int:
        """The view whose camera lies closest in direction to the anchor (front) view the cache
        recorded: the view of previews and of the material-editing figure."""
        a = self.arrays
        if "anchor_azimuth" not in a:
            raise StageInputError(
                self.path,
                "records no anchor view (written by an older version)",
                "Rerun the raycache stage (snakemake --forcerun raycache).",
            )
        front = camera_positions(a["anchor_azimuth"], a["anchor_elevation"], 1.0)
        eyes = a["c2w"][:, :3, 3]
        return int(np.argmax(eyes @ front / np.linalg.norm(eyes, axis=1)))

    def bytes_per_view(self) -> float:
        per_hit = sum(self.arrays[k].nbytes for k in ("pixel", "face", "bary"))
        return per_hit / len(self)


def save_cache(path: Path, arrays: dict[str, np.ndarray]) -> None:
    with atomic_stream(path) as fh:
        np.savez(fh, **arrays)


def trace_cache_visibility(arrays: dict[str, np.ndarray], tracer, directions: int) -> np.ndarray:
    """The visibility bits (:func:`~stages.geometry.visibility.trace_visibility`) of ``directions``
    directions at every hit of a cache (``arrays`` as :func:`trace_views` returns them), each hit's
    normal the flat face normal turned to the side its ray came from -> ``(N, directions / 8)
    uint8``, in the cache's hit order (stored as the cache's ``visibility`` array)."""
    cache = RayCache("<memory>", arrays)
    dirs = fibonacci_directions(directions)
    offset = surface_offset(arrays["vertices"])
    parts = []
    for i in range(len(cache)):
        h = cache.view(i)
        parts.append(trace_visibility(tracer, h.point, viewer_side_normals(h.face_normal, h.direction), dirs, offset))
    return np.concatenate(parts) if parts else np.zeros((0, directions // 8), np.uint8)
