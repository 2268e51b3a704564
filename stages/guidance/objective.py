"""The guidance of an optimisation, one class per mode behind one interface (:class:`Guidance`),
registered under its mode's name (:func:`register`) and chosen once by :func:`choose_guidance`
from ``optimize.guidance`` and, for a mode that fits image targets, ``optimize.target_renderer``:

* :class:`ClipGuidance` (``guidance: clip``, TANGO): CLIP similarity of the renders with the prompt;
* :class:`ImageGuidance` (``guidance: image``, ``target_renderer: mitsuba``): the squared error
  against ground truth path-traced by Mitsuba 3 (the target stage), stored per cached hit and
  attached to the views; nobody here rendered it;
* :class:`SGTargetGuidance` (``guidance: image``, ``target_renderer: sg``): the squared error
  against our own SG renders of a procedural material, on the fly (quick, but the renderer grades
  itself).

Image guidance verifies the whole optimisation without CLIP weights. Each records its ``origin``
(which guidance and weights made a result), which every downstream file carries, and scores the
held-out metric views its own way (:meth:`Guidance.held_out`, the metrics stage's). What the
rest of the workflow knows of a mode without torch (labels, what it needs, how the plan times it)
is its row in :mod:`stages.config.guidance_modes`, which each class carries as ``mode``: a new
mode is one row there and one class here.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import torch
from torch.nn import functional as F

from ..config.guidance_modes import GuidanceMode, guidance_mode
from ..config.sections import OptimizeSettings
from ..core.errors import ConfigError
from ..imaging.images import global_spec, render_cached_view
from ..imaging.quality import highlights, psnr, ssim
from ..imaging.targets import FULL_COVERAGE
from ..imaging.views import CachedView, ViewStore
from ..model.procedural import procedural_light, procedural_material
from ..render.color import linear_to_srgb
from ..render.shading import face_viewer
from .clip import ClipGuide, load_clip
from .scores import clip_metrics


@dataclass
class ImageBatch:
    """One step's images (sRGB, ``(3, H, W)`` each): every view's global image and the crops."""

    globals: list[torch.Tensor] = field(default_factory=list)
    crops: list[torch.Tensor] = field(default_factory=list)

    def add(self, images: list[torch.Tensor]) -> None:
        """A view's images: the global one first, then its crops."""
        self.globals.append(images[0])
        self.crops.extend(images[1:])


@dataclass
class EvalScore:
    """What a guidance measures on the evaluation views: ``figures`` for the stage's metadata and,
    where the guidance has them, the ``targets`` it compared with (sRGB ``(3, H, W)`` each)."""

    figures: dict
    targets: list[torch.Tensor] = field(default_factory=list)


@dataclass
class HeldOut:
    """What a guidance measures on the held-out metric views (the metrics stage): ``figures`` for
    ``metrics.json`` (under the class's :attr:`Guidance.held_out_key`) and, where the guidance has
    them, the ``targets`` it compared with (sRGB ``(V, 3, H, W)``)."""

    figures: dict
    targets: torch.Tensor | None = None


class Guidance(ABC):
    """What an optimisation minimises, how its result is scored on the evaluation views and on the
    held-out metric views. A subclass is registered under its mode (:func:`register`), which sets
    :attr:`mode`."""

    #: the mode's row (:mod:`stages.config.guidance_modes`), set by :func:`register`
    mode: ClassVar[GuidanceMode]
    #: where ``metrics.json`` records the figures of :meth:`held_out` (a field of ``MetricsRecord``)
    held_out_key: ClassVar[str]
    #: the id of the weights or targets that guide (for every output's origin record)
    weights_id: str
    #: whether that guidance is for tests only (the tiny random CLIP)
    test_only: bool = False
    #: what the guidance CLIP ran in, and its image tower's path (None: no CLIP)
    clip_precision: str | None = None
    clip_tower: str | None = None

    def __init__(self, settings: OptimizeSettings, prompt: str) -> None:
        self.settings = settings
        self.prompt = prompt

    @classmethod
    @abstractmethod
    def build(cls, settings: OptimizeSettings, prompt: str, device, guide: ClipGuide | None, targets: str | None) -> Guidance:
        """The guidance of an optimisation (:func:`choose_guidance`): ``guide``, an already loaded
        CLIP; ``targets``, the description of the Mitsuba targets attached to the views."""

    @classmethod
    def for_metrics(cls, settings: OptimizeSettings, prompt: str, device, targets: str | None) -> Guidance:
        """The guidance that scores the held-out metric views (the metrics stage's)."""
        return cls.build(settings, prompt, device, None, targets)

    @property
    def origin(self) -> dict:
        """The record of the guidance and weights that made a result (:meth:`GuidanceMode.origin_record`)."""
        return self.mode.origin_record(self.weights_id, self.test_only, self.prompt)

    def target_colors(self, v: CachedView, sel: torch.Tensor) -> torch.Tensor | None:
        """Linear radiance ``(M, 3)`` of the image target at the hits ``sel`` of view ``v``; None
        where the guidance has no image target."""
        return None

    @abstractmethod
    def loss(self, rendered: ImageBatch, target: ImageBatch | None) -> tuple[torch.Tensor, dict]:
        """The step's loss and its figures for the loss curve; ``target``: the images of
        :meth:`target_colors` composed like ``rendered`` (None where there are none)."""

    @abstractmethod
    def eval_score(self, renders: Sequence[torch.Tensor], views: Sequence[CachedView], width: int, out_width: int) -> EvalScore:
        """The trained field's score on the evaluation views: ``renders[i]`` is view ``views[i]``
        rendered at ``out_width`` from a cache of ``width``."""

    @abstractmethod
    def held_out(self, renders: torch.Tensor, store: ViewStore, candidates: list[str], background: float) -> HeldOut:
        """The trained field's figures on the held-out metric views: ``renders (V, 3, H, W)`` (sRGB)
        of the views of ``store``, at its width, on ``background``; ``candidates``: the grid's
        prompts (the prompt among them)."""


#: the class of each guidance mode by (mode, target renderer): the renderer None for a mode
#: without image targets (:attr:`GuidanceMode.image_targets`)
GUIDANCE_CLASSES: dict[tuple[str, str | None], type[Guidance]] = {}


def register(name: str, target_renderer: str | None = None) -> Callable[[type[Guidance]], type[Guidance]]:
    """Register a :class:`Guidance` class as mode ``name`` (a row of
    :data:`~stages.config.guidance_modes.GUIDANCE_MODES`), for ``target_renderer`` where the mode
    fits image targets; sets the class's :attr:`~Guidance.mode`."""
    mode = guidance_mode(name)
    if (target_renderer is None) == mode.image_targets:
        need = "names its target renderer" if mode.image_targets else "has no target renderer"
        raise TypeError(f"guidance mode {name!r} {need}: register({name!r}{', <renderer>' if mode.image_targets else ''})")

    def add(cls: type[Guidance]) -> type[Guidance]:
        key = (name, target_renderer)
        if key in GUIDANCE_CLASSES:
            raise TypeError(f"{key} is already registered as {GUIDANCE_CLASSES[key].__name__}")
        cls.mode = mode
        GUIDANCE_CLASSES[key] = cls
        return cls

    return add


@register("clip")
class ClipGuidance(Guidance):
    """TANGO's guidance: the CLIP similarity of each global image and each crop with the prompt."""

    held_out_key = "guidance"

    def __init__(self, settings: OptimizeSettings, prompt: str, device, guide: ClipGuide | None = None) -> None:
        super().__init__(settings, prompt)
        self.guide = guide or load_clip(settings.clip_spec(), device=device, bf16=settings.bf16, tower=settings.clip_tower)
        if self.guide.image_size != settings.image_size:
            raise ConfigError(
                f"optimize.image_size is {settings.image_size} but CLIP {self.guide.weights_id} "
                f"takes {self.guide.image_size}x{self.guide.image_size} images"
            )
        self.text = self.guide.embed_text(prompt)
        self.weights_id = self.guide.weights_id
        self.test_only = self.guide.test_only
        self.clip_precision = self.guide.precision
        self.clip_tower = self.guide.tower

    @classmethod
    def build(cls, settings, prompt, device, guide, targets) -> ClipGuidance:
        return cls(settings, prompt, device, guide)

    @classmethod
    def for_metrics(cls, settings, prompt, device, targets) -> ClipGuidance:
        """The guidance CLIP in float32, its batched tower (the held-out figures of every run alike)."""
        return cls(settings, prompt, device, load_clip(settings.clip_spec(), device=device))

    def loss(self, rendered: ImageBatch, target: ImageBatch | None) -> tuple[torch.Tensor, dict]:
        groups = [torch.stack(rendered.globals)] + ([torch.stack(rendered.crops)] if rendered.crops else [])
        sims = self.guide.similarities(groups, self.text)  # one batch through the tower
        loss, stats = -sims[0], {"similarity_global": float(sims[0].detach())}
        if rendered.crops:
            loss = loss - sims[1]
            stats["similarity_crops"] = float(sims[1].detach())
        return loss, stats

    @torch.no_grad()
    def eval_score(self, renders, views, width, out_width) -> EvalScore:
        size = self.guide.image_size
        images = [F.interpolate(rgb[None], size=(size, size), mode="bilinear", align_corners=False) for rgb in renders]
        sims = [float(s) for s in self.guide.similarities(images, self.text)]  # each view's, in one batch
        return EvalScore({"final_similarity": float(np.mean(sims)), "final_similarity_per_view": sims})

    @torch.no_grad()
    def held_out(self, renders, store, candidates, background) -> HeldOut:
        """The guidance CLIP's cosine similarity of the prompt with the views' mean embedding."""
        m = clip_metrics(self.guide, renders, self.prompt, candidates)
        return HeldOut({"weights": m["weights"], "test_only": m["test_only"], "similarity": m["similarity_mean_embedding"]})


class _TargetGuidance(Guidance):
    """Image guidance: the squared error against image targets of a known material and light."""

    held_out_key = "image_target"

    def loss(self, rendered: ImageBatch, target: ImageBatch | None) -> tuple[torch.Tensor, dict]:
        if target is None:
            raise ValueError("image guidance needs the target images of the step")
        loss = F.mse_loss(torch.stack(rendered.globals), torch.stack(target.globals))
        if rendered.crops:
            loss = loss + F.mse_loss(torch.stack(rendered.crops), torch.stack(target.crops))
        return loss, {}

    @abstractmethod
    def target_colors(self, v: CachedView, sel: torch.Tensor) -> torch.Tensor: ...

    @torch.no_grad()
    def held_out(self, renders, store, candidates, background) -> HeldOut:
        """PSNR, SSIM and the highlights of the renders against the targets, over object pixels
        (:func:`render_target`), with the renderer and material of the targets."""
        pairs = [render_target(self, store[i], store.width, store.width, background) for i in range(len(store))]
        t = torch.stack([img for img, _ in pairs])
        mask = torch.stack([m for _, m in pairs])
        px = mask.expand_as(t)
        figures = {
            "weights": self.weights_id,
            "psnr_db": psnr(renders[px], t[px]),
            "ssim": ssim(renders, t, mask),
            "highlights": highlights(renders, t, mask),
            "pixels": "object pixels of the held-out metric views (SSIM: windows centred on them)",
            "target_renderer": self.settings.target_renderer,
            "target_material": self.settings.target_material,
        }
        return HeldOut(figures, t)


@register("image", "mitsuba")
class ImageGuidance(_TargetGuidance):
    """Image targets path-traced by Mitsuba 3 (the target stage), attached to the cached views;
    ``targets``: their description, which becomes the result's weights id. The evaluation views
    have no Mitsuba targets: the metrics stage grades the held-out metric views, which do."""

    def __init__(self, settings: OptimizeSettings, prompt: str, targets: str | None) -> None:
        super().__init__(settings, prompt)
        if not targets:
            raise ConfigError(
                "optimize.target_renderer is mitsuba but no Mitsuba targets were given "
                "(the target stage writes them; or set target_renderer: sg)"
            )
        self.weights_id = f"image targets: {targets}"

    @classmethod
    def build(cls, settings, prompt, device, guide, targets) -> ImageGuidance:
        return cls(settings, prompt, targets)

    def target_colors(self, v: CachedView, sel: torch.Tensor) -> torch.Tensor:
        if v.target is None:
            raise ConfigError("this view has no Mitsuba targets attached (target_renderer: mitsuba)")
        return v.target[sel]

    def eval_score(self, renders, views, width, out_width) -> EvalScore:
        return EvalScore({})


@register("image", "sg")
class SGTargetGuidance(_TargetGuidance):
    """A procedural material (``target_material``) rendered by our own SG renderer under a
    procedural SG light (``target_light``), with the specular model and shadows the field uses, so
    that the target stays representable."""

    def __init__(self, settings: OptimizeSettings, prompt: str, device) -> None:
        super().__init__(settings, prompt)
        self.target_light = procedural_light(settings.target_light, device=device)
        self.weights_id = (
            f"image targets: procedural {settings.target_material} under the {settings.target_light} SG light "
            "(rendered by our own SG renderer)"
        )

    @classmethod
    def build(cls, settings, prompt, device, guide, targets) -> SGTargetGuidance:
        return cls(settings, prompt, device)

    def target_colors(self, v: CachedView, sel: torch.Tensor) -> torch.Tensor:
        visibility = None if v.shadows is None else v.shadows.shares(self.target_light, sel)
        return self.procedural_colors(v.points[sel], v.normals[sel], v.view[sel], visibility)

    def procedural_colors(self, points, normals, view, visibility: torch.Tensor | None = None) -> torch.Tensor:
        """Linear radiance ``(N, 3)`` of the procedural target under the SG light at cached hits,
        each light lobe scaled by its visible share ``visibility (N, K)`` when given."""
        flip = (normals * view).sum(-1, keepdim=True) < 0
        n = face_viewer(torch.where(flip, -normals, normals), view)
        m = procedural_material(self.settings.target_material, points)
        lobe = self.settings.specular_lobe
        return m.brdf.shade(n, view, m, self.target_light, lobe, visibility).rgb

    def eval_score(self, renders, views, width, out_width) -> EvalScore:
        pairs = [render_target(self, v, width, out_width) for v in views]
        pred, tgt = torch.stack(list(renders)), torch.stack([t for t, _ in pairs])
        px = torch.stack([m for _, m in pairs]).expand_as(pred)
        # object pixels only: the background is black in both and would inflate the figure
        figures = {"eval_psnr_db": psnr(pred[px], tgt[px]), "eval_psnr_pixels": "object pixels of the evaluation views, sRGB"}
        return EvalScore(figures, [t for t, _ in pairs])

    def held_out(self, renders, store, candidates, background) -> HeldOut:
        held = super().held_out(renders, store, candidates, background)
        held.figures["target_light"] = self.settings.target_light
        return held


def guidance_class(settings: OptimizeSettings) -> type[Guidance]:
    """The class registered for the guidance mode of ``settings`` (and its target renderer, for a
    mode that fits image targets); a mode without one is a :class:`ConfigError`."""
    mode = settings.guidance_mode()
    key = (mode.name, settings.target_renderer if mode.image_targets else None)
    if key not in GUIDANCE_CLASSES:
        renderer = f" with target_renderer {key[1]}" if key[1] else ""
        raise ConfigError(f"guidance {mode.name!r}{renderer} has no class (stages.guidance.objective.register)")
    return GUIDANCE_CLASSES[key]


def choose_guidance(
    settings: OptimizeSettings, prompt: str, device, guide: ClipGuide | None = None, targets: str | None = None
) -> Guidance:
    """The guidance ``settings`` name: ``guide``, an already loaded CLIP (else loaded from the
    settings); ``targets``, the description of the Mitsuba targets attached to the views."""
    return guidance_class(settings).build(settings, prompt, device, guide, targets)


@torch.no_grad()
def render_target(guidance: _TargetGuidance, v: CachedView, width: int, out_width: int, background: float = 0.0):
    """The target of one cached view ``(3, out, out)`` (sRGB) and its object mask ``(1, out, out)``:
    pixels whose centre ray hits the mesh and, for Mitsuba targets, whose footprint is fully
    covered (edge pixels mix object and background and are left out of the figures)."""

    def colors(view, sel):
        return linear_to_srgb(guidance.target_colors(view, sel))

    img = render_cached_view(v, width, out_width, colors, background)
    spec = global_spec(width, out_width)
    idx = v.index[spec.rows, spec.cols]
    hit = idx >= 0
    if v.coverage is not None:
        cov = v.coverage.cpu().numpy()[np.where(hit, idx, 0)]
        hit = hit & (cov >= FULL_COVERAGE)
    mask = torch.as_tensor(hit, device=v.points.device)[None]
    return img, mask
