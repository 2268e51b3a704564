"""One bounce of light: the diffuse light the mesh sends to itself.

The light a surface point ``x`` receives from the rest of the mesh is the radiance leaving the
points its hemisphere sees. With a diffuse sender that radiance is the same in every direction, so
it is stored once per face side (:class:`BounceLight`'s ``table``: face ``f``'s front, the side its
normal points to, at row ``2 f``, its back at ``2 f + 1``; the sender's direct light, refreshed
from the material as it changes) and the irradiance at ``x`` is the cosine-weighted estimate

.. math::

    E(x) = \\int_{H^2} L(h(x, \\omega)) \\cos\\theta \\, d\\omega
         \\approx \\frac{\\pi}{K} \\sum_{k=1}^{K} L(h(x, \\omega_k)),
    \\qquad \\omega_k \\sim \\cos\\theta / \\pi,

``h(x, omega)`` the face side the ray from ``x`` meets first (a ray that leaves the mesh brings
the environment, which the direct light's visibility already counts: it adds nothing here). The
``K`` directions of each point (:func:`cosine_directions`) are drawn once and their hits traced
once (:meth:`~stages.model.shadows.ShadowCache.bounce_irradiance`), so the estimate is a fixed,
smooth function of the table (Pharr, Jakob & Humphreys, *Physically Based Rendering*, 4th ed.,
sections 13.6 and 15.1: Malley's method, path tracing truncated at two segments).

The receiver reflects it by its diffuse term (``albedo / pi`` times the BRDF's diffuse layer at the
normal): a glossy reflection of nearby surfaces is left out, as is every later bounce.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import torch
from torch import Tensor

from ..shading import Shading, tangent_frame
from .base import DistantLight

#: the golden ratio's fractional part: the second coordinate's step of :func:`cosine_directions`
GOLDEN_STEP = (math.sqrt(5.0) - 1.0) / 2.0


def cosine_directions(normals: Tensor, samples: int, shift: Tensor) -> Tensor:
    """``samples`` directions ``(N, K, 3)`` over each unit normal's hemisphere, distributed as
    ``cos theta / pi`` (Malley's method: a point of the unit disc lifted to the hemisphere) from a
    rank-1 lattice of the unit square (``u_k = (k + 1/2) / K``, ``v_k = k phi``) shifted by each
    point's ``shift (N, 2)`` in ``[0, 1)`` (Cranley-Patterson rotation: each point its own
    stratified set). Valid at the poles (the frame is :func:`~stages.render.shading.tangent_frame`)."""
    k = torch.arange(samples, dtype=normals.dtype, device=normals.device)
    u = torch.remainder((k + 0.5) / samples + shift[:, :1], 1.0)  # (N, K)
    v = torch.remainder(k * GOLDEN_STEP + shift[:, 1:], 1.0)
    r, phi = torch.sqrt(u), 2.0 * math.pi * v
    up = torch.sqrt(torch.clamp(1.0 - u, min=0.0))
    t, b = tangent_frame(normals)
    across = (r * torch.cos(phi))[..., None] * t[:, None] + (r * torch.sin(phi))[..., None] * b[:, None]
    return across + up[..., None] * normals[:, None]


def face_side(face: np.ndarray, direction: np.ndarray, face_normals: np.ndarray) -> np.ndarray:
    """The row of the face side each ray met ``(N,)``: ``2 f`` where a ray of ``direction (N, 3)``
    meets face ``f`` from its front (against its normal), ``2 f + 1`` from behind, -1 for a miss
    (``face`` -1)."""
    face = np.asarray(face, np.int64)
    hit = face >= 0
    out = np.full(face.shape, -1, np.int64)
    n = face_normals[face[hit]]
    back = (n * direction[hit]).sum(-1) > 0.0
    out[hit] = 2 * face[hit] + back.astype(np.int64)
    return out


def indirect_irradiance(table: Tensor, sides: Tensor) -> Tensor:
    """``pi / K`` times the sum of ``table (P, C)`` at each point's ``K`` hit face sides ``sides
    (N, K)`` (-1: a miss, adding nothing) -> ``(N, C)``: the estimate of the module docstring."""
    hit = sides >= 0
    rows = table[torch.clamp(sides, min=0)] * hit[..., None].to(table.dtype)  # (N, K, C)
    return rows.sum(1) * (math.pi / sides.shape[1])


@dataclass(frozen=True)
class BounceLight:
    """The light the mesh sends to itself, one bounce: ``table (P, C)``, the diffuse radiance
    leaving each face side (``P = 2 F``, the module's rows), and ``samples`` directions per point.

    The light component of kind ``bounce``: its visibility input is each point's indirect
    irradiance ``(N, C)`` (:func:`indirect_irradiance` of the table at the face sides the point
    sees, :meth:`~stages.model.shadows.ShadowCache.bounce_irradiance`); without it (None) it
    adds nothing. It is no part of the environment and no distant light: an asset's renderer
    makes its own bounces."""

    table: Tensor
    samples: int = 16

    #: its kind's name (:mod:`stages.model.lights`)
    kind: ClassVar[str] = "bounce"
    #: not drawn into an environment image (it comes from the mesh, not from afar)
    in_environment: ClassVar[bool] = False

    @property
    def device(self) -> torch.device:
        return self.table.device

    def shade(self, brdf, normal: Tensor, view: Tensor, material, lobe: str | None, visibility: Tensor | None) -> Shading:
        """The diffuse term under the indirect irradiance ``visibility (N, C)``: ``albedo / pi``
        times the BRDF's diffuse layer at the normal (glTF's ``1 - F`` at ``h = (v + n) / |v + n|``)
        times the irradiance; no specular term. Zeros without an irradiance."""
        zeros = torch.zeros_like(material.albedo)
        if visibility is None:
            return Shading(zeros, zeros)
        vh = 0.5 * torch.linalg.vector_norm(view + normal, dim=-1, keepdim=True)
        diffuse = material.albedo / math.pi * brdf.diffuse_layer(vh) * visibility.to(material.albedo.dtype)
        return Shading(diffuse, zeros)

    def radiance(self, directions: Tensor) -> Tensor:
        """None from afar: zeros ``(..., C)``."""
        return torch.zeros(*directions.shape[:-1], self.table.shape[-1], dtype=directions.dtype, device=directions.device)

    def energy(self) -> Tensor:
        """None from afar: zeros ``(C,)``."""
        return torch.zeros(self.table.shape[-1], dtype=self.table.dtype, device=self.device)

    def describe(self) -> dict:
        """Its kind, face sides, samples per point and the table's mean radiance per channel."""
        return {
            "kind": self.kind,
            "face_sides": int(self.table.shape[0]),
            "samples": self.samples,
            "mean_radiance": [float(x) for x in self.table.double().mean(0)] if len(self.table) else None,
        }

    def arrays(self) -> dict[str, np.ndarray]:
        """``bounce_table`` as it is."""
        return {"bounce_table": self.table.detach().cpu().numpy()}

    def distant_lights(self) -> list[DistantLight]:
        """None: it is the mesh's own light."""
        return []

    def shadowed_by(self, shadows: Any, index: Tensor | None) -> Tensor:
        """Each point's indirect irradiance ``(n, C)`` at the points ``index`` of ``shadows``
        (:meth:`stages.model.shadows.ShadowCache.bounce_irradiance`: first hits, traced once)."""
        return shadows.bounce_irradiance(self, index)

    def like(self, leaf: Callable[..., Tensor]) -> BounceLight:
        """A table of its shape from ``leaf``, held non-negative."""
        return BounceLight(leaf(*self.table.shape).abs(), self.samples)

    def visibility_like(self, leaf: Callable[..., Tensor], points: int) -> Tensor:
        """An irradiance ``(points, C)`` from ``leaf``, held non-negative."""
        return leaf(points, self.table.shape[-1]).abs()

    def to(self, device: torch.device | str) -> BounceLight:
        return BounceLight(self.table.to(device), self.samples)

    def detach(self) -> BounceLight:
        return BounceLight(self.table.detach(), self.samples)
