"""Sharp lights: suns, each a disc of the sky of uniform radiance (the light component of kind
``sun``, :class:`SunLight`).

A sun has a unit ``direction`` (towards its centre), an ``irradiance`` per channel (what it gives
a surface facing it, unshadowed: its radiance times its solid angle) and an angular ``radius``
(the disc's half angle; a directional light in the limit 0). Its radiance inside the disc is
``E / Omega`` with ``Omega = 2 pi (1 - cos rho)``, zero outside.

It shades by evaluating the BRDF at directions inside its disc
(:meth:`~stages.render.brdf.Brdf.at_directions`): ``M`` directions of equal solid angle
(:func:`cap_offsets`: heights uniform in ``cos theta`` over the cap, azimuths on the golden-angle
spiral), each carrying ``E / M``, each with its own visible share (its shadow ray,
:mod:`stages.model.shadows`). Where the BRDF's specular lobe is narrower than a direction's cell
(a mirror under the sun), the normal distribution is widened by the cell's size
(:func:`cell_widening`), so that the disc's image is resolved to its cells, not to points that
fall between the lobe's peak and miss it. Where the disc is narrower than the lobe, the directions
agree and the sum is the BRDF at the centre times ``E`` (exact as ``rho -> 0``).

Unlike the SG lobes, whose closed forms approximate a BRDF's integral against each lobe, a sun is
shaded with the BRDF's own formula: a sun at the mirror direction of a glossy surface, which the
fitted lobe misses by up to 30%, is exact here to the quadrature's resolution of the disc.

References: [Karis13] B. Karis, "Real Shading in Unreal Engine 4" (area lights as roughness
widened over the source's size, the idea of :func:`cell_widening`); the cap's equal-area
parametrisation: uniform ``cos theta`` (Archimedes' hat-box theorem).
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

#: the golden angle, the azimuth step of :func:`cap_offsets`' spiral
GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


def cap_offsets(samples: int, dtype: torch.dtype = torch.float32, device=None) -> tuple[Tensor, Tensor]:
    """The quadrature of a spherical cap by ``samples`` directions of equal solid angle: each
    direction's share ``u (M,)`` of the cap's height ``1 - cos rho`` (the midpoints ``(j + 1/2) /
    M``: uniform in ``cos theta`` is uniform in solid angle) and its azimuth ``phi (M,)`` (``j``
    golden angles). Exact for any ``rho``: the cap itself is only scaled (:func:`disc_directions`)."""
    j = torch.arange(samples, dtype=torch.float64, device=device)
    return ((j + 0.5) / samples).to(dtype), torch.remainder(j * GOLDEN_ANGLE, 2.0 * math.pi).to(dtype)


def cap_height(radius: Tensor) -> Tensor:
    """``1 - cos rho`` as ``2 sin^2(rho / 2)``: no cancellation for a small disc (float32's
    ``1 - cos`` is 0 below 3.5e-4 radians)."""
    return 2.0 * torch.sin(0.5 * radius) ** 2


def solid_angle(radius: Tensor) -> Tensor:
    """The disc's solid angle ``2 pi (1 - cos rho)`` for angular ``radius`` ``rho`` in [0, pi]."""
    return 2.0 * math.pi * cap_height(radius)


def disc_directions(axis: Tensor, radius: Tensor, u: Tensor, phi: Tensor) -> Tensor:
    """The quadrature's directions ``(S, M, 3)`` inside the discs of unit ``axis (S, 3)`` and
    angular ``radius (S, 1)`` (:func:`cap_offsets`' ``u`` and ``phi (M,)``): ``cos theta = 1 - u
    h``, ``sin theta = sqrt(u h (2 - u h))`` with ``h = 1 - cos rho`` (:func:`cap_height`), so
    that a disc of radius 1e-6 keeps its directions apart and differentiable in ``rho``."""
    t, s = tangent_frame(axis)
    depth = u[None, :] * cap_height(radius)  # (S, M): 1 - cos theta
    sin = torch.sqrt(torch.clamp(depth * (2.0 - depth), min=0.0))
    across = torch.cos(phi)[None, :, None] * t[:, None, :] + torch.sin(phi)[None, :, None] * s[:, None, :]
    return (1.0 - depth)[..., None] * axis[:, None, :] + sin[..., None] * across


def cell_widening(radius: Tensor, samples: int) -> Tensor:
    """What each quadrature direction adds to the normal distribution's ``alpha^2`` ``(S, 1)``: its
    cell has solid angle ``Omega / M``, a disc of radius ``c = sqrt(Omega / (pi M))``. A normal
    distribution ``exp(-theta_h^2 / alpha^2)`` has per-axis variance ``alpha^2 / 2`` in the half
    vector, which moves half as far as the light, so blurring the light by a Gaussian of per-axis
    deviation ``c`` adds ``c^2 / 4`` there and ``alpha'^2 = alpha^2 + c^2 / 2 = alpha^2 + Omega /
    (2 pi M)``: a deviation of a cell's radius, so that the blurred directions overlap into an even
    disc (a deviation of half the radius, the cell's own, left dips of half the peak between
    them; tests/render/test_sun.py). Negligible where the lobe is wider than the cells; a mirror
    sees the disc resolved to its cells."""
    return solid_angle(radius) / (2.0 * math.pi * samples)


def sun_radiance_reference(
    brdf, normal: Tensor, view: Tensor, material, axis, irradiance, radius, samples: int, visibility=None
) -> Shading:
    """:meth:`SunLight.shade` written plainly, one sun and one direction at a time (a loop), for
    the tests: the reference the batched form is held to."""
    u, phi = cap_offsets(samples, normal.dtype, normal.device)
    diffuse = torch.zeros_like(normal)
    specular = torch.zeros_like(normal)
    for k in range(axis.shape[0]):
        dirs = disc_directions(axis[k : k + 1], radius[k : k + 1], u, phi)[0]  # (M, 3)
        widen = cell_widening(radius[k : k + 1], samples)
        for j in range(samples):
            part = brdf.at_directions(normal, view, dirs[j : j + 1][None], material, widen)
            share = 1.0 if visibility is None else visibility[:, k * samples + j, None]
            diffuse = diffuse + part.diffuse[:, 0] * irradiance[k] / samples * share
            specular = specular + part.specular[:, 0] * irradiance[k] / samples * share
    return Shading(diffuse, specular)


@dataclass(frozen=True)
class SunLight:
    """``S`` suns: ``direction (S, 3)`` unit, ``irradiance (S, C) >= 0``, angular ``radius (S, 1)``
    in radians (> 0; a directional light as it nears 0), shaded with ``samples`` directions each.

    The light component of kind ``sun`` (:class:`~stages.render.light.LightComponent`); its
    visibility input is each direction's visible share ``(N, S M)`` (suns in order, each one's
    ``M`` directions together)."""

    direction: Tensor
    irradiance: Tensor
    radius: Tensor
    samples: int = 8

    #: its kind's name (:mod:`stages.model.lights`)
    kind: ClassVar[str] = "sun"
    #: an asset carries its suns as distant lights, not in its environment image
    in_environment: ClassVar[bool] = False

    @property
    def device(self) -> torch.device:
        return self.direction.device

    @property
    def suns(self) -> int:
        """Its number of suns ``S``."""
        return int(self.direction.shape[0])

    def directions(self) -> Tensor:
        """Each sun's quadrature directions ``(S, M, 3)`` (:func:`disc_directions`)."""
        u, phi = cap_offsets(self.samples, self.direction.dtype, self.device)
        return disc_directions(self.direction, self.radius, u, phi)

    def shade(self, brdf, normal: Tensor, view: Tensor, material, lobe: str | None, visibility: Tensor | None) -> Shading:
        """The BRDF at each sun's directions (:meth:`~stages.render.brdf.Brdf.at_directions`),
        each carrying ``E / M`` and scaled by its visible share ``visibility (N, S M)`` (None:
        unshadowed), summed: diffuse and specular radiance ``(N, C)``. ``lobe`` is the SG lobes'
        model and plays no part here. Any enclosing autocast is switched off."""
        if torch.is_autocast_enabled(normal.device.type):
            with torch.autocast(normal.device.type, enabled=False):
                return self.shade(brdf, normal, view, material, lobe, visibility)
        dirs = self.directions().reshape(1, -1, 3).to(normal.dtype)  # (1, S M, 3)
        widen = cell_widening(self.radius, self.samples).to(normal.dtype).repeat_interleave(self.samples, 0)
        part = brdf.at_directions(normal, view, dirs, material, widen)  # (N, S M, C)
        weight = (self.irradiance / self.samples).repeat_interleave(self.samples, 0).to(normal.dtype)  # (S M, C)
        if visibility is not None:
            weight = visibility[..., None].to(normal.dtype) * weight
        return Shading((part.diffuse * weight).sum(1), (part.specular * weight).sum(1))

    def radiance(self, directions: Tensor) -> Tensor:
        """``L(w) (..., C)``: each sun's ``E / Omega`` inside its disc (the angle to its centre
        below its radius), zero outside, summed over the suns."""
        work = torch.promote_types(directions.dtype, torch.float32)
        flat = directions.reshape(-1, 3).to(work)
        apart = torch.cdist(flat, self.direction.to(work), compute_mode="donot_use_mm_for_euclid_dist")  # chord
        inside = apart <= 2.0 * torch.sin(0.5 * self.radius.to(work).T)  # (P, S)
        level = self.irradiance.to(work) / solid_angle(self.radius.to(work))  # (S, C)
        out = inside.to(work) @ level
        return out.reshape(*directions.shape[:-1], -1)

    def energy(self) -> Tensor:
        """Its radiance integrated over the sphere per channel ``(C,)``: ``E / Omega`` over
        ``Omega``, the irradiance summed over the suns."""
        return self.irradiance.sum(0)

    def describe(self) -> dict:
        """Its kind, and each sun's direction (with its elevation above the ``y``-up horizon and
        azimuth), angular radius (degrees), irradiance and radiance per channel."""
        suns = []
        for k in range(self.suns):
            d = self.direction[k].double()
            suns.append(
                {
                    "direction": [round(float(x), 6) for x in d],
                    "elevation_deg": round(math.degrees(math.asin(float(d[1].clamp(-1, 1)))), 4),
                    "azimuth_rad": round(math.atan2(float(d[2]), float(d[0])), 6),
                    "radius_deg": round(math.degrees(float(self.radius[k, 0])), 6),
                    "irradiance": [float(x) for x in self.irradiance[k]],
                    "radiance": [float(x) for x in self.irradiance[k] / solid_angle(self.radius[k, 0].double())],
                }
            )
        return {"kind": self.kind, "suns": suns, "samples": self.samples, "energy": self.energy().tolist()}

    def arrays(self) -> dict[str, np.ndarray]:
        """``sun_direction``, ``sun_irradiance`` and ``sun_radius`` as they are."""
        return {
            "sun_direction": self.direction.cpu().numpy(),
            "sun_irradiance": self.irradiance.cpu().numpy(),
            "sun_radius": self.radius.cpu().numpy(),
        }

    def distant_lights(self) -> list[DistantLight]:
        """Each sun as a :class:`~stages.render.light.base.DistantLight` (float64 figures)."""
        d, e, r = (t.detach().double().cpu().numpy() for t in (self.direction, self.irradiance, self.radius))
        return [DistantLight(tuple(map(float, d[k])), tuple(map(float, e[k])), float(r[k, 0])) for k in range(self.suns)]

    def shadowed_by(self, shadows: Any, index: Tensor | None) -> Tensor:
        """Each direction's visible share ``(n, S M)`` at the points ``index`` of ``shadows``
        (:meth:`stages.model.shadows.ShadowCache.sun_shares`: shadow rays)."""
        return shadows.sun_shares(self, index)

    def like(self, leaf: Callable[..., Tensor]) -> SunLight:
        """``S`` suns from ``leaf``: normalised directions, irradiances, radii in (0, 0.1)."""
        direction = torch.nn.functional.normalize(leaf(self.suns, 3), dim=-1)
        radius = 0.1 * torch.sigmoid(leaf(self.suns, 1))
        return SunLight(direction, leaf(self.suns, self.irradiance.shape[1]), radius, self.samples)

    def visibility_like(self, leaf: Callable[..., Tensor], points: int) -> Tensor:
        return leaf(points, self.suns * self.samples)

    def to(self, device) -> SunLight:
        return SunLight(self.direction.to(device), self.irradiance.to(device), self.radius.to(device), self.samples)

    def detach(self) -> SunLight:
        return SunLight(self.direction.detach(), self.irradiance.detach(), self.radius.detach(), self.samples)
