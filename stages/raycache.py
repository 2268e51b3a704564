"""raycache: trace one primary ray per pixel once per mesh, and keep only the pixels that hit.

TANGO (Sec. 3.1) casts a ray through each pixel of views sampled around an anchor view, keeps the
first intersection and the intersected face, and uses the face normal as the surface normal. None
of that depends on the prompt or on the learned fields, so it is done once per mesh (and
decimation level) here and every optimisation of that mesh reads it.

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
``fov_deg, width``        scalars      full field of view (degrees), image width = height
``vertices, faces``       f4, i4       the traced mesh, so points are ``bary`` on ``faces``
``face_normals (F, 3)``   float32      flat face normals (right-hand rule, not flipped)
========================  ===========  ========================================================

Per hit that is 12 bytes (4 + 4 + 2 * 2); the hit point (to 1/65535 of a triangle edge, far
below float32's resolution of the unit sphere for meshes up to millions of faces) and the flat
face normal (exactly) are recovered from the face id and barycentrics by :class:`RayCache`.
Normals are *not* flipped towards the camera: a hit on a back face (inside an open vase) has
``dot(normal, ray) > 0``, and the renderer decides what to do with it.
"""

from __future__ import annotations

import argparse
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .cameras import (
    camera_positions,
    camera_space_directions,
    grid_views,
    look_at,
    sample_views,
    world_rays,
)
from .errors import ConfigError, StageInputError, stage_errors
from .meshio import TriMesh, load_ply
from .provenance import Timer, atomic_path, metadata, setup_logging, write_json_atomic
from .settings import Settings

log = logging.getLogger(__name__)

BYTES_PER_HIT = 4 + 4 + 2 * 2
BARY_SCALE = 65535.0


@dataclass(frozen=True, kw_only=True)
class RaycacheSettings(Settings):
    """Settings of the raycache stage (config section ``raycache``, overridable per mesh)."""

    section = "raycache"
    #: size of the sampled training view pool (view 0 is the anchor)
    views: int = 64
    #: image width = height in pixels (TANGO: 512)
    resolution: int = 512
    #: full field of view in degrees (TANGO: 60)
    fov_deg: float = 60.0
    #: camera distance from the origin; the unit sphere fills the view at 1 / sin(fov / 2)
    radius: float = 2.0
    #: anchor (front) view, radians (TANGO's demos: azimuth 1.96, elevation 0.63)
    anchor_azimuth: float = 1.96
    anchor_elevation: float = 0.63
    #: spread divisor: elevation std pi/std, azimuth std 2 pi/std (TANGO's demos: 8)
    std: float = 8.0
    #: seed of the view sampler
    seed: int = 0
    #: evaluation views: this many azimuths times these elevations (degrees)
    eval_azimuths: int = 8
    eval_elevations_deg: tuple[float, ...] = (-30.0, 0.0, 30.0)
    eval_radius: float = 2.0
    eval_fov_deg: float = 60.0
    eval_resolution: int = 512
    #: metric views (the X-Mesh protocol): azimuths x elevations, radius 2.5, 45 deg, 224 px
    metrics_azimuths: int = 8
    metrics_elevations_deg: tuple[float, ...] = (-30.0, 0.0, 30.0)
    metrics_radius: float = 2.5
    metrics_fov_deg: float = 45.0
    metrics_resolution: int = 224
    #: ray-tracing backend: "embree" (embreex) or "trimesh" (pure Python; tiny test inputs only)
    backend: str = "embree"

    def __post_init__(self) -> None:
        problems = []
        if self.views < 1:
            problems.append(f"views must be >= 1, got {self.views}")
        for name in ("resolution", "eval_resolution"):
            if not 8 <= getattr(self, name) <= 8192:
                problems.append(f"{name} must be in [8, 8192], got {getattr(self, name)}")
        for name in ("fov_deg", "eval_fov_deg"):
            if not 0.0 < getattr(self, name) < 180.0:
                problems.append(f"{name} must be in (0, 180), got {getattr(self, name)}")
        for name in ("radius", "eval_radius", "std"):
            if not getattr(self, name) > 0:
                problems.append(f"{name} must be > 0, got {getattr(self, name)}")
        if self.backend not in ("embree", "trimesh"):
            problems.append(f"backend must be 'embree' or 'trimesh', got {self.backend!r}")
        if problems:
            raise ConfigError("raycache settings: " + "; ".join(problems))


@dataclass(frozen=True)
class Hits:
    """First hits of one batch of rays: ``face (N,) int32`` (-1 = miss), ``bary (N, 2) float32``,
    ``depth (N,) float32`` (ray parameter ``t`` for unit directions; inf on a miss)."""

    face: np.ndarray
    bary: np.ndarray
    depth: np.ndarray


class EmbreeTracer:
    """First-hit queries against a triangle mesh through embreex (Embree 4)."""

    def __init__(self, mesh: TriMesh) -> None:
        try:
            from embreex import rtcore_scene
            from embreex.mesh_construction import TriangleMesh
        except ImportError as exc:  # pragma: no cover
            raise ImportError("the raycache stage needs embreex: pip install embreex") from exc
        self._scene = rtcore_scene.EmbreeScene()
        triangles = np.ascontiguousarray(mesh.vertices[mesh.faces], dtype=np.float32)
        self._geometry = TriangleMesh(self._scene, triangles)  # keep a reference alive

    def trace(self, origins: np.ndarray, directions: np.ndarray) -> Hits:
        """``origins, directions (N, 3)``; directions need not be unit (depth is then ``t``)."""
        out = self._scene.run(
            np.ascontiguousarray(origins, dtype=np.float32),
            np.ascontiguousarray(directions, dtype=np.float32),
            output=1,
        )
        face = out["primID"].astype(np.int32, copy=False)
        bary = np.stack([out["u"], out["v"]], axis=1)
        depth = np.where(face >= 0, out["tfar"], np.inf).astype(np.float32)
        return Hits(face, bary, depth)


class TrimeshTracer:
    """trimesh's pure-Python tracer (about 400 rays/s): a reference for tests on tiny inputs."""

    def __init__(self, mesh: TriMesh) -> None:
        import trimesh
        from trimesh.ray.ray_triangle import RayMeshIntersector

        self._mesh = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
        self._rmi = RayMeshIntersector(self._mesh)

    def trace(self, origins: np.ndarray, directions: np.ndarray) -> Hits:
        origins = np.asarray(origins, np.float64)
        directions = np.asarray(directions, np.float64)
        n = len(origins)
        face = np.full(n, -1, np.int32)
        bary = np.zeros((n, 2), np.float32)
        depth = np.full(n, np.inf, np.float32)
        tri_idx, ray_idx, loc = self._rmi.intersects_id(origins, directions, multiple_hits=True, return_locations=True)
        if len(ray_idx):
            t = np.einsum("ij,ij->i", loc - origins[ray_idx], directions[ray_idx]) / np.einsum(
                "ij,ij->i", directions[ray_idx], directions[ray_idx]
            )
            order = np.lexsort((t, ray_idx))
            first = order[np.r_[True, ray_idx[order][1:] != ray_idx[order][:-1]]]
            r, f = ray_idx[first], tri_idx[first]
            face[r] = f
            depth[r] = t[first]
            tri = self._mesh.vertices[self._mesh.faces[f]]
            e1, e2, p = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], loc[first] - tri[:, 0]
            d11, d12, d22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
            p1, p2 = (p * e1).sum(1), (p * e2).sum(1)
            den = d11 * d22 - d12 * d12
            bary[r, 0] = (d22 * p1 - d12 * p2) / den
            bary[r, 1] = (d11 * p2 - d12 * p1) / den
        return Hits(face, bary, depth)


def make_tracer(mesh: TriMesh, backend: str = "embree"):
    return EmbreeTracer(mesh) if backend == "embree" else TrimeshTracer(mesh)


@dataclass
class ViewSet:
    """Cameras of one view set: ``azimuth, elevation, radius (V,)`` float64, scalars fov/width."""

    azimuth: np.ndarray
    elevation: np.ndarray
    radius: np.ndarray
    fov_deg: float
    width: int

    @property
    def c2w(self) -> np.ndarray:
        return look_at(camera_positions(self.azimuth, self.elevation, self.radius))

    def __len__(self) -> int:
        return len(self.azimuth)


def training_views(s: RaycacheSettings) -> ViewSet:
    rng = np.random.default_rng(s.seed)
    az, el = sample_views(
        s.views,
        anchor_azimuth=s.anchor_azimuth,
        anchor_elevation=s.anchor_elevation,
        std=s.std,
        rng=rng,
    )
    return ViewSet(az, el, np.full(len(az), s.radius), s.fov_deg, s.resolution)


def evaluation_views(s: RaycacheSettings) -> ViewSet:
    az, el = grid_views(s.eval_azimuths, s.eval_elevations_deg)
    return ViewSet(az, el, np.full(len(az), s.eval_radius), s.eval_fov_deg, s.eval_resolution)


def metric_views(s: RaycacheSettings) -> ViewSet:
    az, el = grid_views(s.metrics_azimuths, s.metrics_elevations_deg)
    return ViewSet(az, el, np.full(len(az), s.metrics_radius), s.metrics_fov_deg, s.metrics_resolution)


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
        "vertices": mesh.vertices.astype(np.float32),
        "faces": mesh.faces.astype(np.int32),
        "face_normals": mesh.face_normals.astype(np.float32),
    }
    return arrays, stats


@dataclass(frozen=True)
class ViewHits:
    """Hits of one cached view: ``pixel (N,) int64``, ``face (N,) int64``, ``point (N, 3)``,
    ``normal (N, 3)`` (flat face normals), ``direction (N, 3)`` unit ray directions, all float32."""

    pixel: np.ndarray
    face: np.ndarray
    point: np.ndarray
    normal: np.ndarray
    direction: np.ndarray
    c2w: np.ndarray
    width: int


class RayCache:
    """Read access to one cache file written by this stage."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        with np.load(self.path) as z:
            self.arrays = {k: z[k] for k in z.files}
        self.width = int(self.arrays["width"])
        self.fov_deg = float(self.arrays["fov_deg"])

    def __len__(self) -> int:
        return len(self.arrays["offsets"]) - 1

    def view(self, i: int) -> ViewHits:
        a = self.arrays
        lo, hi = a["offsets"][i], a["offsets"][i + 1]
        pixel = a["pixel"][lo:hi].astype(np.int64)
        face = a["face"][lo:hi].astype(np.int64)
        uv = dequantize_bary(a["bary"][lo:hi])
        tri = a["vertices"][a["faces"][face]]
        point = tri[:, 0] + uv[:, :1] * (tri[:, 1] - tri[:, 0]) + uv[:, 1:] * (tri[:, 2] - tri[:, 0])
        cam = camera_space_directions(self.width, self.fov_deg)[pixel]
        direction = (cam @ a["c2w"][i][:3, :3].T).astype(np.float32)
        return ViewHits(
            pixel,
            face,
            point.astype(np.float32),
            a["face_normals"][face],
            direction,
            a["c2w"][i],
            self.width,
        )

    def mask(self, i: int) -> np.ndarray:
        """``(W, W) bool`` coverage of view ``i``."""
        m = np.zeros(self.width * self.width, bool)
        lo, hi = self.arrays["offsets"][i], self.arrays["offsets"][i + 1]
        m[self.arrays["pixel"][lo:hi]] = True
        return m.reshape(self.width, self.width)

    def bytes_per_view(self) -> float:
        per_hit = sum(self.arrays[k].nbytes for k in ("pixel", "face", "bary"))
        return per_hit / len(self)


def _save_cache(path: Path, arrays: dict[str, np.ndarray]) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)


def run(
    in_mesh: Path,
    out_train: Path,
    out_eval: Path,
    out_meta: Path,
    settings: RaycacheSettings,
    out_metrics: Path | None = None,
) -> dict:
    """Trace the training pool, the evaluation views and (when ``out_metrics`` is given) the
    metric views of ``in_mesh``; write one cache per set."""
    timer = Timer()
    with timer("load"):
        if not Path(in_mesh).is_file():
            raise StageInputError(in_mesh, "file not found", "Run the normalize (and decimate) stage first.")
        mesh = load_ply(in_mesh)
    with timer("build_bvh"):
        tracer = make_tracer(mesh, settings.backend)
    summary = {}
    results = {}
    sets = [("train", training_views(settings)), ("eval", evaluation_views(settings))]
    if out_metrics is not None:
        sets.append(("metrics", metric_views(settings)))
    for name, views in sets:
        with timer(f"trace_{name}"):
            arrays, st = trace_views(mesh, views, tracer)
        if st.hits == 0:
            raise StageInputError(
                in_mesh,
                f"none of the {len(views)} {name} views sees the mesh (0 of {st.rays} rays hit)",
                "Check the raycache camera settings (radius, fov_deg, anchor, eval views) for this mesh.",
            )
        empty = sum(h == 0 for h in st.hits_per_view)
        if empty:
            log.warning("%s: %d of %d %s views see nothing", in_mesh, empty, len(views), name)
        per_hit_bytes = sum(arrays[k].nbytes for k in ("pixel", "face", "bary"))
        summary[name] = {
            "views": len(views),
            "width": views.width,
            "rays": st.rays,
            "hits": st.hits,
            "coverage_mean": st.hits / st.rays,
            "hits_per_view_min": min(st.hits_per_view),
            "hits_per_view_max": max(st.hits_per_view),
            "empty_views": empty,
            "bytes_per_view": per_hit_bytes / len(views),
            "trace_seconds": st.trace_seconds,
            "rays_per_second_trace": st.rays / st.trace_seconds,
            "rays_per_second_total": st.rays / st.total_seconds,
        }
        results[name] = arrays
    with timer("write"):
        _save_cache(out_train, results["train"])
        _save_cache(out_eval, results["eval"])
        if out_metrics is not None:
            _save_cache(out_metrics, results["metrics"])
    for name, s in summary.items():
        log.info(
            "%s %s: %d views of %dx%d, coverage %.1f%%, %.0f bytes/view, %.2f M rays/s",
            in_mesh,
            name,
            s["views"],
            s["width"],
            s["width"],
            100 * s["coverage_mean"],
            s["bytes_per_view"],
            s["rays_per_second_total"] / 1e6,
        )
    write_json_atomic(
        out_meta,
        metadata(
            stage="raycache",
            settings=settings.to_dict(),
            seed=settings.seed,
            inputs={"mesh": in_mesh},
            outputs={"train": out_train, "eval": out_eval, "metrics": out_metrics},
            timings={**timer.seconds, "total": timer.total()},
            extra={"stats": summary, "bytes_per_hit": BYTES_PER_HIT},
        ),
    )
    return summary


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m stages.raycache", description=__doc__.split("\n")[0])
    parser.add_argument("--input", required=True, type=Path, help="normalised (or decimated) mesh (.ply)")
    parser.add_argument("--train", required=True, type=Path, help="output cache of the training pool (.npz)")
    parser.add_argument("--eval", required=True, type=Path, help="output cache of the evaluation views (.npz)")
    parser.add_argument("--meta", required=True, type=Path, help="output metadata (.json)")
    parser.add_argument("--metrics", type=Path, default=None, help="output cache of the metric views (.npz)")
    parser.add_argument("--settings", default="{}", help="JSON of the raycache settings")
    parser.add_argument("-v", "--verbose", action="store_true")
    args = parser.parse_args(argv)
    setup_logging(args.verbose)
    with stage_errors("raycache") as status:
        run(
            args.input,
            args.train,
            args.eval,
            args.meta,
            RaycacheSettings.from_json(args.settings),
            args.metrics,
        )
    return status.code


if __name__ == "__main__":
    raise SystemExit(main())
