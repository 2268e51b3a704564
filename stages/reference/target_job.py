"""A mesh's image targets as the target stage makes them: the training and held-out metric views
path-traced by Mitsuba 3 through the ray caches' own cameras (:class:`~.targets.TargetRenderer`),
the material's ground truth at the metric hits, the metric views relit under each of
``target.relight_environments``, and what the stage records of them (noise, coverage, speed)."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch

from ..config.sections import TargetSettings
from ..core.provenance import Timer
from ..geometry.meshio import TriMesh
from ..geometry.raycache import RayCache
from ..imaging.sheets import contact_sheet
from ..render.color import srgb_encode
from .targets import TargetRenderer, ViewTargets, truth_at_senders

log = logging.getLogger(__name__)

#: seed offsets of the metric views and of each relit environment (the training views use the
#: seed itself), so that no two renders share samples
METRIC_SEED, RELIT_SEED, RELIT_STRIDE = 500_009, 700_001, 7919


def describe(kind: str, settings: TargetSettings, variant: str) -> str:
    """The one line that names these targets wherever a result made from them goes."""
    return (
        f"Mitsuba 3 ({variant}) path-traced {kind} (principled BSDF, textures, normal map, "
        f"{settings.shading_normals} normals) under "
        f"{settings.environment}, {settings.spp} spp (metric views {settings.metric_spp}), max depth {settings.max_depth}"
    )


@dataclass
class MeshTargets:
    """One mesh's targets in one material: the ``renderer`` (its scene and the truth), the training
    and metric views' renders, the ``truth`` at the metric hits and which of them ``missing`` the
    rendered mesh, each relit environment's render and light energy, the ``text`` that names
    them, and the truth at the metric cache's face sides (``senders``)."""

    renderer: TargetRenderer
    train: ViewTargets
    metrics: ViewTargets
    truth: dict
    missing: np.ndarray
    relit: dict[str, tuple[ViewTargets, np.ndarray]]
    text: str
    #: the truth at the metric cache's face sides (:func:`~stages.reference.targets.truth_at_senders`)
    senders: dict | None = None


def metric_seeds(settings: TargetSettings) -> list[tuple[str, int]]:
    """The environment and seed of each render of the metric views, in the targets' order: the
    training environment's, then each of ``target.relight_environments`` (the training views use
    :func:`base_seed` itself)."""
    seed = base_seed(settings)
    relit = [(env, seed + RELIT_SEED + RELIT_STRIDE * j) for j, env in enumerate(settings.relight_environments)]
    return [(settings.environment, seed + METRIC_SEED), *relit]


def base_seed(settings: TargetSettings) -> int:
    """The seed of the training views' renders, from ``target.seed``."""
    return settings.seed * 1_000_003


def render_targets(
    mesh: TriMesh, material: str, settings: TargetSettings, caches: tuple[RayCache, RayCache], timer: Timer
) -> MeshTargets:
    """Render ``mesh`` in ``material`` from the training and metric ``caches`` (each step timed in
    ``timer``); a metric hit whose ray misses the rendered (finer) mesh is no object pixel."""
    train, metric = caches
    (_, metric_seed), *relit_seeds = metric_seeds(settings)
    with timer("scene"):
        renderer = TargetRenderer(mesh, material, settings)
    text = describe(material, settings, renderer.variant)
    log.info("rendering %s", text)
    with timer("render_train"):
        tt = renderer.render_cache(train, settings.spp, base_seed(settings))
    with timer("render_metrics"):
        tm = renderer.render_cache(metric, settings.metric_spp, metric_seed)
    with timer("truth"):
        truth, met = renderer.truth_at_hits(metric)
        senders = truth_at_senders(renderer.truth, mesh, metric.mesh())  # what a bounce's ceiling sends
    tm.coverage[~met] = 0.0
    relit = {}
    with timer("render_relit"):
        for env, relit_seed in relit_seeds:
            judge = TargetRenderer(mesh, material, settings, environment=env, truth=renderer.truth)
            t = judge.render_cache(metric, settings.metric_spp, relit_seed)
            t.coverage[~met] = 0.0
            relit[env] = (t, judge.env_energy)
            log.info("relit ground truth under %s: noise PSNR %.1f dB, %.1f s", env, t.noise_psnr_db, t.seconds)
    return MeshTargets(renderer, tt, tm, truth, ~met, relit, text, senders)


def view_summary(t: ViewTargets, spp: int, width: int, missing: np.ndarray | None = None) -> dict:
    """What the stage records of one view set's targets: views, samples, the measured noise,
    coverage and speed (``missing``: the metric hits that miss the rendered mesh)."""
    summary = {
        "views": len(t.pixels),
        "spp": spp,
        "noise_psnr_db": t.noise_psnr_db,
        "noise_rms_srgb": float(np.sqrt((t.noise_mse * t.pixels).sum() / max(t.pixels.sum(), 1))),
        "noise_measured_on": "fully covered object pixels, sRGB: half the squared difference of two half-sample renders",
        "partly_covered_hits": float((t.coverage < 0.999).mean()),
        **({"hits_missing_the_rendered_mesh": int(missing.sum())} if missing is not None else {}),
        "uncovered_hits": int((t.coverage <= 0).sum()),
        "render_seconds": t.seconds,
    }
    summary["samples_per_second"] = len(t.pixels) * width * width * spp / max(t.seconds, 1e-9)
    return summary


def target_sheet(cache: RayCache, radiance: np.ndarray) -> torch.Tensor:
    """The targets of every view of ``cache`` (linear radiance per hit) as one sRGB contact sheet,
    one column per azimuth."""
    tiles = []
    offsets = cache.arrays["offsets"]
    w = cache.width
    for i in range(len(cache)):
        img = np.zeros((w * w, 3))
        img[cache.arrays["pixel"][offsets[i] : offsets[i + 1]]] = srgb_encode(radiance[offsets[i] : offsets[i + 1]])
        tiles.append(torch.from_numpy(img.reshape(w, w, 3)).permute(2, 0, 1).float())
    return contact_sheet(tiles, len(np.unique(np.round(cache.arrays["azimuth"], 9))))


def material_sheet(renderer: TargetRenderer, texture_size: int) -> torch.Tensor:
    """The true material's base colour, roughness, metallic and normal textures side by side (a
    preview: at most 512 pixels a side)."""
    g = renderer.truth
    textures = [srgb_encode(g.base_color), np.repeat(g.roughness, 3, -1), np.repeat(g.metallic, 3, -1), 0.5 * g.normal + 0.5]
    step = max(1, texture_size // 512)
    tiles = [torch.from_numpy(np.ascontiguousarray(t[::step, ::step])).permute(2, 0, 1).float().clamp(0, 1) for t in textures]
    return contact_sheet(tiles, 4)
