"""raycache: trace one primary ray per pixel once per mesh, and keep only the pixels that hit.

TANGO (Sec. 3.1) casts a ray through each pixel of views sampled around an anchor view, keeps the
first intersection and the intersected face, and uses the face normal as the surface normal. None
of that depends on the prompt or on the learned fields, so it is done once per mesh (and
decimation level) here and every optimisation of that mesh reads it.

The cache format and its reader are :mod:`stages.geometry.raycache`.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from .config.records import RaycacheRecord
from .config.sections import RaycacheSettings
from .core.cli import stage_main
from .core.errors import StageInputError
from .core.provenance import Timer, metadata, write_json_atomic
from .geometry.meshio import load_ply
from .geometry.raycache import (
    BYTES_PER_HIT,
    evaluation_views,
    metric_views,
    save_cache,
    trace_cache_visibility,
    trace_views,
    training_views,
)
from .geometry.tracing import EmbreeTracer, make_tracer
from .geometry.visibility import measure_self_occlusion

log = logging.getLogger(__name__)


def run(
    in_mesh: Path,
    out_train: Path,
    out_eval: Path,
    out_meta: Path,
    settings: RaycacheSettings,
    out_metrics: Path | None = None,
) -> dict:
    """Trace the training pool, the evaluation views and (when ``out_metrics`` is given) the
    metric views of ``in_mesh``; write one cache per set. The metadata also records the mesh's
    self-occlusion (:func:`~stages.geometry.visibility.measure_self_occlusion`: the share of the
    hemisphere its surface sees blocked, mean, median and 95th percentile)."""
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
            results[name], summary[name] = _trace_set(in_mesh, mesh, name, views, tracer)
    with timer("self_occlusion"):
        # Embree whatever the backend: the measurement traces millions of rays
        occlusion = measure_self_occlusion(mesh, tracer if settings.backend == "embree" else EmbreeTracer(mesh), settings.seed)
    log.info(
        "%s: self-occlusion over the surface: median %.3f, 95th percentile %.3f of the hemisphere blocked",
        in_mesh,
        occlusion["median"],
        occlusion["p95"],
    )
    decision = visibility_decision(settings, occlusion)
    if decision["on"]:
        embree = tracer if settings.backend == "embree" else EmbreeTracer(mesh)
        with timer("visibility"):
            for name, arrays in results.items():
                arrays["visibility"] = trace_cache_visibility(arrays, embree, settings.visibility_directions)
                arrays["visibility_directions"] = np.int64(settings.visibility_directions)
                summary[name]["visibility_bytes"] = int(arrays["visibility"].nbytes)
    log.info("%s: visibility %s (%s)", in_mesh, "traced" if decision["on"] else "not traced", decision["why"])
    with timer("write"):
        save_cache(out_train, results["train"])
        save_cache(out_eval, results["eval"])
        if out_metrics is not None:
            save_cache(out_metrics, results["metrics"])
    write_json_atomic(
        out_meta,
        metadata(
            stage="raycache",
            settings=settings.to_dict(),
            seed=settings.seed,
            inputs={"mesh": in_mesh},
            outputs={"train": out_train, "eval": out_eval, "metrics": out_metrics},
            timings={**timer.seconds, "total": timer.total()},
            extra={
                "stats": summary,
                "bytes_per_hit": BYTES_PER_HIT,
                "anchor": anchor_record(settings),
                **RaycacheRecord(self_occlusion=occlusion).stats(),
                "visibility": decision,
            },
        ),
    )
    return summary


def _trace_set(in_mesh: Path, mesh, name: str, views, tracer) -> tuple[dict, dict]:
    """One view set traced: its cache arrays and what the metadata records of it (refused when no
    view sees the mesh)."""
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
    summary = {
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
    log.info(
        "%s %s: %d views of %dx%d, coverage %.1f%%, %.0f bytes/view, %.2f M rays/s",
        in_mesh,
        name,
        len(views),
        views.width,
        views.width,
        100 * summary["coverage_mean"],
        summary["bytes_per_view"],
        summary["rays_per_second_total"] / 1e6,
    )
    return arrays, summary


def visibility_decision(settings: RaycacheSettings, occlusion: dict) -> dict:
    """Whether the caches carry visibility (``raycache.visibility``; ``auto``: from the mesh's
    measured self-occlusion at its 95th percentile), and why, as recorded in the metadata."""
    if settings.visibility != "auto":
        return {
            "on": settings.visibility == "on",
            "why": f"visibility: {settings.visibility}",
            "directions": settings.visibility_directions,
        }
    on = occlusion["p95"] >= settings.visibility_auto_p95
    why = (
        f"visibility: auto, self-occlusion p95 {occlusion['p95']:.3f} "
        f"{'>=' if on else '<'} visibility_auto_p95 {settings.visibility_auto_p95}"
    )
    return {"on": on, "why": why, "directions": settings.visibility_directions}


def anchor_record(settings: RaycacheSettings) -> dict:
    """The anchor (front) view the caches were traced around, in both units, and what set it."""
    az, el, source = settings.anchor()
    return {
        "azimuth_deg": math.degrees(az),
        "elevation_deg": math.degrees(el),
        "azimuth_rad": az,
        "elevation_rad": el,
        "set_by": source,
    }


def main(argv: list[str] | None = None) -> int:
    def arguments(parser):
        parser.add_argument("--input", required=True, type=Path, help="normalised (or decimated) mesh (.ply)")
        parser.add_argument("--train", required=True, type=Path, help="output cache of the training pool (.npz)")
        parser.add_argument("--eval", required=True, type=Path, help="output cache of the evaluation views (.npz)")
        parser.add_argument("--meta", required=True, type=Path, help="output metadata (.json)")
        parser.add_argument("--metrics", type=Path, default=None, help="output cache of the metric views (.npz)")
        parser.add_argument("--settings", default="{}", help="JSON of the raycache settings")

    def body(args):
        settings = RaycacheSettings.from_json(args.settings)
        run(args.input, args.train, args.eval, args.meta, settings, args.metrics)

    return stage_main("raycache", __doc__, arguments, body, argv, threads=True)


if __name__ == "__main__":
    raise SystemExit(main())
