"""metrics: quality numbers of one grid cell on fixed metric views (the X-Mesh protocol: 8
azimuths x elevations -30/0/30 degrees, radius 2.5, 45-degree field of view, 224 x 224, white
background; see the raycache stage's ``metrics_*`` settings).

* ``guidance`` (CLIP-guided runs): cosine similarity of the prompt with the renders under the
  guidance model (the CLIP the optimisation used), averaged over views;
* ``evaluation``: the CLIP score (100 x mean cosine similarity) under an *independent* evaluation
  model (``metrics.clip_model`` / ``clip_pretrained`` / ``clip_checkpoint``) and R-precision over
  the grid's prompts (the fraction of views whose render ranks its own prompt first among the
  ``candidates`` prompts of the grid);
* ``image_target`` (image-guided runs): PSNR and SSIM of the renders against the image targets
  on the same held-out views, over object pixels only (for Mitsuba targets: pixels fully covered
  by the object), and for Mitsuba targets the recovered material's error against the ground
  truth at every fully covered hit of those views (albedo, specular colour, roughness, shading
  normal) and the recovered light's energy against the environment's.

The first and the last are the guidance's own figures (:meth:`~stages.guidance.objective.Guidance.held_out`,
of the class of the run's guidance mode). Every number sits under the id of the weights that
produced it, with ``test_only: true`` for the tiny random test CLIP; the report never mixes those
with real ones in a table.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import torch

from .config.records import MetricsRecord
from .config.sections import MetricsSettings
from .core.cli import stage_main
from .core.errors import StageInputError
from .core.provenance import ORIGIN_KEY, Timer, metadata, staged_outputs, write_json_atomic
from .core.safefiles import read_json
from .geometry.raycache import RayCache
from .guidance.clip import load_clip
from .guidance.objective import guidance_class
from .guidance.scores import clip_metrics
from .imaging.quality import material_errors
from .imaging.relit import training_ceiling
from .imaging.sheets import contact_sheet, save_png
from .imaging.targets import FULL_COVERAGE, TargetSet
from .imaging.views import ViewStore, render_views
from .model.checkpoint import load_field

log = logging.getLogger(__name__)


#: the steps of the SG fit of the training environment for the ceiling (the relight stage's default)
CEILING_FIT_ITERATIONS = 400


def run(
    field_path: Path,
    metrics_cache: Path,
    prompt: str,
    candidates: list[str],
    out_dir: Path,
    settings: MetricsSettings,
    device: str = "cpu",
    targets_path: Path | None = None,
) -> dict:
    timer = Timer()
    for p in (field_path, metrics_cache):
        if not Path(p).is_file():
            raise StageInputError(p, "file not found", "Run the optimize and raycache stages first.")
    if prompt not in candidates:
        candidates = [prompt, *candidates]
    dev = torch.device(device)
    field, opt_settings = load_field(field_path, dev)
    cache = RayCache(metrics_cache)
    mitsuba = opt_settings.mitsuba_targets()
    if mitsuba and targets_path is None:
        raise StageInputError(
            field_path, "was trained on Mitsuba targets but no --targets file was given", "Pass the target stage's metrics.npz."
        )
    targets = TargetSet(targets_path, cache) if mitsuba else None
    store = ViewStore(cache, dev, field.normals, targets, shadows=field.shadows)
    with timer("render"):
        imgs = render_views(field, store, settings.background)
    out_dir = Path(out_dir)
    with staged_outputs(out_dir) as staging:
        save_png(staging / "views.png", contact_sheet(list(imgs), len(store.azimuths())))
        result: dict = {"prompt": prompt, ORIGIN_KEY: field.origin}
        result["protocol"] = {
            "views": len(store),
            "resolution": store.width,
            "fov_deg": float(store.cache.arrays["fov_deg"]),
            "radius": float(store.cache.arrays["radius"][0]),
            "background": settings.background,
        }
        kind = guidance_class(opt_settings)  # its figures: under "guidance" (CLIP) or "image_target"
        with timer(kind.held_out_key):
            guidance = kind.for_metrics(opt_settings, prompt, dev, targets.description if targets else None)
            held = guidance.held_out(imgs, store, candidates, 1.0 if settings.background == "white" else 0.0)
            if targets is not None:  # Mitsuba's targets: their noise, and the material against its truth
                held.figures["target_noise_psnr_db"] = _noise_psnr(targets_path)
                if targets.has_truth:
                    held.figures["material"] = _material_errors(field, store, targets)
                    if targets.environment is not None and all(k in targets.arrays for k in field.brdf.parameters):
                        held.figures["ceiling"] = training_ceiling(
                            field, store, targets, targets.environment, field.light.lobes, CEILING_FIT_ITERATIONS
                        )
        result[kind.held_out_key] = held.figures
        if held.targets is not None:
            save_png(staging / "targets.png", contact_sheet(list(held.targets), len(store.azimuths())))
        if settings.clip:
            with timer("evaluation"):
                e = load_clip(settings.clip_spec(), device=dev)
                result["evaluation"] = clip_metrics(e, imgs, prompt, candidates)
        record = MetricsRecord(result.get("guidance"), result.get("evaluation"), result.get("image_target"))
        write_json_atomic(staging / "metrics.json", {**result, **record.stats()})
        write_json_atomic(
            staging / "meta.json",
            metadata(
                stage="metrics",
                settings=settings.to_dict(),
                inputs={"field": field_path, "metrics_cache": metrics_cache, **({"targets": targets_path} if targets else {})},
                outputs={"metrics": out_dir / "metrics.json", "views": out_dir / "views.png"},
                timings={**timer.seconds, "total": timer.total()},
                extra={"candidates": candidates, ORIGIN_KEY: field.origin},
            ),
        )
    return result


def _noise_psnr(targets_path: Path) -> float | None:
    """The noise of the metric views' targets, as the target stage measured it."""
    meta = Path(targets_path).parent / "meta.json"
    if not meta.is_file():
        return None
    return read_json(meta)["views"]["metrics"]["noise_psnr_db"]


@torch.no_grad()
def _material_errors(field, store: ViewStore, targets: TargetSet) -> dict:
    """The recovered material at every fully covered hit of the metric views against the truth."""
    pred: dict[str, list] = {"albedo": [], "specular": [], "roughness": [], "normal": []}
    truth: dict[str, list] = {k: [] for k in pred}
    for i in range(len(store)):
        v = store[i]
        keep = v.coverage >= FULL_COVERAGE
        mat, normal = field.surface(v.points[keep], v.normals[keep], v.view[keep])
        pred["albedo"].append(mat.albedo)
        pred["specular"].append(mat.specular)
        pred["roughness"].append(mat.roughness)
        pred["normal"].append(normal)
        for k in truth:
            truth[k].append(torch.from_numpy(targets.view(i, k)).to(v.points.device)[keep])
    if pred["specular"][0] is None:
        pred["specular"] = pred["roughness"] = None
    cat = {k: (torch.cat(x) if x is not None else None) for k, x in pred.items()}
    out = material_errors(cat, {k: torch.cat(x) for k, x in truth.items()}, field.light.energy(), targets.arrays["env_energy"])
    out["hits"] = int(sum(len(x) for x in truth["albedo"]))
    out["measured_on"] = "every fully covered hit of the held-out metric views"
    return out


def main(argv: list[str] | None = None) -> int:
    def arguments(parser):
        parser.add_argument("--field", required=True, type=Path)
        parser.add_argument("--metrics-cache", required=True, type=Path, help="the metric views' ray cache (.npz)")
        parser.add_argument("--prompt", required=True, help="the prompt's text (CLIP scores the renders against it)")
        parser.add_argument("--candidates", default="[]", help="JSON list of the grid's prompt texts for this mesh")
        parser.add_argument("--out-dir", required=True, type=Path)
        parser.add_argument("--settings", default="{}")
        parser.add_argument("--targets", type=Path, default=None, help="Mitsuba targets of the metric views (target stage)")

    def body(args):
        settings = MetricsSettings.from_json(args.settings)
        candidates = json.loads(args.candidates)
        run(args.field, args.metrics_cache, args.prompt, candidates, args.out_dir, settings, args.device, args.targets)

    return stage_main("metrics", __doc__, arguments, body, argv, device="cpu")


if __name__ == "__main__":
    raise SystemExit(main())
