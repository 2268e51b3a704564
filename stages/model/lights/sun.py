"""Suns (kind ``sun``): a few learnable discs of the sky, each a direction, an RGB irradiance and
an angular radius (:class:`SunLightModule`, its renderer's component
:class:`~stages.render.light.sun.SunLight`), and how they are found in an environment map
(:func:`find_suns`): the map's sharpest bright regions, which the SG lobes and the cached
visibility cannot represent, measured (:func:`sun_criterion`, what ``optimize.suns: auto``
decides by)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from ...config.sections import FieldSettings
from ...render.envmap import equirect_directions, load_env, radiant_energy, solid_angles
from ...render.light.sun import SunLight
from ...render.visibility import resolvable_sharpness
from .base import LightComponentModule

#: the range a sun's angular radius is kept in (radians): from a point-like star to 20 degrees
RADIUS_RANGE = (1e-4, math.radians(20.0))
#: a sun's irradiance is kept below exp(this)
LOG_IRRADIANCE_MAX = 30.0
#: Rec. 709 luminance weights: which pixel is brightest
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])
#: a sun's region: pixels within this many of its core's radius (plus two pixels) of its centre ...
REGION_RADII = 1.5
#: ... whose luminance above the background exceeds this share of the peak's (its anti-aliased edge)
EDGE_SHARE = 0.02


@dataclass(frozen=True)
class FoundSun:
    """One sun found in a map: unit ``direction (3,)``, ``irradiance (3,)`` (its radiance above the
    sky around it, integrated over its disc), angular ``radius`` (radians), its ``share`` of the
    map's energy (luminance) and the ``background (3,)`` radiance it stood on."""

    direction: np.ndarray
    irradiance: np.ndarray
    radius: float
    share: float
    background: np.ndarray

    def record(self) -> dict:
        return {
            "direction": [round(float(x), 6) for x in self.direction],
            "irradiance": [float(x) for x in self.irradiance],
            "radius_deg": round(math.degrees(self.radius), 4),
            "share": round(self.share, 6),
        }


def visibility_radius(directions: int) -> float:
    """The angular radius below which a light is too sharp for ``directions`` stored visibility
    directions: the width ``1 / sqrt(lam)`` of the sharpest lobe they resolve
    (:func:`~stages.render.visibility.resolvable_sharpness`; 18 degrees at 512 directions)."""
    return 1.0 / math.sqrt(resolvable_sharpness(directions))


def find_suns(env: np.ndarray, count: int) -> tuple[list[FoundSun], np.ndarray]:
    """The ``count`` brightest compact regions of the equirectangular ``env (H, W, 3)``, one after
    another, each taken out of the map before the next is looked for; returns them and what is
    left of the map (each region at its background).

    A region: the brightest pixel (luminance); its core, the pixels within 20 degrees at more than
    half the peak, whose solid angle gives a first radius and whose centre the distances are
    measured from; the background, the median radiance of
    the ring from ``1.5`` to ``3`` core radii (plus pixels); the region, pixels within ``1.5`` core
    radii (plus two pixels) whose luminance above the background exceeds 2% of the peak's (the
    disc's anti-aliased edge). Its irradiance is the region's radiance above the background
    integrated over solid angle (exact for a disc drawn with its edge's coverage), its direction
    the luminance-weighted mean, its solid angle that irradiance over the core's radiance
    (``Omega = E / L``; for a disc smaller than a pixel, the pixel's), its radius from the solid
    angle, ``rho = 2 asin(sqrt(Omega / 4 pi))``."""
    env = np.asarray(env, np.float64)
    h, w, _ = env.shape
    dirs = equirect_directions(h, w).double().numpy().reshape(-1, 3)
    omega = np.broadcast_to(solid_angles(h, w)[..., None], (h, w, 1)).reshape(-1)
    left = env.reshape(-1, 3).copy()
    total = float(radiant_energy(env) @ LUMINANCE)
    pixel = math.pi / h
    found = []
    for _ in range(count):
        lum = left @ LUMINANCE
        peak = int(np.argmax(lum))
        near = np.arccos(np.clip(dirs @ dirs[peak], -1.0, 1.0)) < math.radians(20.0)
        core = near & (lum > 0.5 * lum[peak])
        # measured from the core's centre (a wide disc's brightest pixel may lie at its edge)
        centre = ((lum * omega)[core, None] * dirs[core]).sum(0)
        angle = np.arccos(np.clip(dirs @ (centre / np.linalg.norm(centre)), -1.0, 1.0))
        core_radius = 2.0 * math.asin(min(1.0, math.sqrt(float(omega[core].sum()) / (4 * math.pi))))
        ring = (angle > REGION_RADII * core_radius + pixel) & (angle < 3.0 * core_radius + 3 * pixel)
        background = np.median(left[ring], axis=0) if ring.any() else np.zeros(3)
        above = left - background
        lum_above = above @ LUMINANCE
        peak_above = max(float(lum_above[core].max()), 1e-30)
        region = (angle < REGION_RADII * core_radius + 2 * pixel) & (lum_above > EDGE_SHARE * peak_above)
        weight = np.clip(above[region], 0.0, None) * omega[region, None]
        irradiance = weight.sum(0)
        lum_weight = weight @ LUMINANCE
        centre = (lum_weight[:, None] * dirs[region]).sum(0)
        direction = centre / max(np.linalg.norm(centre), 1e-30)
        core_level = float(np.clip(above[core], 0.0, None) @ LUMINANCE @ omega[core]) / max(float(omega[core].sum()), 1e-30)
        solid = float(irradiance @ LUMINANCE) / max(core_level, 1e-30)
        radius = 2.0 * math.asin(min(1.0, math.sqrt(solid / (4 * math.pi))))
        share = float(irradiance @ LUMINANCE) / max(total, 1e-30)
        found.append(FoundSun(direction, irradiance, radius, share, background))
        left[region] = np.minimum(left[region], background)
    return found, left.reshape(h, w, 3).astype(np.float32)


def sun_criterion(env: np.ndarray, directions: int, share: float, most: int) -> tuple[int, dict]:
    """``optimize.suns: auto`` on the map ``env``: how many suns it has, found one after another
    (:func:`find_suns`) while the next holds at least ``share`` of the map's energy within a radius
    below the cached visibility's resolution (:func:`visibility_radius` of ``directions``; with no
    visibility, 512 directions' width), at most ``most``; and the figures it decided by (each
    candidate's radius and share, the limits) for the metadata and the plan."""
    limit = visibility_radius(directions or 512)
    candidates, _ = find_suns(env, most + 1)
    count = 0
    for sun in candidates[:most]:
        if sun.share < share or sun.radius > limit:
            break
        count += 1
    record = {
        "suns": count,
        "share_needed": share,
        "radius_limit_deg": round(math.degrees(limit), 4),
        "candidates": [s.record() for s in candidates[: count + 1]],
    }
    return count, record


def resolve_suns(setting: int | str, environment: str | None, directions: int, share: float, most: int = 4) -> tuple[int, dict]:
    """``optimize.suns`` as a count, and the record of how it was decided (for the metadata and
    the plan): a number as it is; ``auto`` by :func:`sun_criterion` on the known ``environment``
    (``builtin:<name>`` or a map's path: the fixed light's map, or the image targets'), with the
    cached visibility's ``directions`` (0: none) and the share ``share``; 0 where none is known."""
    if setting != "auto":
        return int(setting), {"setting": int(setting), "suns": int(setting)}
    if environment is None:
        return 0, {"setting": "auto", "suns": 0, "why": "no environment is known (a learned light without image targets)"}
    count, record = sun_criterion(load_env(environment, SunLightModule.fit_height), directions, share, most)
    return count, {"setting": "auto", "environment": environment, **record}


class SunLightModule(LightComponentModule):
    """The light component of kind ``sun``: ``S`` learnable suns.

    Parametrisation (multiplicative, as the SG lobes': an Adam step changes a sun's irradiance and
    radius by a factor): unit directions ``u / |u|``; per channel the irradiance ``exp(e)`` (``e <=
    LOG_IRRADIANCE_MAX``); the radius ``exp(r)`` with ``r`` clamped to ``log RADIUS_RANGE``. A
    sun is shaded with ``samples`` directions of its disc (:class:`SunLight`)."""

    kind = "sun"
    #: fitted before the SG lobes, which take what the suns leave of a map (:meth:`LightModule.hold`)
    fit_order = -1
    #: the rows of map a fit reads (a 1.5-degree sun is a few pixels across at 512)
    fit_height = 512

    def __init__(self, suns: int = 1, *, samples: int = 8, total_irradiance: float = 3.0, share: float = 0.2) -> None:
        super().__init__()
        self.samples = samples
        #: the share of an environment's energy a region holds to be a sun (``optimize.suns_share``):
        #: how a map it is relit by is judged (:func:`~stages.model.lights.fit_environment_like`)
        self.share = share
        k = torch.arange(suns, dtype=torch.float64)
        azimuth = k * (math.pi * (3.0 - math.sqrt(5.0)))
        elevation = torch.full_like(k, math.radians(45.0))
        start = torch.stack(
            [torch.cos(elevation) * torch.cos(azimuth), torch.sin(elevation), torch.cos(elevation) * torch.sin(azimuth)], -1
        )
        self.axis_raw = nn.Parameter(start.float())
        self.log_irradiance = nn.Parameter(torch.full((suns, 3), math.log(total_irradiance / suns)))
        self.log_radius = nn.Parameter(torch.full((suns, 1), math.log(math.radians(2.0))))

    @property
    def suns(self) -> int:
        return int(self.axis_raw.shape[0])

    def forward(self) -> SunLight:
        axis = self.axis_raw / torch.linalg.vector_norm(self.axis_raw, dim=-1, keepdim=True)
        lo, hi = (math.log(x) for x in RADIUS_RANGE)
        radius = torch.exp(self.log_radius.clamp(lo, hi))
        irradiance = torch.exp(self.log_irradiance.clamp(max=LOG_IRRADIANCE_MAX))
        return SunLight(axis, irradiance, radius, self.samples)

    @classmethod
    def build(cls, settings: FieldSettings) -> SunLightModule | None:
        """``optimize.suns`` suns (as resolved: a count), each shaded with ``sun_samples``
        directions, starting at 45 degrees of elevation on a golden-angle spiral of azimuths with
        half of ``light_energy`` between them (the SG lobes keep theirs); none where it is 0."""
        count = settings.suns
        if count == "auto":
            raise ValueError("optimize.suns: auto is decided before a field is built (stages.model.lights.sun.resolve_suns)")
        if count == 0:
            return None
        return cls(count, samples=settings.sun_samples, total_irradiance=settings.light_energy / 2.0, share=settings.suns_share)

    def fit(self, env: np.ndarray, iterations: int) -> dict:
        """Its suns at the map's brightest compact regions (:func:`find_suns`); what the map keeps
        once they are taken out is :meth:`left_of`'s."""
        found, left = find_suns(env, self.suns)
        self.set_suns(found)
        self._left = (env, left)  # what left_of gives for this map, without searching it again
        return {"suns_found": [s.record() for s in found]}

    def start_at(self, environment: str) -> dict:
        """Start its suns (still learning) at those of ``environment`` (``builtin:<name>`` or a
        map's path; :func:`find_suns`): a learned light's suns where the image targets' are.
        Returns the record of where they started."""
        found, _ = find_suns(load_env(environment, self.fit_height), self.suns)
        self.set_suns(found)
        return {"environment": environment, "suns": [s.record() for s in found]}

    def left_of(self, env: np.ndarray) -> np.ndarray:
        """The map with its suns' regions at their background: what the components fitted after
        it take (the fit's own, where it was just fitted to ``env``)."""
        fitted, self._left = getattr(self, "_left", None), None  # (not kept: a map is megabytes)
        if fitted is not None and fitted[0] is env:
            return fitted[1]
        return find_suns(env, self.suns)[1]

    @torch.no_grad()
    def set_suns(self, found: list[FoundSun]) -> None:
        """Put its suns at ``found`` (:class:`FoundSun`, in order)."""
        lo, hi = RADIUS_RANGE
        for k, sun in enumerate(found[: self.suns]):
            self.axis_raw[k] = torch.from_numpy(sun.direction).to(self.axis_raw)
            self.log_irradiance[k] = torch.log(torch.from_numpy(sun.irradiance).to(self.log_irradiance).clamp(min=1e-30))
            self.log_radius[k] = math.log(min(max(sun.radius, lo), hi))
