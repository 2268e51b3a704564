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
import torch

from .config.sections import MATERIALS, TargetSettings
from .core.cli import stage_main
from .core.errors import StageInputError
from .core.provenance import Timer, metadata, staged_outputs, write_json_atomic
from .geometry.meshio import TriMesh, load_ply
from .geometry.raycache import RayCache
from .imaging.sheets import contact_sheet, save_png
from .imaging.targets import save_relit, save_targets
from .reference.targets import TargetRenderer, target_normals
from .render.color import srgb_encode

log = logging.getLogger(__name__)


def describe(kind: str, settings: TargetSettings, variant: str) -> str:
    """The one line that names these targets wherever a result made from them goes."""
    return (
        f"Mitsuba 3 ({variant}) path-traced {kind} (principled BSDF, textures, normal map, "
        f"{settings.shading_normals} normals) under "
        f"{settings.environment}, {settings.spp} spp (metric views {settings.metric_spp}), max depth {settings.max_depth}"
    )


def _sheet(cache: RayCache, radiance: np.ndarray, columns: int) -> np.ndarray:
    tiles = []
    offsets = cache.arrays["offsets"]
    w = cache.width
    for i in range(len(cache)):
        img = np.zeros((w * w, 3))
        img[cache.arrays["pixel"][offsets[i] : offsets[i + 1]]] = srgb_encode(radiance[offsets[i] : offsets[i + 1]])
        tiles.append(torch.from_numpy(img.reshape(w, w, 3)).permute(2, 0, 1).float())
    return contact_sheet(tiles, columns)


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
    with timer("scene"):
        renderer = TargetRenderer(mesh, material, settings)
    text = describe(material, settings, renderer.variant)
    log.info("rendering %s", text)
    with timer("render_train"):
        tt = renderer.render_cache(train, settings.spp, settings.seed * 1_000_003)
    with timer("render_metrics"):
        tm = renderer.render_cache(metric, settings.metric_spp, settings.seed * 1_000_003 + 500_009)
    with timer("truth"):
        truth, met = renderer.truth_at_hits(metric)
    # a hit whose ray misses the rendered (finer) mesh is no object pixel of the truth
    tm.coverage[~met] = 0.0
    relit = {}
    with timer("render_relit"):
        for j, env in enumerate(settings.relight_environments):
            judge = TargetRenderer(mesh, material, settings, environment=env, truth=renderer.truth)
            t = judge.render_cache(metric, settings.metric_spp, settings.seed * 1_000_003 + 700_001 + 7919 * j)
            t.coverage[~met] = 0.0
            relit[env] = (t, judge.env_energy)
            log.info("relit ground truth under %s: noise PSNR %.1f dB, %.1f s", env, t.noise_psnr_db, t.seconds)
    out_dir = Path(out_dir)
    summary = {}
    for name, t in (("train", tt), ("metrics", tm)):
        summary[name] = {
            "views": len(t.pixels),
            "spp": settings.spp if name == "train" else settings.metric_spp,
            "noise_psnr_db": t.noise_psnr_db,
            "noise_rms_srgb": float(np.sqrt((t.noise_mse * t.pixels).sum() / max(t.pixels.sum(), 1))),
            "noise_measured_on": "fully covered object pixels, sRGB: half the squared difference of two half-sample renders",
            "partly_covered_hits": float((t.coverage < 0.999).mean()),
            **({"hits_missing_the_rendered_mesh": int((~met).sum())} if name == "metrics" else {}),
            "uncovered_hits": int((t.coverage <= 0).sum()),
            "render_seconds": t.seconds,
        }
        width = (train if name == "train" else metric).width
        summary[name]["samples_per_second"] = len(t.pixels) * width * width * summary[name]["spp"] / max(t.seconds, 1e-9)
        log.info(
            "%s targets: %d views, noise PSNR %.1f dB at %d spp, %.1f s",
            name,
            summary[name]["views"],
            summary[name]["noise_psnr_db"],
            summary[name]["spp"],
            t.seconds,
        )
    with staged_outputs(out_dir) as staging:
        common = {"description": np.array(text), "env_energy": renderer.env_energy}
        save_targets(
            staging / "train.npz",
            {"radiance": tt.radiance, "coverage": tt.coverage, "offsets": train.arrays["offsets"], **common},
        )
        save_targets(
            staging / "metrics.npz",
            {"radiance": tm.radiance, "coverage": tm.coverage, "offsets": metric.arrays["offsets"], **truth, **common},
        )
        save_relit(staging / "relit.npz", relit, metric.arrays["offsets"], text)
        columns = len(np.unique(np.round(metric.arrays["azimuth"], 9)))
        save_png(staging / "targets.png", _sheet(metric, tm.radiance, columns))
        g = renderer.truth
        textures = [g.base_color, np.repeat(g.roughness, 3, -1), np.repeat(g.metallic, 3, -1), 0.5 * g.normal + 0.5]
        textures[0] = srgb_encode(textures[0])
        step = max(1, settings.texture_size // 512)  # a preview: at most 512 pixels a side
        tiles = [torch.from_numpy(np.ascontiguousarray(t[::step, ::step])).permute(2, 0, 1).float().clamp(0, 1) for t in textures]
        save_png(staging / "material.png", contact_sheet(tiles, 4))
        write_json_atomic(
            staging / "meta.json",
            metadata(
                stage="target",
                settings=settings.to_dict(),
                seed=settings.seed,
                inputs={"train": train_path, "metrics": metrics_path},
                outputs={k: out_dir / k for k in ("train.npz", "metrics.npz", "relit.npz", "targets.png", "material.png")},
                timings={**timer.seconds, "textures": renderer.seconds_textures, "total": timer.total()},
                extra={
                    "material": material,
                    "description": text,
                    "rendered_mesh": {
                        "path": str(mesh_path) if mesh_path is not None else str(train_path),
                        "faces": len(mesh.faces),
                        "cache_faces": len(train.arrays["faces"]),
                        "shading_normals": target_normals(settings).describe(),
                    },
                    "renderer": {
                        "name": "Mitsuba 3",
                        "version": renderer.mi.__version__,
                        "variant": renderer.variant,
                        "libllvm": renderer.libllvm,
                    },
                    "environment_energy": renderer.env_energy.tolist(),
                    "principled_specular": g.specular,
                    "views": summary,
                    "relit": {
                        env: {"noise_psnr_db": t.noise_psnr_db, "render_seconds": t.seconds, "environment_energy": e.tolist()}
                        for env, (t, e) in relit.items()
                    },
                },
            ),
        )
    return summary


def main(argv: list[str] | None = None) -> int:
    def arguments(parser):
        parser.add_argument(
            "--mesh", type=Path, default=None, help="full-resolution mesh to render (.ply); default: the caches' mesh"
        )
        parser.add_argument("--train", required=True, type=Path, help="training ray cache (.npz)")
        parser.add_argument("--metrics", required=True, type=Path, help="metric-view ray cache (.npz)")
        parser.add_argument("--material", required=True, choices=MATERIALS)
        parser.add_argument("--out-dir", required=True, type=Path)
        parser.add_argument("--settings", default="{}", help="JSON of the target settings")

    def body(args):
        run(args.train, args.metrics, args.material, args.out_dir, TargetSettings.from_json(args.settings), args.mesh)

    return stage_main("target", __doc__, arguments, body, argv)


if __name__ == "__main__":
    raise SystemExit(main())
