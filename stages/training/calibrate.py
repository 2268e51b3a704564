"""How long one optimisation step of given settings takes on this machine, measured.

A short real run of the optimiser: the built-in vase, a training pool of a few views traced at
the cell's ray-cache settings (a step renders ``views_per_step`` views of the pool, so its cost
does not depend on the pool's size), with what its guidance mode's ``calibration`` names
(:data:`CALIBRATIONS`): the settings' CLIP architecture with random weights (the same arithmetic
as the real weights; none need be downloaded) or targets from our own renderer; one warm-up step,
then ``steps`` timed steps.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from functools import cache

import numpy as np

from ..config.sections import NormalizeSettings, OptimizeSettings, RaycacheSettings
from ..core.errors import ConfigError
from ..core.provenance import Timer
from ..geometry.normalization import normalize_mesh
from ..geometry.raycache import RayCache, trace_cache_visibility, trace_views, training_views
from ..geometry.tracing import EmbreeTracer, make_tracer
from ..guidance.clip import TINY_MODEL, ClipGuide, load_clip, register_tiny_model
from ..guidance.compat import import_open_clip
from .optimizer import Optimizer

log = logging.getLogger(__name__)


@cache
def random_guide(model_name: str, bf16: bool, tower: str, device: str) -> ClipGuide:
    """A CLIP architecture with random weights (timing only: marked test-only); made once per
    process for each architecture and precision."""
    import torch

    open_clip = import_open_clip()
    if model_name == TINY_MODEL:
        register_tiny_model()
    torch.manual_seed(0)
    model = open_clip.create_model(model_name, pretrained=None, device=device)
    size = model.visual.image_size
    return ClipGuide(
        model,
        open_clip.get_tokenizer(model_name),
        image_size=int(size[0] if isinstance(size, tuple | list) else size),
        weights_id="calibration: random weights",
        test_only=True,
        device=device,
        bf16=bf16,
        tower=tower,
    )


@cache
def _pool(raycache: RaycacheSettings, visibility: bool = False) -> RayCache:
    """The built-in vase traced with these ray-cache settings, once per process; with
    ``visibility`` its hits' visibility bits too (``raycache.visibility_directions``, traced
    through Embree as the raycache stage traces them), as a run with shadows needs them."""
    mesh = normalize_mesh("builtin:vase", NormalizeSettings()).mesh
    arrays, _ = trace_views(mesh, training_views(raycache), make_tracer(mesh, raycache.backend))
    if visibility:
        arrays["visibility"] = trace_cache_visibility(arrays, EmbreeTracer(mesh), raycache.visibility_directions)
        arrays["visibility_directions"] = np.int64(raycache.visibility_directions)
    return RayCache("calibration: built-in vase", arrays)


def _clip_calibration(settings: OptimizeSettings, device) -> tuple[OptimizeSettings, ClipGuide | None]:
    """The guidance CLIP's architecture with random weights (the tiny test CLIP itself)."""
    if settings.clip_tiny_test:
        return settings, load_clip(settings.clip_spec(), device, settings.bf16, settings.clip_tower)
    return settings, random_guide(settings.clip_model, settings.bf16, settings.clip_tower, str(device))


def _own_targets_calibration(settings: OptimizeSettings, device) -> tuple[OptimizeSettings, ClipGuide | None]:
    """Image targets from our own renderer: Mitsuba's are rendered once per mesh by the target
    stage (the plan counts those apart), and a step costs the same with either."""
    return dataclasses.replace(settings, target_renderer="sg"), None


#: how a step of each guidance mode is timed (its row's ``calibration``): the settings to time
#: and the CLIP to time them with (None: the guidance loads none)
CALIBRATIONS: dict[str, Callable[[OptimizeSettings, object], tuple[OptimizeSettings, ClipGuide | None]]] = {
    "clip": _clip_calibration,
    "own_targets": _own_targets_calibration,
}


def calibration(settings: OptimizeSettings, device) -> tuple[OptimizeSettings, ClipGuide | None]:
    """The settings and the CLIP that time a step of ``settings``' guidance mode; a mode whose
    calibration this module does not know is a :class:`ConfigError`, never another mode's timing."""
    mode = settings.guidance_mode()
    if mode.calibration not in CALIBRATIONS:
        raise ConfigError(
            f"guidance {mode.name!r} is timed by calibration {mode.calibration!r}, which stages.training.calibrate "
            f"does not know (it knows {', '.join(CALIBRATIONS)}): add it to CALIBRATIONS"
        )
    return CALIBRATIONS[mode.calibration](settings, device)


def seconds_per_step(settings: OptimizeSettings, raycache: RaycacheSettings, device, steps: int = 2) -> float:
    """Wall seconds of one optimisation step of ``settings`` on ``device`` (mean of ``steps``
    steps after one warm-up step)."""
    # shadows where the cache will carry visibility for certain (raycache.visibility: on) or a bounce
    # needs it: the vase is traced with it; visibility: auto (decided by each mesh) is timed without
    visibility = settings.shadows and (settings.bounces == 1 or raycache.visibility == "on")
    train = _pool(dataclasses.replace(raycache, views=max(2, settings.views_per_step)), visibility)
    settings, guide = calibration(settings, device)
    # the eager renderer: a compiled one (compile_shading) would spend its compilation, 13 s to
    # 94 s, inside the plan; the estimate of a compiled run is then on the slow side. The levers
    # that ride on it off too: asked for without it, they would only warn that they cannot run.
    # The C allocator as it is: the plan runs inside Snakemake's own process, which would otherwise
    # keep the calibration's memory for the whole workflow (the estimate errs on the slow side again)
    settings = dataclasses.replace(
        settings, compile_shading="off", compile_networks="off", compile_static="off", keep_freed_memory="off"
    )
    opt = Optimizer(settings, train, "a vase made of wood", device, guide=guide)
    timer = Timer()
    opt.step(timer)
    t0 = time.perf_counter()
    for _ in range(steps):
        opt.step(timer)
    seconds = (time.perf_counter() - t0) / steps
    log.info("calibration: %.3f s per step (%s, %d timed steps)", seconds, settings.clip_model, steps)
    return seconds
