"""Relighting judged by ground truth: the recovered field under another light against Mitsuba's
render of the *true* material under that light, on the held-out metric views.

A light that is blurred, or shadows painted into the albedo, still fit the training light; under
another light they show. For each environment of the relit ground truth
(:func:`~stages.imaging.targets.load_relit`) the environment is brought into the renderer as the
relight stage brings any map (an SG fit, :func:`~stages.model.lightfit.fit_sg_light`), the field's
forward pass shades every hit of the metric views under it, and the PSNR is taken over the fully
covered object pixels in sRGB, as the metrics stage grades the training light. Beside it, the
*ceiling*: our renderer given the true material and normals under the same fitted light, the best
the model could reach there (the SG fit of the map, the closed-form BRDF and the missing shadows
and interreflection are what separates it from Mitsuba).
"""

from __future__ import annotations

import numpy as np
import torch

from ..model.lightfit import fit_sg_light
from ..render.color import linear_to_srgb
from ..render.envmap import load_env
from ..render.shading import SGLight, face_viewer, shade, shade_gltf
from .quality import psnr
from .targets import FULL_COVERAGE, GLTF_TRUTH_KEYS, RelitTruth, TargetSet
from .views import ViewStore


@torch.no_grad()
def _field_radiance(field, store: ViewStore, light: SGLight) -> torch.Tensor:
    """Linear radiance ``(N, 3)`` of every hit of ``store``'s views (cache order) under ``light``."""
    parts = []
    for i in range(len(store)):
        v = store[i]
        parts.append(field(v.points, v.normals, v.view, light).shading.rgb)
    return torch.cat(parts)


@torch.no_grad()
def _truth_radiance(truth: TargetSet, store: ViewStore, light: SGLight, lobe: str, brdf: str = "tango") -> torch.Tensor:
    """Linear radiance ``(N, 3)`` of our renderer (the BRDF ``brdf``) given the true material and
    shading normals."""
    dev = light.axis.device
    view = torch.cat([store[i].view for i in range(len(store))])
    keys = ("albedo", "specular", "roughness", "normal", *(GLTF_TRUTH_KEYS if brdf == "gltf" else ()))
    a = {k: torch.from_numpy(truth.arrays[k].astype(np.float32)).to(dev) for k in keys}
    n = face_viewer(torch.nn.functional.normalize(a["normal"], dim=-1), view)
    rough = a["roughness"].clamp(0.01, 1.0)
    if brdf == "gltf":
        return shade_gltf(n, view, a["base"], a["metallic"], rough, light, lobe).rgb
    return shade(n, view, a["albedo"], light, a["specular"], rough, lobe).rgb


def grade_relighting(
    field, store: ViewStore, relit: list[RelitTruth], truth: TargetSet | None, lobes: int, iterations: int
) -> list[dict]:
    """Per environment of ``relit``: ``environment``, ``psnr_db`` (the field relit against Mitsuba's
    truth), ``ceiling_psnr_db`` (the true material in our renderer, when ``truth`` carries it),
    ``pixels``, ``noise_psnr_db`` (the truth's own noise) and ``sg_fit_relative_rms`` (the
    environment's SG fit)."""
    out = []
    dev = next(field.parameters()).device
    for r in relit:
        fitted, rel = fit_sg_light(load_env(r.environment), lobes, iterations)
        light = SGLight(fitted.axis.to(dev), fitted.sharpness.to(dev), fitted.amplitude.to(dev))
        full = torch.from_numpy(r.coverage >= FULL_COVERAGE).to(dev)
        goal = linear_to_srgb(torch.from_numpy(r.radiance).to(dev))[full]
        ours = linear_to_srgb(_field_radiance(field, store, light))[full]
        row = {
            "environment": r.environment,
            "psnr_db": psnr(ours, goal),
            "pixels": int(full.sum()),
            "noise_psnr_db": r.noise_psnr_db,
            "sg_fit_relative_rms": rel,
        }
        brdf = getattr(field, "brdf", "tango")
        if truth is not None and truth.has_truth and (brdf == "tango" or all(k in truth.arrays for k in GLTF_TRUTH_KEYS)):
            ceiling = linear_to_srgb(_truth_radiance(truth, store, light, field.specular_lobe, brdf))[full]
            row["ceiling_psnr_db"] = psnr(ceiling, goal)
        out.append(row)
    return out
