"""Relighting judged by ground truth: the recovered field under another light against Mitsuba's
render of the *true* material under that light, on the held-out metric views.

A light that is blurred, or shadows painted into the albedo, still fit the training light; under
another light they show. For each environment of the relit ground truth
(:func:`~stages.imaging.targets.load_relit`) the environment is brought into the renderer as the
relight stage brings any map (an SG fit, :func:`~stages.model.lightfit.fit_sg_light`), the field's
forward pass shades every hit of the metric views under it, and the PSNR is taken over the fully
covered object pixels in sRGB, as the metrics stage grades the training light. Beside it, the
*ceiling*: our renderer given the true material and normals under the same fitted light, with the
shadows the field's views cast (where they do), the best the model could reach there (the SG fit
of the map, the closed-form BRDF, interreflection and, without visibility, the missing shadows are
what separates it from Mitsuba).
"""

from __future__ import annotations

import numpy as np
import torch

from ..model.field import shade_material
from ..model.lightfit import fit_sg_light
from ..model.networks import Material
from ..render.color import linear_to_srgb
from ..render.envmap import load_env
from ..render.shading import SGLight, face_viewer
from .quality import psnr
from .targets import FULL_COVERAGE, GLTF_TRUTH_KEYS, RelitTruth, TargetSet
from .views import ViewStore


@torch.no_grad()
def _field_radiance(field, store: ViewStore, light: SGLight) -> torch.Tensor:
    """Linear radiance ``(N, 3)`` of every hit of ``store``'s views (cache order) under ``light``."""
    parts = []
    for i in range(len(store)):
        v = store[i]
        parts.append(v.shade(field, light=light).shading.rgb)
    return torch.cat(parts)


@torch.no_grad()
def _truth_radiance(truth: TargetSet, store: ViewStore, light: SGLight, lobe: str, brdf: str = "tango") -> torch.Tensor:
    """Linear radiance ``(N, 3)`` of our renderer (the BRDF ``brdf``) given the true material and
    shading normals, with the shadows of ``store``'s views when they carry them (as the field's)."""
    dev = light.axis.device
    view = torch.cat([store[i].view for i in range(len(store))])
    keys = ("albedo", "specular", "roughness", "normal", *(GLTF_TRUTH_KEYS if brdf == "gltf" else ()))
    a = {k: torch.from_numpy(truth.arrays[k].astype(np.float32)).to(dev) for k in keys}
    n = face_viewer(torch.nn.functional.normalize(a["normal"], dim=-1), view)
    rough = a["roughness"].clamp(0.01, 1.0)
    material = Material.gltf(a["base"], a["metallic"], rough) if brdf == "gltf" else Material(a["albedo"], a["specular"], rough)
    shadows = [store[i].shadows for i in range(len(store))]
    visibility = None if any(s is None for s in shadows) else torch.cat([s.shares(light) for s in shadows])
    return shade_material(n, view, material, light, lobe, visibility).rgb


def channel_scale(pred: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """The per-channel factor ``(3,)`` that best maps linear ``pred (N, 3)`` onto ``truth`` in
    least squares, ``sum(p t) / sum(p p)`` (1 where ``pred`` is all zero)."""
    num, den = (pred * truth).sum(0), (pred * pred).sum(0)
    return torch.where(den > 0, num / den.clamp(min=torch.finfo(den.dtype).tiny), torch.ones_like(den))


def grade_relighting(
    field, store: ViewStore, relit: list[RelitTruth], truth: TargetSet | None, lobes: int, iterations: int
) -> list[dict]:
    """Per environment of ``relit``: ``environment``, ``psnr_db`` (the field relit against Mitsuba's
    truth), ``psnr_scaled_db`` and ``scale`` (the same after one least-squares factor per channel,
    :func:`channel_scale`: an image fit cannot tell an albedo from a light brighter by the same
    factor, so the raw figure also counts that unrecoverable scale; inverse-rendering evaluations
    align it), ``ceiling_psnr_db`` and ``ceiling_psnr_scaled_db`` (the true material in our
    renderer, when ``truth`` carries it), ``pixels``, ``noise_psnr_db`` (the truth's own noise) and
    ``sg_fit_relative_rms`` (the environment's SG fit)."""
    out = []
    dev = next(field.parameters()).device
    for r in relit:
        fitted, rel = fit_sg_light(load_env(r.environment), lobes, iterations)
        light = SGLight(fitted.axis.to(dev), fitted.sharpness.to(dev), fitted.amplitude.to(dev))
        full = torch.from_numpy(r.coverage >= FULL_COVERAGE).to(dev)
        truth_linear = torch.from_numpy(r.radiance).to(dev)[full]
        goal = linear_to_srgb(truth_linear)
        ours_linear = _field_radiance(field, store, light)[full]
        scale = channel_scale(ours_linear, truth_linear)
        row = {
            "environment": r.environment,
            "psnr_db": psnr(linear_to_srgb(ours_linear), goal),
            "psnr_scaled_db": psnr(linear_to_srgb(ours_linear * scale), goal),
            "scale": scale.tolist(),
            "pixels": int(full.sum()),
            "noise_psnr_db": r.noise_psnr_db,
            "sg_fit_relative_rms": rel,
        }
        brdf = getattr(field, "brdf", "tango")
        if truth is not None and truth.has_truth and (brdf == "tango" or all(k in truth.arrays for k in GLTF_TRUTH_KEYS)):
            ceiling = _truth_radiance(truth, store, light, field.specular_lobe, brdf)[full]
            row["ceiling_psnr_db"] = psnr(linear_to_srgb(ceiling), goal)
            row["ceiling_psnr_scaled_db"] = psnr(linear_to_srgb(ceiling * channel_scale(ceiling, truth_linear)), goal)
        out.append(row)
    return out
