"""optimize: learn material, normal map and light so renders of a mesh match a prompt (TANGO).

The run (:class:`~stages.training.optimizer.Optimizer`) minimises minus the CLIP similarity of
renders of the cached views with the prompt, or with ``guidance: image`` the error against image
targets of a known material and light: Mitsuba's path-traced ground truth (``--targets``, from the
target stage) or our own SG renders of a procedural material (``target_renderer: sg``). Atomic
checkpoints every ``checkpoint_every`` iterations; a rerun after a kill resumes from the last one
and ends with the same parameters as an uninterrupted run. Outputs (in ``--out-dir``, see
:data:`stages.config.layout.OPTIMIZE_FILES`): ``field.pt``, ``loss.csv``, ``loss.png``,
``renders/*.png`` from the evaluation views, ``light.npz`` and ``meta.json``.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch

from .config.layout import OPTIMIZE_FILES, RENDER_KINDS
from .config.records import OptimizeRecord
from .config.sections import OptimizeSettings
from .core.cli import stage_main
from .core.device import cpu_isa, resolve_device
from .core.errors import StageInputError
from .core.progress import Progress, job_label
from .core.provenance import ORIGIN_KEY, Timer, metadata, staged_outputs, write_json_atomic
from .core.safefiles import atomic_stream, remove
from .geometry.raycache import RayCache
from .imaging.sheets import contact_sheet, save_png
from .imaging.targets import TargetSet
from .imaging.views import ViewStore, render_view
from .model.checkpoint import read_torch_file, save_field
from .render.color import linear_to_srgb
from .training.optimizer import Optimizer, plot_loss, save_checkpoint, write_loss_csv

log = logging.getLogger(__name__)


def run(
    train_path: Path,
    eval_path: Path,
    prompt: str,
    out_dir: Path,
    settings: OptimizeSettings,
    device: str = "auto",
    stop_after: int | None = None,
    targets_path: Path | None = None,
) -> dict:
    """Optimise (resuming from ``out_dir/checkpoint.pt`` when it matches) and write the outputs.

    ``stop_after`` ends the process's work after that many iterations *of this call* without
    writing final outputs, as a kill would (used by tests of resumption). ``targets_path``: the
    Mitsuba image targets of ``train_path`` (needed by ``target_renderer: mitsuba``).
    """
    timer = Timer()
    dev = resolve_device(device)
    for p in (train_path, eval_path):
        if not Path(p).is_file():
            raise StageInputError(p, "file not found", "Run the raycache stage first.")
    mitsuba_targets = settings.mitsuba_targets()
    if mitsuba_targets and targets_path is None:
        raise StageInputError(
            train_path, "target_renderer is mitsuba but no --targets file was given", "Pass the target stage's train.npz."
        )
    out_dir = Path(out_dir)
    ckpt = out_dir / "checkpoint.pt"
    with timer("setup"):
        train = RayCache(train_path)
        targets = TargetSet(targets_path, train) if mitsuba_targets else None
        run = Optimizer(settings, train, prompt, dev, targets=targets)
    settings = run.settings  # as the run resolved them (optimize.suns: auto, a count)
    resumed_from = _resume(run, ckpt, settings, dev) if ckpt.is_file() else None
    progress = Progress(job_label("optimize", out_dir), settings.iterations, initial=run.iteration)
    done_here = 0
    t_loop = time.perf_counter()
    while run.iteration < settings.iterations:
        row = run.step(timer)
        done_here += 1
        if run.iteration % settings.checkpoint_every == 0 and run.iteration < settings.iterations:
            with timer("checkpoint"):
                save_checkpoint(ckpt, **run.state())
        progress.update(loss=f"{row['loss']:.4f}")
        if stop_after is not None and done_here >= stop_after:
            progress.close()
            return {"stopped_at": run.iteration}
    progress.close()
    if run.senders is not None:  # the bounce the field is saved with, from the material it ends with
        with timer("bounce"):
            run.refresh_bounce()
    loop_s = time.perf_counter() - t_loop
    # every output is staged and moved into place together, the metadata last; the checkpoint
    # goes only after that, so a kill at any point leaves either a resumable run or finished outputs
    with staged_outputs(out_dir) as staging:
        with timer("outputs"):
            result = _write_outputs(run, eval_path, staging, settings, prompt)
        timings = {**timer.seconds, "loop": loop_s, "total": timer.total()}
        iters_here = max(done_here, 1)
        record = OptimizeRecord(
            prompt=prompt,
            guidance=settings.guidance,
            weights=run.guidance.weights_id,
            test_only_weights=run.guidance.test_only,
            settings=settings.to_dict(),
            final_similarity=result.get("final_similarity"),
            eval_psnr_db=result.get("eval_psnr_db"),
            light_components=run.field.light.describe(),
        )
        meta = metadata(
            stage="optimize",
            settings=settings.to_dict(),
            seed=settings.seed,
            inputs={
                "train": train_path,
                "eval": eval_path,
                **({"targets": targets_path} if targets else {}),
                **({"light_map": Path(settings.light_map)} if "sha256" in run.light_record else {}),
            },
            outputs={k: out_dir / v for k, v in OPTIMIZE_FILES.items()},
            timings=timings,
            extra={
                **record.stats(),
                **_how_it_ran(run, dev),
                "resumed_from_iteration": resumed_from,
                "seconds_per_iteration": loop_s / iters_here,
                "points_per_iteration": run.points_total / max(run.steps_taken, 1),
                "parameters": sum(p.numel() for p in run.field.parameters()),
                "light_energy": run.field.light.energy().tolist(),
                "light_lobes": run.field.light.lobes,
                "light_pruned": run.light_pruned,
                "light": run.light_record,
                "suns": run.suns_record,
                "bounces": {**run.bounces_record, "refreshes": run.bounce_refreshes},
                **result,
            },
        )
        write_json_atomic(staging / "meta.json", meta)
    remove(ckpt)
    return meta


def _how_it_ran(run: Optimizer, dev: torch.device) -> dict:
    """What the run ran on and in, for the metadata: the device and the CPU (its instruction set and
    features: what the timings and bfloat16's choice depend on), CLIP's and the networks'
    precision, the renderer, what the C allocator does with freed memory, who runs the float32
    linear layers (oneDNN or ATen), the shadows cast (from
    the cache's visibility, or none and why) and the guidance's origin."""
    return {
        "device": str(dev),
        "cpu": cpu_isa(),
        "clip_precision": run.guidance.clip_precision,
        "clip_tower": run.guidance.clip_tower,
        "network_precision": run.network_precision,
        "shading_path": run.shading_path,
        "allocator": run.allocator,
        "float32_products": run.float32_products,
        "shadows": shadow_record(run.field.shadows, run.views.cache.visibility_directions),
        ORIGIN_KEY: run.guidance.origin,
    }


def _resume(run: Optimizer, ckpt: Path, settings: OptimizeSettings, dev) -> int | None:
    """Resume ``run`` from the checkpoint when it was written under the same settings and light;
    the iteration it resumed from, or None (a checkpoint of other settings is ignored)."""
    state = read_torch_file(ckpt, dev, remedy="Delete it to start this optimisation afresh.")
    if state.get("digest") != settings.digest():
        log.warning("ignoring %s: written under other settings", ckpt)
        return None
    if state.get("light", run.light_record) != run.light_record:  # light: fixed, its map's file edited since
        log.warning("ignoring %s: written under another light (%s)", ckpt, state.get("light"))
        return None
    try:
        run.load(state)
    except (KeyError, TypeError, ValueError, RuntimeError, IndexError, AttributeError) as err:
        why = " ".join(f"{type(err).__name__}: {err}".split())[:160]
        raise StageInputError(ckpt, f"is not a checkpoint of this optimisation ({why})", "Delete it to start afresh.") from None
    log.info("resumed from %s at iteration %d", ckpt, run.iteration)
    return run.iteration


def _write_outputs(run: Optimizer, eval_path: Path, out_dir: Path, settings: OptimizeSettings, prompt: str) -> dict:
    trained = run.field.eval()
    eval_views = ViewStore(RayCache(eval_path), run.device, run.field.normals, shadows=run.field.shadows)
    renders = {k: [] for k in RENDER_KINDS}
    views = [eval_views[i] for i in range(len(eval_views))]
    for v in views:
        r = render_view(trained, v, eval_views.width, settings.eval_width)
        for k in RENDER_KINDS:
            renders[k].append(r[k])
    score = run.guidance.eval_score(renders["rgb"], views, eval_views.width, settings.eval_width)
    columns = len(eval_views.azimuths())
    for k, imgs in renders.items():
        save_png(out_dir / "renders" / f"{k}.png", contact_sheet(imgs, columns))
    result: dict = {
        "eval_views": len(eval_views),
        "sheet": {"columns": int(columns), "tile": settings.eval_width, "front_view": eval_views.cache.front_view()},
        **score.figures,
    }
    if score.targets:
        save_png(out_dir / "renders" / "target.png", contact_sheet(score.targets, columns))
    # the light: equirectangular radiance (linear, float32), each component's arrays, and a
    # tone-mapped preview
    with torch.no_grad():
        light = trained.light()
        radiance = light.equirect(128, 256)
    with atomic_stream(out_dir / "light.npz") as fh:
        np.savez(fh, equirect=radiance.cpu().numpy().astype(np.float32), **light.arrays())
    preview = linear_to_srgb(radiance / radiance.max().clamp(min=1e-12))
    save_png(out_dir / "renders" / "light.png", (preview.cpu().numpy() * 255).round().astype(np.uint8))
    # the field and the loss curve
    save_field(out_dir / "field.pt", trained, settings, prompt, run.guidance.origin)
    write_loss_csv(out_dir / "loss.csv", run.history)
    title = f"{prompt} ({run.guidance.weights_id})"
    plot_loss(out_dir / "loss.png", run.history, title)
    return result


def shadow_record(cast: bool, directions: int) -> dict:
    """Whether the field cast shadows (``optimize.shadows`` and a cache with visibility) and why."""
    if not directions:
        return {"cast": False, "why": "the ray cache holds no visibility (raycache.visibility)"}
    if not cast:
        return {"cast": False, "why": "optimize.shadows: false", "directions": directions}
    return {"cast": True, "why": f"visibility of {directions} directions per hit", "directions": directions}


def main(argv: list[str] | None = None) -> int:
    def arguments(parser):
        parser.add_argument("--train", required=True, type=Path, help="training ray cache (.npz)")
        parser.add_argument("--eval", required=True, type=Path, help="evaluation ray cache (.npz)")
        parser.add_argument("--prompt", required=True, help="text prompt (CLIP guidance)")
        parser.add_argument("--out-dir", required=True, type=Path)
        parser.add_argument("--settings", default="{}", help="JSON of the optimize settings")
        parser.add_argument("--targets", type=Path, default=None, help="Mitsuba image targets of --train (target stage)")

    def body(args):
        settings = OptimizeSettings.from_json(args.settings)
        run(args.train, args.eval, args.prompt, args.out_dir, settings, args.device, targets_path=args.targets)

    return stage_main("optimize", __doc__, arguments, body, argv, device="auto")


if __name__ == "__main__":
    raise SystemExit(main())
