"""The objective of an optimisation: CLIP similarity of renders with the prompt (TANGO), or, with
``guidance: image``, the squared error against renders of a known procedural material and light
(which verifies the whole optimisation without CLIP weights)."""

from __future__ import annotations

import torch
from torch.nn import functional as F

from ..config.sections import OptimizeSettings
from ..core.errors import ConfigError
from ..core.provenance import origin_record
from ..imaging.images import global_spec, render_cached_view
from ..imaging.views import CachedView
from ..model.procedural import procedural_light, procedural_material
from ..render.color import linear_to_srgb
from ..render.shading import face_viewer, shade
from .clip import load_clip


class Objective:
    """The guidance: CLIP similarity, or image error against a procedural target."""

    def __init__(self, settings: OptimizeSettings, prompt: str, device, guide=None) -> None:
        """``guide``: an already loaded :class:`~stages.guidance.clip.ClipGuide` (else loaded from
        the settings)."""
        self.s = settings
        self.device = device
        self.guide = None
        self.weights_id = None
        self.test_only = False
        if settings.guidance == "clip":
            self.guide = guide or load_clip(settings.clip_spec(), device=device, bf16=settings.bf16)
            if self.guide.image_size != settings.image_size:
                raise ConfigError(
                    f"optimize.image_size is {settings.image_size} but CLIP {self.guide.weights_id} "
                    f"takes {self.guide.image_size}x{self.guide.image_size} images"
                )
            self.text = self.guide.embed_text(prompt)
            self.weights_id = self.guide.weights_id
            self.test_only = self.guide.test_only
        else:
            self.target_light = procedural_light(settings.target_light, device=device)
            self.weights_id = f"image targets: procedural {settings.target_material} under {settings.target_light} light"
        self.origin = origin_record(guidance=settings.guidance, weights=self.weights_id, test_only=self.test_only, prompt=prompt)

    def target_colors(self, points, normals, view) -> torch.Tensor:
        """Linear radiance ``(N, 3)`` of the procedural target at cached hits (image guidance)."""
        flip = (normals * view).sum(-1, keepdim=True) < 0
        n = face_viewer(torch.where(flip, -normals, normals), view)
        m = procedural_material(self.s.target_material, points)
        return shade(n, view, m.albedo, self.target_light, m.specular, m.roughness).rgb

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
    """The procedural target of one cached view ``(3, out, out)`` and its object mask ``(1, out, out)``."""
    img = render_cached_view(v, width, out_width, lambda p, n, d: linear_to_srgb(objective.target_colors(p, n, d)), background)
    spec = global_spec(width, out_width)
    mask = torch.as_tensor(v.index[spec.rows, spec.cols] >= 0, device=v.points.device)[None]
    return img, mask
