"""The objective of an optimisation: CLIP similarity of renders with the prompt (TANGO), or, with
``guidance: image``, the squared error against image targets of a known material and light, which
verifies the whole optimisation without CLIP weights. The targets are either path-traced by
Mitsuba 3 (``target_renderer: mitsuba``, the target stage: ground truth nobody here rendered,
stored per cached hit and attached to the views) or rendered on the fly by our own SG renderer
(``target_renderer: sg``: quick, but the renderer grades itself)."""

from __future__ import annotations

import numpy as np
import torch
from torch.nn import functional as F

from ..config.sections import OptimizeSettings
from ..core.errors import ConfigError
from ..core.provenance import origin_record
from ..imaging.images import global_spec, render_cached_view
from ..imaging.targets import FULL_COVERAGE
from ..imaging.views import CachedView
from ..model.procedural import procedural_light, procedural_material
from ..render.color import linear_to_srgb
from ..render.shading import face_viewer, shade
from .clip import load_clip


class Objective:
    """The guidance: CLIP similarity, or image error against a procedural target."""

    def __init__(self, settings: OptimizeSettings, prompt: str, device, guide=None, targets: str | None = None) -> None:
        """``guide``: an already loaded :class:`~stages.guidance.clip.ClipGuide` (else loaded from
        the settings). ``targets``: the description of the Mitsuba targets attached to the views
        (``target_renderer: mitsuba``), which becomes the weights id of the result."""
        self.s = settings
        self.device = device
        self.guide = None
        self.weights_id = None
        self.test_only = False
        #: what the guidance CLIP ran in (None: no CLIP, image guidance)
        self.clip_precision = None
        self.clip_tower = None
        if settings.guidance == "clip":
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
        elif settings.target_renderer == "mitsuba":
            if not targets:
                raise ConfigError(
                    "optimize.target_renderer is mitsuba but no Mitsuba targets were given "
                    "(the target stage writes them; or set target_renderer: sg)"
                )
            self.weights_id = f"image targets: {targets}"
        else:
            self.target_light = procedural_light(settings.target_light, device=device)
            self.weights_id = (
                f"image targets: procedural {settings.target_material} under the {settings.target_light} SG light "
                "(rendered by our own SG renderer)"
            )
        self.origin = origin_record(guidance=settings.guidance, weights=self.weights_id, test_only=self.test_only, prompt=prompt)

    def target_colors(self, v: CachedView, sel: torch.Tensor) -> torch.Tensor:
        """Linear radiance ``(M, 3)`` of the image target at the hits ``sel`` of view ``v``: the
        Mitsuba targets attached to the view, or the SG-rendered procedural target."""
        if self.s.target_renderer == "mitsuba":
            if v.target is None:
                raise ConfigError("this view has no Mitsuba targets attached (target_renderer: mitsuba)")
            return v.target[sel]
        # the view's shadows, as the field casts them: the target stays representable
        visibility = None if v.shadows is None else v.shadows.shares(self.target_light, sel)
        return self.procedural_colors(v.points[sel], v.normals[sel], v.view[sel], visibility)

    def procedural_colors(self, points, normals, view, visibility: torch.Tensor | None = None) -> torch.Tensor:
        """Linear radiance ``(N, 3)`` of the procedural target under the SG light at cached hits,
        shaded with the specular model the field uses (``optimize.specular_lobe``), each light
        lobe scaled by its visible share ``visibility (N, K)`` when given (the field's shadows)."""
        flip = (normals * view).sum(-1, keepdim=True) < 0
        n = face_viewer(torch.where(flip, -normals, normals), view)
        m = procedural_material(self.s.target_material, points)
        return shade(
            n, view, m.albedo, self.target_light, m.specular, m.roughness, self.s.specular_lobe, visibility=visibility
        ).rgb

    def loss(self, globals_, crops, globals_t=None, crops_t=None) -> tuple[torch.Tensor, dict]:
        if self.guide is not None:
            sim_g = self.guide.similarity(torch.stack(globals_), self.text)
            loss = -sim_g
            stats = {"similarity_global": float(sim_g.detach())}
            if crops:
                sim_c = self.guide.similarity(torch.stack(crops), self.text)
                loss = loss - sim_c
                stats["similarity_crops"] = float(sim_c.detach())
            return loss, stats
        loss = F.mse_loss(torch.stack(globals_), torch.stack(globals_t))
        if crops:
            loss = loss + F.mse_loss(torch.stack(crops), torch.stack(crops_t))
        return loss, {}


@torch.no_grad()
def render_target(objective: Objective, v: CachedView, width: int, out_width: int, background: float = 0.0):
    """The target of one cached view ``(3, out, out)`` (sRGB) and its object mask ``(1, out, out)``:
    pixels whose centre ray hits the mesh and, for Mitsuba targets, whose footprint is fully
    covered (edge pixels mix object and background and are left out of the figures)."""

    def colors(view, sel):
        return linear_to_srgb(objective.target_colors(view, sel))

    img = render_cached_view(v, width, out_width, colors, background)
    spec = global_spec(width, out_width)
    idx = v.index[spec.rows, spec.cols]
    hit = idx >= 0
    if v.coverage is not None:
        cov = v.coverage.cpu().numpy()[np.where(hit, idx, 0)]
        hit = hit & (cov >= FULL_COVERAGE)
    mask = torch.as_tensor(hit, device=v.points.device)[None]
    return img, mask
