"""Known materials and lights for the image-target guidance (verification without CLIP).

Analytic fields over normalised positions ``(N, 3)``: a wood-like material (concentric rings
around the y axis, warped), a brushed metal (dark diffuse, coloured specular, roughness striped
along y), a polished chrome (roughness 0.08-0.12: it mirrors a light's shape), and a plaster-like
diffuse-dominant material; and two lights: ``studio``, four SG lobes
(warm key, cool fill, rim, dim ambient), which a model with 4 or more lobes represents exactly, and
``sky``, a small sun and a sky that brightens towards the horizon and a dark ground, made of 97
lobes with sharpnesses the model's lobes do not start from, which no model of 16-64 lobes
represents exactly. Rendering them on cached views gives target images whose material and light
the optimisation must recover. Both are rendered by our own SG renderer: such targets check the
optimisation, not the renderer (an independent renderer is the reference issue's job).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..config.sections import LIGHTS, MATERIALS
from ..render.shading import SGLight
from .lights.sg import fibonacci_sphere
from .networks import Material


def _mix(a, b, t: Tensor) -> Tensor:
    a = torch.tensor(a, dtype=t.dtype, device=t.device)
    b = torch.tensor(b, dtype=t.dtype, device=t.device)
    return a + (b - a) * t


def procedural_material(kind: str, points: Tensor) -> Material:
    """The analytic material ``kind`` at ``points (N, 3)`` (float32 or float64)."""
    x, y, z = points.unbind(-1)
    if kind == "wood":
        r = torch.sqrt(x * x + z * z) * 4.0 + 0.15 * torch.sin(3.0 * y + 2.0 * x)
        ring = (0.5 + 0.5 * torch.cos(2.0 * math.pi * r))[:, None] ** 3
        albedo = _mix((0.36, 0.20, 0.09), (0.78, 0.52, 0.30), ring)
        rough = 0.55 + 0.2 * ring
        spec = torch.full_like(albedo, 0.04)
    elif kind == "metal":
        stripes = (0.5 + 0.5 * torch.sin(40.0 * y + 0.5 * torch.sin(5.0 * x)))[:, None]
        albedo = torch.full((len(points), 3), 0.06, dtype=points.dtype, device=points.device)
        spec = _mix((0.80, 0.80, 0.82), (0.95, 0.93, 0.90), stripes)
        rough = 0.25 + 0.12 * stripes
    elif kind == "chrome":
        swirl = (0.5 + 0.5 * torch.sin(6.0 * x + 4.0 * z + 2.0 * y))[:, None]
        albedo = torch.full((len(points), 3), 0.02, dtype=points.dtype, device=points.device)
        spec = _mix((0.90, 0.91, 0.93), (0.97, 0.96, 0.94), swirl)
        rough = 0.08 + 0.04 * swirl
    elif kind == "plaster":
        t = (0.5 + 0.5 * torch.sin(2.0 * x + 1.5 * y) * torch.cos(1.5 * z))[:, None]
        albedo = _mix((0.70, 0.68, 0.62), (0.85, 0.80, 0.72), t)
        spec = torch.full_like(albedo, 0.02)
        rough = 0.9 + 0.0 * t
    else:
        raise ValueError(f"unknown procedural material {kind!r}; choose one of {', '.join(MATERIALS)}")
    return Material(albedo, spec, rough)


def procedural_light(kind: str = "studio", dtype=torch.float32, device="cpu") -> SGLight:
    """A fixed SG light (y up). ``studio``: warm key, cool fill, rim and dim ambient lobes (4).
    ``sky``: a sharp warm sun (sharpness 2000, about 1.5 degrees wide) at elevation 35 degrees, a
    sky of 64 lobes on the upper hemisphere (sharpness 12) whose blue radiance rises towards the
    horizon, and a dark warm ground of 32 lobes: 97 lobes in all."""
    if kind == "studio":
        axes = torch.tensor([[0.3, 0.8, 0.9], [-0.9, 0.3, 0.4], [0.0, 0.5, -1.0], [0.0, 1.0, 0.0]], dtype=dtype)
        axes = axes / torch.linalg.vector_norm(axes, dim=-1, keepdim=True)
        lam = torch.tensor([[30.0], [6.0], [20.0], [0.5]], dtype=dtype)
        amp = torch.tensor([[6.0, 5.2, 4.2], [0.8, 1.0, 1.3], [2.0, 2.0, 2.2], [0.25, 0.25, 0.28]], dtype=dtype)
        return SGLight(axes.to(device), lam.to(device), amp.to(device))
    if kind == "sky":
        elev = math.radians(35.0)
        sun = torch.tensor([[math.cos(elev) * 0.6, math.sin(elev), math.cos(elev) * 0.8]], dtype=dtype)
        dirs = fibonacci_sphere(192).to(dtype)
        upper = dirs[dirs[:, 1] > 0.05][:64]
        lower = dirs[dirs[:, 1] < -0.05][:32]
        horizon = (1.0 - upper[:, 1:2]).clamp(0, 1)
        sky_amp = torch.tensor([0.25, 0.35, 0.60], dtype=dtype) * (0.4 + 0.8 * horizon)
        ground_amp = torch.tensor([0.06, 0.05, 0.04], dtype=dtype).expand(len(lower), 3)
        axes = torch.cat([sun, upper, lower])
        axes = axes / torch.linalg.vector_norm(axes, dim=-1, keepdim=True)
        lam = torch.cat([torch.full((1, 1), 2000.0), torch.full((len(upper), 1), 12.0), torch.full((len(lower), 1), 6.0)]).to(
            dtype
        )
        amp = torch.cat([torch.tensor([[900.0, 800.0, 650.0]], dtype=dtype), sky_amp, ground_amp])
        return SGLight(axes.to(device), lam.to(device), amp.to(device))
    raise ValueError(f"unknown procedural light {kind!r}; choose one of {', '.join(LIGHTS)}")
