"""target: ground-truth image targets path-traced by Mitsuba 3 (``target_renderer: mitsuba``).

For one mesh and one procedural material, Mitsuba renders every view of the training ray cache
and of the held-out metric views through the caches' own cameras: the material as a principled
BSDF with textures and a normal map, under an environment map that no SG sum represents (see
:mod:`stages.reference.targets`). The targets are stored per cached hit
(:mod:`stages.imaging.targets`); the metric views also carry the material's ground truth at
every hit, so the metrics stage can grade the recovered albedo, roughness and light energy.

The metric views are also rendered under each of ``target.relight_environments`` (the same
material and samples, another light): ``relit.npz``, the ground truth the relight stage grades the
recovered field's relighting against.

Outputs (in ``--out-dir``): ``train.npz``, ``metrics.npz``, ``relit.npz``, ``targets.png`` (the metric views),
``material.png`` (base colour, roughness, metallic and normal textures) and ``meta.json`` (samples
per pixel, the measured noise of the targets, the Mitsuba version and variant, timings).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from .config.sections import MATERIALS, TargetSettings
from .core.cli import stage_main
from .core.errors import StageInputError
from .core.provenance import Timer, metadata, staged_outputs, write_json_atomic
from .geometry.meshio import TriMesh, load_ply
from .geometry.raycache import RayCache
from .imaging.sheets import save_png
from .imaging.targets import SENDER_PREFIX, save_relit, save_targets
from .reference.target_job import MeshTargets, material_sheet, render_targets, target_sheet, view_summary
from .reference.targets import target_normals

log = logging.getLogger(__name__)

#: the stage's outputs, in its folder
OUTPUTS = ("train.npz", "metrics.npz", "relit.npz", "targets.png", "material.png")


def run(
    train_path: Path,
    metrics_path: Path,
    material: str,
    out_dir: Path,
    settings: TargetSettings,
    mesh_path: Path | None = None,
) -> dict:
    """Render the targets of both caches and write them (atomically, all or nothing). The scene's
    mesh is ``mesh_path`` (the full-resolution normalised mesh; the workflow always passes it),
    else the mesh the caches traced."""
    timer = Timer()
    for p in (train_path, metrics_path, *([mesh_path] if mesh_path is not None else [])):
        if not Path(p).is_file():
            raise StageInputError(p, "file not found", "Run the normalize and raycache stages first.")
    if material not in MATERIALS:
        raise StageInputError(material, "not a procedural material", f"Use one of {', '.join(MATERIALS)}.")
    with timer("load"):
        train, metric = RayCache(train_path), RayCache(metrics_path)
        if mesh_path is not None:
            mesh = load_ply(mesh_path)
        else:
            mesh = TriMesh(train.arrays["vertices"].astype(np.float64), train.arrays["faces"].astype(np.int64))
    targets = render_targets(mesh, material, settings, (train, metric), timer)
    summary = {
        "train": view_summary(targets.train, settings.spp, train.width),
        "metrics": view_summary(targets.metrics, settings.metric_spp, metric.width, targets.missing),
    }
    for name, s in summary.items():
        log.info(
            "%s targets: %d views, noise PSNR %.1f dB at %d spp, %.1f s",
            name,
            s["views"],
            s["noise_psnr_db"],
            s["spp"],
            s["render_seconds"],
        )
    out_dir = Path(out_dir)
    with staged_outputs(out_dir) as staging:
        _write_targets(staging, targets, train, metric)
        save_png(staging / "targets.png", target_sheet(metric, targets.metrics.radiance))
        save_png(staging / "material.png", material_sheet(targets.renderer, settings.texture_size))
        record = {
            "material": material,
            "description": targets.text,
            "rendered_mesh": {
                "path": str(mesh_path) if mesh_path is not None else str(train_path),
                "faces": len(mesh.faces),
                "cache_faces": len(train.arrays["faces"]),
                "shading_normals": target_normals(settings).describe(),
            },
            **_renderer_record(targets),
            "views": summary,
        }
        write_json_atomic(
            staging / "meta.json",
            metadata(
                stage="target",
                settings=settings.to_dict(),
                seed=settings.seed,
                inputs={"train": train_path, "metrics": metrics_path},
                outputs={k: out_dir / k for k in OUTPUTS},
                timings={**timer.seconds, "textures": targets.renderer.seconds_textures, "total": timer.total()},
                extra=record,
            ),
        )
    return summary


def _write_targets(staging: Path, targets: MeshTargets, train: RayCache, metric: RayCache) -> None:
    """The targets per cached hit: the training views', the metric views' with the truth, the relit."""
    common = {
        "description": np.array(targets.text),
        "env_energy": targets.renderer.env_energy,
        "environment": np.array(targets.renderer.environment),
    }
    tt, tm = targets.train, targets.metrics
    save_targets(
        staging / "train.npz", {"radiance": tt.radiance, "coverage": tt.coverage, "offsets": train.arrays["offsets"], **common}
    )
    metrics = {"radiance": tm.radiance, "coverage": tm.coverage, "offsets": metric.arrays["offsets"], **targets.truth, **common}
    metrics.update({f"{SENDER_PREFIX}{k}": v for k, v in (targets.senders or {}).items()})
    save_targets(staging / "metrics.npz", metrics)
    save_relit(staging / "relit.npz", targets.relit, metric.arrays["offsets"], targets.text)


def _renderer_record(targets: MeshTargets) -> dict:
    """What the metadata says of the renderer, its light and the relit renders."""
    r = targets.renderer
    return {
        "renderer": {"name": "Mitsuba 3", "version": r.mi.__version__, "variant": r.variant, "libllvm": r.libllvm},
        "environment_energy": r.env_energy.tolist(),
        "principled_specular": r.truth.specular,
        "relit": {
            env: {"noise_psnr_db": t.noise_psnr_db, "render_seconds": t.seconds, "environment_energy": e.tolist()}
            for env, (t, e) in targets.relit.items()
        },
    }


def main(argv: list[str] | None = None) -> int:
    def arguments(parser):
        parser.add_argument(
            "--mesh", type=Path, default=None, help="full-resolution mesh to render (.ply); default: the caches' mesh"
        )
        parser.add_argument("--train", required=True, type=Path, help="training ray cache (.npz)")
        parser.add_argument("--metrics", required=True, type=Path, help="metric-view ray cache (.npz)")
        parser.add_argument("--material", required=True, choices=MATERIALS, help="the procedural material to render")
        parser.add_argument("--out-dir", required=True, type=Path)
        parser.add_argument("--settings", default="{}", help="JSON of the target settings")

    def body(args):
        run(args.train, args.metrics, args.material, args.out_dir, TargetSettings.from_json(args.settings), args.mesh)

    return stage_main("target", __doc__, arguments, body, argv, threads=True)


if __name__ == "__main__":
    raise SystemExit(main())
