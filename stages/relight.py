"""relight: re-render a finished result under another environment map, and edit its material.

The environment map (an equirectangular ``.hdr`` or ``.exr``, or ``builtin:<name>`` for a
procedural one, see :mod:`stages.render.envmap`) is fitted by SG lobes (least squares over the
sphere, :func:`stages.model.lights.sg.fit_sg_light`, and suns where the field has them and the map
holds any: :func:`stages.model.lights.fit_environment_like`), so the field's own forward pass renders it (a
light override, a light of those lobes alone). Outputs: ``relit.png`` (the evaluation views under
the new light), ``material_edit.png`` (TANGO's material-editing figure: the front view, rows =
roughness scales, columns = specular scales, under the new light), ``light_fit.png`` (the map and
its SG fit) and ``meta.json`` (fit error, mean brightness of each image); for a graded cell also ``ground_truth.png`` (per judge
environment: the field relit, Mitsuba's truth and 4 x their difference on the metric views).

For an image-guided cell with Mitsuba targets the relighting is also *graded*: the target stage
rendered the true material on the held-out metric views under each of
``target.relight_environments``, and the field relit under each of them is compared with it
(object-pixel PSNR; :mod:`stages.imaging.relit`), beside the ceiling of the true material in our
renderer. A blurred light or shadows painted into the albedo fail this even when the
training-light PSNR looks good.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch

from .config.records import RelightRecord
from .config.sections import RelightSettings
from .core.cli import stage_main
from .core.errors import StageInputError
from .core.provenance import ORIGIN_KEY, Timer, metadata, staged_outputs, write_json_atomic
from .core.safefiles import remove
from .geometry.raycache import RayCache
from .imaging.images import render_cached_view
from .imaging.relit import comparison_rows, grade_relighting
from .imaging.sheets import annotate, contact_sheet, save_png
from .imaging.targets import TargetSet, load_relit
from .imaging.views import ViewStore
from .model.checkpoint import load_field
from .model.field import MaterialEdit
from .model.lights import fit_environment_like
from .render.color import linear_to_srgb, srgb_encode, to_u8
from .render.envmap import load_env

log = logging.getLogger(__name__)


@torch.no_grad()
def render_edit(field, view, width: int, out: int, light, edit: MaterialEdit | None = None):
    """One cached view through the field's forward pass under ``light`` with the material edited
    by ``edit`` -> ``(3, out, out)`` sRGB."""

    def colors(v, sel):
        return linear_to_srgb(v.shade(field, sel, light, edit).shading.rgb)

    return render_cached_view(view, width, out, colors)


#: the most metric views the comparison with the truth shows per row
TRUTH_SHEET_VIEWS = 8


def _truth_sheet(store: ViewStore, relit, renders: dict, width: int) -> np.ndarray:
    """``ground_truth.png``: per environment three rows over the metric views of the front view's
    elevation (at most :data:`TRUTH_SHEET_VIEWS`): the field relit, Mitsuba's truth, 4 x |difference|."""
    elevation = store.cache.arrays["elevation"]
    ring = np.flatnonzero(np.isclose(elevation, elevation[store.cache.front_view()]))[:TRUTH_SHEET_VIEWS].tolist()
    images = [img for r in relit for img in comparison_rows(store, ring, renders[r.environment], r.radiance, width)]
    rows = [f"{r.environment}: {what}" for r in relit for what in ("ours, relit", "Mitsuba, true material", "4 x |difference|")]
    return annotate(
        contact_sheet(images, len(ring)),
        f"Relit against the truth, held-out views at elevation {float(elevation[ring[0]]):.0f} deg (sRGB)",
        columns=_azimuth_labels(store, ring),
        rows=rows,
        scale=("0", "0.25", "|difference| of sRGB values, per channel, times 4 (clipped at 0.25)"),
    )


def _azimuth_labels(store: ViewStore, views: list[int]) -> list[str]:
    return [f"azimuth {float(store.cache.arrays['azimuth'][i]):.0f} deg" for i in views]


def _material_edit(field, store: ViewStore, front: int, light, settings: RelightSettings, path: Path) -> list:
    """``material_edit.png``: the front view under the new light, rows = roughness scales, columns =
    specular scales, labelled; returns the renders."""
    grid = [
        render_edit(field, store[front], store.width, settings.width, light, MaterialEdit(rs, ss))
        for rs in settings.roughness_scales
        for ss in settings.specular_scales
    ]
    edit = annotate(
        contact_sheet(grid, len(settings.specular_scales)),
        f"Material editing, front view under {settings.envmap}",
        columns=[f"specular x {x:g}" for x in settings.specular_scales],
        rows=[f"roughness x {x:g}" for x in settings.roughness_scales],
    )
    save_png(path, edit)
    return grid


def _light_fit_sheet(env: np.ndarray, light, settings: RelightSettings) -> np.ndarray:
    """``light_fit.png``: the new environment above its fit, both divided by the map's peak, labelled."""
    h, w = env.shape[:2]
    fit = light.equirect(h, w).cpu().numpy()
    top = max(float(env.max()), 1e-12)
    both = np.concatenate([env, fit], axis=0) / top
    return annotate(
        to_u8(srgb_encode(both)),
        f"{settings.envmap} (equirectangular) and its fit",
        rows=[settings.envmap, f"its fit ({settings.lobes} SG lobes)"],
        scale=("0", f"{top:.3g}", "radiance, both divided by the map's peak (sRGB encoded)"),
    )


def run(
    field_path: Path,
    eval_path: Path,
    out_dir: Path,
    settings: RelightSettings,
    device: str = "cpu",
    truth_path: Path | None = None,
    targets_path: Path | None = None,
    metrics_cache: Path | None = None,
) -> dict:
    """Relight the field (figures), and with ``truth_path`` (the target stage's ``relit.npz``, with
    the metric-view cache ``metrics_cache`` it belongs to and that cache's targets
    ``targets_path``, which carry the true material) grade its relighting against Mitsuba's."""
    timer = Timer()
    graded = truth_path is not None
    if graded and (targets_path is None or metrics_cache is None):
        raise StageInputError(truth_path, "relit ground truth given without --targets and --metrics", "Pass all three.")
    for p in (field_path, eval_path, *((truth_path, targets_path, metrics_cache) if graded else ())):
        if not Path(p).is_file():
            raise StageInputError(p, "file not found", "Run the optimize stage first.")
    dev = torch.device(device)
    field, _ = load_field(field_path, dev)
    store = ViewStore(RayCache(eval_path), dev, field.normals, shadows=field.shadows)
    with timer("fit"):  # the field's transport: suns where it has them and the map holds any
        env = load_env(settings.envmap)
        fitted, fit_record = fit_environment_like(
            field.light, settings.envmap, settings.lobes, settings.fit_iterations, store.cache.visibility_directions
        )
    light = store.light_of(field, fitted.to(dev))  # where the field bounces, its bounce under this light
    out_dir = Path(out_dir)
    with staged_outputs(out_dir) as staging:
        with timer("render"):
            views = [render_edit(field, store[i], store.width, settings.width, light) for i in range(len(store))]
            title = f"Relit under {settings.envmap}: the evaluation views (sRGB)"
            save_png(staging / "relit.png", annotate(contact_sheet(views, len(store.azimuths())), title))
            front = store.cache.front_view()
            grid = _material_edit(field, store, front, light, settings, staging / "material_edit.png")
            save_png(staging / "light_fit.png", _light_fit_sheet(env, light, settings))
        ground_truth = []
        if graded:
            with timer("ground_truth"):
                cache = RayCache(metrics_cache)
                metric = ViewStore(cache, dev, field.normals, shadows=field.shadows)
                relit, truth = load_relit(truth_path, cache), TargetSet(targets_path, cache)
                renders: dict = {}
                ground_truth = grade_relighting(field, metric, relit, truth, settings.lobes, settings.fit_iterations, renders)
                save_png(staging / "ground_truth.png", _truth_sheet(metric, relit, renders, settings.width))
            for g in ground_truth:
                log.info(
                    "relit under %s: %.2f dB against Mitsuba's truth (ceiling %.2f dB)",
                    g["environment"],
                    g["psnr_db"],
                    g.get("ceiling_psnr_db", float("nan")),
                )
        stats = {
            **RelightRecord(ground_truth=ground_truth).stats(),
            "envmap": settings.envmap,
            **fit_record,
            "mean_relit": float(torch.stack(views).mean()),
            "mean_material_edit": [float(g.mean()) for g in grid],
            "front_view": front,
        }
        write_json_atomic(
            staging / "meta.json",
            metadata(
                stage="relight",
                settings=settings.to_dict(),
                inputs={
                    "field": field_path,
                    "eval": eval_path,
                    **({"truth": truth_path, "targets": targets_path, "metrics_cache": metrics_cache} if graded else {}),
                },
                outputs={
                    k: out_dir / f"{k}.png"
                    for k in ("relit", "material_edit", "light_fit", *(("ground_truth",) if graded else ()))
                },
                timings={**timer.seconds, "total": timer.total()},
                extra={"stats": stats, ORIGIN_KEY: field.origin},
            ),
        )
    if not graded:  # a comparison left by an earlier, graded run is not this run's (removed once this run's files are in)
        remove(out_dir / "ground_truth.png")
    return stats


def main(argv: list[str] | None = None) -> int:
    def arguments(parser):
        parser.add_argument("--field", required=True, type=Path)
        parser.add_argument("--eval", required=True, type=Path)
        parser.add_argument("--out-dir", required=True, type=Path)
        parser.add_argument("--settings", default="{}")
        parser.add_argument("--truth", type=Path, default=None, help="the target stage's relit.npz (image-guided cells)")
        parser.add_argument("--targets", type=Path, default=None, help="the metric views' targets (the true material)")
        parser.add_argument("--metrics", type=Path, default=None, help="the metric-view ray cache of --truth")

    def body(args):
        run(
            args.field,
            args.eval,
            args.out_dir,
            RelightSettings.from_json(args.settings),
            args.device,
            args.truth,
            args.targets,
            args.metrics,
        )

    return stage_main("relight", __doc__, arguments, body, argv, device="cpu")


if __name__ == "__main__":
    raise SystemExit(main())
