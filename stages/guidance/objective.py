"""The guidance of an optimisation, one class per mode behind one interface (:class:`Guidance`),
chosen once by :func:`choose_guidance` from ``optimize.guidance`` and ``optimize.target_renderer``:

* :class:`ClipGuidance` (``guidance: clip``, TANGO): CLIP similarity of the renders with the prompt;
* :class:`ImageGuidance` (``guidance: image``, ``target_renderer: mitsuba``): the squared error
  against ground truth path-traced by Mitsuba 3 (the target stage), stored per cached hit and
  attached to the views; nobody here rendered it;
* :class:`SGTargetGuidance` (``guidance: image``, ``target_renderer: sg``): the squared error
  against our own SG renders of a procedural material, on the fly (quick, but the renderer grades
  itself).

Image guidance verifies the whole optimisation without CLIP weights. Each records its ``origin``
(which guidance and weights made a result), which every downstream file carries.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from torch.nn import functional as F

from ..config.sections import OptimizeSettings
from ..core.errors import ConfigError
from ..core.provenance import origin_record
from ..imaging.images import global_spec, render_cached_view
from ..imaging.quality import psnr
from ..imaging.targets import FULL_COVERAGE
from ..imaging.views import CachedView
from ..model.procedural import procedural_light, procedural_material
from ..render.color import linear_to_srgb
from ..render.shading import face_viewer, shade
from .clip import ClipGuide, load_clip


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


class Guidance(ABC):
    """What an optimisation minimises, and how its result is scored on the evaluation views."""

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

    @property
    def origin(self) -> dict:
        """The record of the guidance and weights that made a result (:func:`origin_record`)."""
        s = self.settings
        return origin_record(guidance=s.guidance, weights=self.weights_id, test_only=self.test_only, prompt=self.prompt)

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


class ClipGuidance(Guidance):
    """TANGO's guidance: the CLIP similarity of each global image and each crop with the prompt."""

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


class _TargetGuidance(Guidance):
    """Image guidance: the squared error against image targets of a known material and light."""

    def loss(self, rendered: ImageBatch, target: ImageBatch | None) -> tuple[torch.Tensor, dict]:
        if target is None:
            raise ValueError("image guidance needs the target images of the step")
        loss = F.mse_loss(torch.stack(rendered.globals), torch.stack(target.globals))
        if rendered.crops:
            loss = loss + F.mse_loss(torch.stack(rendered.crops), torch.stack(target.crops))
        return loss, {}

    @abstractmethod
    def target_colors(self, v: CachedView, sel: torch.Tensor) -> torch.Tensor: ...


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

    def target_colors(self, v: CachedView, sel: torch.Tensor) -> torch.Tensor:
        if v.target is None:
            raise ConfigError("this view has no Mitsuba targets attached (target_renderer: mitsuba)")
        return v.target[sel]

    def eval_score(self, renders, views, width, out_width) -> EvalScore:
        return EvalScore({})


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
        return shade(n, view, m.albedo, self.target_light, m.specular, m.roughness, lobe, visibility=visibility).rgb

    def eval_score(self, renders, views, width, out_width) -> EvalScore:
        pairs = [render_target(self, v, width, out_width) for v in views]
        pred, tgt = torch.stack(list(renders)), torch.stack([t for t, _ in pairs])
        px = torch.stack([m for _, m in pairs]).expand_as(pred)
        # object pixels only: the background is black in both and would inflate the figure
        figures = {"eval_psnr_db": psnr(pred[px], tgt[px]), "eval_psnr_pixels": "object pixels of the evaluation views, sRGB"}
        return EvalScore(figures, [t for t, _ in pairs])


def choose_guidance(
    settings: OptimizeSettings, prompt: str, device, guide: ClipGuide | None = None, targets: str | None = None
) -> Guidance:
    """The guidance ``settings`` name: ``guide``, an already loaded CLIP (else loaded from the
    settings); ``targets``, the description of the Mitsuba targets attached to the views."""
    if settings.guidance == "clip":
        return ClipGuidance(settings, prompt, device, guide)
    if settings.target_renderer == "mitsuba":
        return ImageGuidance(settings, prompt, targets)
    return SGTargetGuidance(settings, prompt, device)


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
