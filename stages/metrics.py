"""metrics: quality numbers of one grid cell on fixed metric views (the X-Mesh protocol: 8
azimuths x elevations -30/0/30 degrees, radius 2.5, 45-degree field of view, 224 x 224, white
background; see the raycache stage's ``metrics_*`` settings).

* ``guidance``: cosine similarity of the prompt with the renders under the guidance model (the
  CLIP the optimisation used), averaged over views;
* ``evaluation``: the CLIP score (100 x mean cosine similarity) under an *independent* evaluation
  model (``metrics.clip_model`` / ``clip_pretrained`` / ``clip_checkpoint``) and R-precision over
  the grid's prompts (the fraction of views whose render ranks its own prompt first among the
  ``candidates`` prompts of the grid);
* ``image_target`` (image-guided runs): PSNR and SSIM of the renders against the procedural
  targets on the same (held-out) views, over the whole 224 x 224 frames.

Every number sits under the id of the weights that produced it, with ``test_only: true`` for the
tiny random test CLIP; the report never mixes those with real ones in a table.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import torch
from torch.nn import functional as F

from .errors import StageInputError, stage_errors
from .provenance import (
    ORIGIN_KEY,
    Timer,
    add_torch_arguments,
    apply_torch_arguments,
    metadata,
    staged_outputs,
    write_json_atomic,
)
from .settings import Settings

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class MetricsSettings(Settings):
    """Settings of the metrics stage (config section ``metrics``)."""

    section = "metrics"
    #: compute the CLIP-based metrics (needs weights, or clip_tiny_test)
    clip: bool = True
    #: the independent evaluation model (open_clip name, pretrained tag or local checkpoint)
    clip_model: str = "ViT-B-16"
    clip_pretrained: str = "openai"
    clip_checkpoint: str | None = None
    clip_tiny_test: bool = False
    background: str = "white"


def ssim(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None, window: int = 11, sigma: float = 1.5) -> float:
    """Mean structural similarity (Wang et al. 2004) of images ``(B, 3, H, W)`` in [0, 1]:
    Gaussian window 11 / 1.5, constants ``(0.01)^2`` and ``(0.03)^2``, per channel, 'valid'
    windows only, averaged over every window or, with ``mask (B, 1, H, W)`` bool, over the
    windows centred on object pixels (so the background does not count)."""
    c1, c2 = 0.01**2, 0.03**2
    x = torch.arange(window, dtype=a.dtype) - (window - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    g = (g / g.sum()).to(a.device)
    k = (g[:, None] * g[None, :])[None, None].repeat(a.shape[1], 1, 1, 1)

    def blur(t):
        return F.conv2d(t, k, groups=a.shape[1])

    mu_a, mu_b = blur(a), blur(b)
    saa = blur(a * a) - mu_a**2
    sbb = blur(b * b) - mu_b**2
    sab = blur(a * b) - mu_a * mu_b
    num = (2 * mu_a * mu_b + c1) * (2 * sab + c2)
    den = (mu_a**2 + mu_b**2 + c1) * (saa + sbb + c2)
    smap = num / den
    if mask is None:
        return float(smap.mean())
    h = (window - 1) // 2
    centre = mask[:, :, h : mask.shape[2] - h, h : mask.shape[3] - h].expand_as(smap)
    return float(smap[centre].mean())


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(F.mse_loss(a, b))
    return float("inf") if mse == 0 else 10.0 * math.log10(1.0 / mse)


@torch.no_grad()
def render_metric_views(field, store, background: str) -> torch.Tensor:
    """All metric views rendered at the cache's resolution: ``(V, 3, S, S)`` sRGB in [0, 1]."""
    from .imaging import linear_to_srgb, render_cached_view

    def colors(p, n, d):
        return linear_to_srgb(field(p, n, d).shading.rgb)

    bg = 1.0 if background == "white" else 0.0
    return torch.stack([render_cached_view(store[i], store.width, store.width, colors, bg) for i in range(len(store))])


def _resize(imgs: torch.Tensor, size: int) -> torch.Tensor:
    if imgs.shape[-1] == size:
        return imgs
    return F.interpolate(imgs, size=(size, size), mode="bicubic", align_corners=False).clamp(0, 1)


@torch.no_grad()
def clip_metrics(guide, imgs: torch.Tensor, prompt: str, candidates: list[str]) -> dict:
    """CLIP score of ``prompt`` and R-precision among ``candidates`` (which include ``prompt``)."""
    x = _resize(imgs, guide.image_size)
    emb = F.normalize(guide.embed_images(x), dim=-1)  # (V, D)
    texts = torch.stack([guide.embed_text(t) for t in candidates])  # (P, D)
    sims = emb @ texts.T  # (V, P)
    own = candidates.index(prompt)
    top = sims.argmax(1)
    return {
        "weights": guide.weights_id,
        "test_only": guide.test_only,
        "clip_score": float(100.0 * sims[:, own].mean()),
        "similarity_mean_embedding": float(F.cosine_similarity(emb.mean(0), texts[own], dim=0)),
        "r_precision": float((top == own).float().mean()),
        "candidates": len(candidates),
        "views": int(len(imgs)),
    }


def run(
    field_path: Path,
    metrics_cache: Path,
    prompt: str,
    candidates: list[str],
    out_dir: Path,
    settings: MetricsSettings,
    device: str = "cpu",
) -> dict:
    from .guidance import ClipSpec, load_clip
    from .optimize import Objective, ViewStore, contact_sheet, load_field, render_target, save_png, settings_eval_azimuths
    from .raycache import RayCache

    timer = Timer()
    for p in (field_path, metrics_cache):
        if not Path(p).is_file():
            raise StageInputError(p, "file not found", "Run the optimize and raycache stages first.")
    if prompt not in candidates:
        candidates = [prompt, *candidates]
    dev = torch.device(device)
    field, opt_settings = load_field(field_path, dev)
    store = ViewStore(RayCache(metrics_cache), dev)
    with timer("render"):
        imgs = render_metric_views(field, store, settings.background)
    out_dir = Path(out_dir)
    with staged_outputs(out_dir) as staging:
        save_png(staging / "views.png", contact_sheet(list(imgs), len(settings_eval_azimuths(store))))
        result: dict = {"prompt": prompt, ORIGIN_KEY: field.origin}
        result["protocol"] = {
            "views": len(store),
            "resolution": store.width,
            "fov_deg": float(store.cache.arrays["fov_deg"]),
            "radius": float(store.cache.arrays["radius"][0]),
            "background": settings.background,
        }
        if opt_settings.guidance == "clip":
            with timer("guidance"):
                g = load_clip(
                    ClipSpec(
                        opt_settings.clip_model,
                        opt_settings.clip_pretrained,
                        opt_settings.clip_checkpoint,
                        opt_settings.clip_tiny_test,
                    ),
                    device=dev,
                )
                m = clip_metrics(g, imgs, prompt, candidates)
                result["guidance"] = {
                    "weights": m["weights"],
                    "test_only": m["test_only"],
                    "similarity": m["similarity_mean_embedding"],
                }
        if settings.clip:
            with timer("evaluation"):
                e = load_clip(
                    ClipSpec(
                        settings.clip_model,
                        settings.clip_pretrained,
                        settings.clip_checkpoint,
                        settings.clip_tiny_test,
                    ),
                    device=dev,
                )
                result["evaluation"] = clip_metrics(e, imgs, prompt, candidates)
        if opt_settings.guidance == "image":
            with timer("image_target"):
                obj = Objective(opt_settings, prompt, dev)
                bg = 1.0 if settings.background == "white" else 0.0
                pairs = [render_target(obj, store[i], store.width, store.width, bg) for i in range(len(store))]
                t = torch.stack([img for img, _ in pairs])
                mask = torch.stack([m for _, m in pairs])
                px = mask.expand_as(t)
                result["image_target"] = {
                    "weights": obj.weights_id,
                    "psnr_db": psnr(imgs[px], t[px]),
                    "ssim": ssim(imgs, t, mask),
                    "pixels": "object pixels of the held-out metric views (SSIM: windows centred on them)",
                    "target_light": opt_settings.target_light,
                    "target_material": opt_settings.target_material,
                }
                save_png(staging / "targets.png", contact_sheet(list(t), len(settings_eval_azimuths(store))))
        write_json_atomic(staging / "metrics.json", result)
        write_json_atomic(
            staging / "meta.json",
            metadata(
                stage="metrics",
                settings=settings.to_dict(),
                inputs={"field": field_path, "metrics_cache": metrics_cache},
                outputs={"metrics": out_dir / "metrics.json", "views": out_dir / "views.png"},
                timings={**timer.seconds, "total": timer.total()},
                extra={"candidates": candidates, ORIGIN_KEY: field.origin},
            ),
        )
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m stages.metrics", description=__doc__.split("\n")[0])
    parser.add_argument("--field", required=True, type=Path)
    parser.add_argument("--metrics-cache", required=True, type=Path)
    parser.add_argument("--prompt", required=True)
    parser.add_argument("--candidates", default="[]", help="JSON list of the grid's prompt texts for this mesh")
    parser.add_argument("--out-dir", required=True, type=Path)
    parser.add_argument("--settings", default="{}")
    add_torch_arguments(parser, "cpu")
    args = parser.parse_args(argv)
    apply_torch_arguments(args)
    from .guidance import ClipWeightsUnavailable

    with stage_errors("metrics") as status:
        try:
            run(
                args.field,
                args.metrics_cache,
                args.prompt,
                json.loads(args.candidates),
                args.out_dir,
                MetricsSettings.from_json(args.settings),
                args.device,
            )
        except ClipWeightsUnavailable as exc:
            raise StageInputError(None, str(exc)) from exc
    return status.code


if __name__ == "__main__":
    raise SystemExit(main())
