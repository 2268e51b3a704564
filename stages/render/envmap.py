"""Equirectangular environment maps: pixel directions, procedural skies (no downloads), loading,
and the radiant energy of a map.

``sun_sky``: a clear sky with a hard-edged sun disc (angular radius 1.5 degrees, elevation 35
degrees), a horizon brighter than the zenith, an aureole around the sun and a dim ground below a
sharp horizon: the Mitsuba ground-truth targets' default light, chosen because no finite sum of
spherical Gaussians represents its disc edge or its horizon step. ``sunset``: a warm low sun, an
orange-to-blue sky and a dim ground; ``overcast``: a soft, bright, nearly uniform sky;
``night``: the same layout as sunset at a twentieth of the brightness (for checks that a darker
environment darkens a render); ``studio``: a dim room, a large key softbox and a strip light
(shipped as the file ``config/envmaps/studio.hdr``, the offline demo's "user HDR" for grading
relighting). Rows run from the zenith (row 0) to the nadir; columns follow
the cameras' azimuth (see :func:`equirect_directions`).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..config.sections import PROCEDURAL_ENVMAPS as PROCEDURAL
from ..core.cli import stage_main
from ..core.errors import StageInputError
from .hdrio import read_envmap, write_hdr

log = logging.getLogger(__name__)


def equirect_directions(height: int, width: int) -> Tensor:
    """Unit directions ``(H, W, 3)`` of an equirectangular image, y up: row 0 is the zenith,
    column ``j`` has azimuth ``2 pi (j + 0.5) / W`` measured like the cameras
    (``(cos a, 0, sin a)``)."""
    el = math.pi / 2 - math.pi * (torch.arange(height) + 0.5) / height
    az = 2 * math.pi * (torch.arange(width) + 0.5) / width
    ee, aa = torch.meshgrid(el, az, indexing="ij")
    return torch.stack([torch.cos(ee) * torch.cos(aa), torch.sin(ee), torch.cos(ee) * torch.sin(aa)], dim=-1)


def procedural_envmap(name: str, height: int = 128) -> np.ndarray:
    """``(height, 2 height, 3) float32`` linear radiance of the named procedural sky."""
    d = equirect_directions(height, 2 * height).numpy().astype(np.float64)
    y = d[..., 1]
    if name in ("sunset", "night"):
        sun = np.array([math.cos(0.25) * math.cos(2.0), math.sin(0.25), math.cos(0.25) * math.sin(2.0)])
        cos_sun = d @ sun
        sky = np.where(
            y[..., None] >= 0,
            (1 - y[..., None]) * np.array([1.2, 0.55, 0.25]) + y[..., None] * np.array([0.25, 0.4, 0.9]),
            np.array([0.12, 0.1, 0.08]),
        )
        img = sky + 12.0 * np.exp(150.0 * (cos_sun[..., None] - 1.0)) * np.array([1.0, 0.75, 0.45])
        img += 1.5 * np.exp(20.0 * (cos_sun[..., None] - 1.0)) * np.array([1.0, 0.6, 0.3])
        if name == "night":
            img = img / 20.0
    elif name == "overcast":
        img = np.where(y[..., None] >= 0, 0.9 + 0.3 * y[..., None], 0.3) * np.array([1.0, 1.0, 1.02])
    elif name == "sun_sky":
        img = _sun_sky(d, height)
    elif name == "studio":
        img = _studio(d)
    else:
        raise ValueError(f"unknown procedural environment {name!r}; choose one of {', '.join(PROCEDURAL)}")
    return img.astype(np.float32)


#: the sun of ``sun_sky``: direction (elevation 35 degrees, azimuth 2.2 rad), angular radius, radiance
SUN_ELEVATION = math.radians(35.0)
SUN_AZIMUTH = 2.2
SUN_RADIUS = math.radians(1.5)
SUN_RADIANCE = (1300.0, 1225.0, 1100.0)


def sun_direction() -> np.ndarray:
    """Unit direction ``(3,)`` towards the centre of ``sun_sky``'s sun (y up)."""
    e, a = SUN_ELEVATION, SUN_AZIMUTH
    return np.array([math.cos(e) * math.cos(a), math.sin(e), math.cos(e) * math.sin(a)])


def _sun_sky(d: np.ndarray, height: int) -> np.ndarray:
    y = d[..., 1:2]
    angle = np.arccos(np.clip(d @ sun_direction(), -1.0, 1.0))[..., None]
    up = np.clip(y, 0.0, 1.0)
    zenith, horizon = np.array([0.08, 0.15, 0.35]), np.array([0.31, 0.34, 0.40])
    sky = zenith + (horizon - zenith) * (1.0 - up) ** 4 + 0.45 * np.exp(-angle / 0.12) * np.array([1.0, 0.9, 0.7])
    ground = np.array([0.08, 0.065, 0.05]) * (0.6 + 0.4 * np.clip(-y, 0.0, 1.0))
    img = np.where(y >= 0.0, sky, ground)
    # the disc, its edge anti-aliased over one pixel's angular size
    pixel = math.pi / height
    cover = np.clip((SUN_RADIUS - angle) / pixel + 0.5, 0.0, 1.0)
    return img + cover * np.array(SUN_RADIANCE)


def _softbox(d: np.ndarray, centre: np.ndarray, half_width: float, half_height: float) -> np.ndarray:
    """``(...)`` in [0, 1]: directions ``d`` inside an upright rectangle of angular half sizes
    (radians) around ``centre``, its edges softened over about a degree."""
    c = centre / np.linalg.norm(centre)
    right = np.cross(c, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, c)
    ahead = np.clip(d @ c, 1e-6, None)
    x, y = np.arctan2(d @ right, ahead), np.arctan2(d @ up, ahead)
    edge = math.radians(1.0)
    inside = np.clip((half_width - np.abs(x)) / edge + 0.5, 0, 1) * np.clip((half_height - np.abs(y)) / edge + 0.5, 0, 1)
    return np.where(d @ c > 0, inside, 0.0)


def _studio(d: np.ndarray) -> np.ndarray:
    """A photo studio: a dim warm room, a large cool-white key softbox high on one side, a narrow
    warm strip light behind the object on the other and a brighter floor: hard-edged rectangles
    that, like a sun, no SG sum represents exactly, from directions the sky maps do not use."""
    y = d[..., 1:2]
    room = np.where(y >= 0, 0.06 + 0.03 * y, 0.10) * np.array([1.0, 0.95, 0.88])
    key = _softbox(d, np.array([0.8, 0.55, 0.45]), math.radians(22.0), math.radians(14.0))[..., None]
    strip = _softbox(d, np.array([-0.7, 0.25, -0.65]), math.radians(4.0), math.radians(25.0))[..., None]
    return room + 4.0 * key * np.array([0.95, 1.0, 1.05]) + 6.0 * strip * np.array([1.0, 0.85, 0.65])


def load_env(spec: str, height: int = 128) -> np.ndarray:
    """``(H, W, 3) float32`` radiance of ``spec``: a ``.hdr``/``.exr`` path or ``builtin:<name>``
    (procedural maps at ``height`` rows; files at their own size)."""
    if spec.startswith("builtin:"):
        name = spec.split(":", 1)[1]
        if name not in PROCEDURAL:
            raise StageInputError(spec, f"no procedural environment {name!r}", f"Use one of {', '.join(PROCEDURAL)}.")
        return procedural_envmap(name, height)
    return read_envmap(spec)


def solid_angles(height: int, width: int) -> np.ndarray:
    """Solid angle ``(H, 1)`` of each pixel of an equirectangular image's rows (exact, per row:
    ``2 pi / W (cos(theta_top) - cos(theta_bottom))``); the rows sum to ``4 pi``."""
    theta = np.pi * np.arange(height + 1) / height
    return (2.0 * np.pi / width * (np.cos(theta[:-1]) - np.cos(theta[1:])))[:, None]


def downsample(env: np.ndarray, factor: int) -> np.ndarray:
    """An equirectangular ``env (H, W, 3)`` at ``1 / factor`` of its rows and columns (both
    divisible by ``factor``): each pixel the solid-angle-weighted mean of its block, so that the
    map keeps its radiant energy (:func:`radiant_energy`) exactly."""
    h, w, c = env.shape
    if h % factor or w % factor:
        raise ValueError(f"a map of {h} x {w} pixels cannot be brought down by {factor}")
    weight = np.broadcast_to(solid_angles(h, w).reshape(h, -1)[..., None], (h, w, 1)).astype(np.float64)
    blocks = (env.astype(np.float64) * weight).reshape(h // factor, factor, w // factor, factor, c).sum((1, 3))
    area = weight.reshape(h // factor, factor, w // factor, factor, 1).sum((1, 3))
    return (blocks / area).astype(np.float32)


def radiant_energy(env: np.ndarray) -> np.ndarray:
    """``int L(w) dw`` over the sphere, per channel ``(3,)``, of an equirectangular ``env (H, W, 3)``
    (exact for a map constant over each pixel)."""
    h, w, _ = env.shape
    return (env.astype(np.float64) * solid_angles(h, w)[..., None]).sum((0, 1))


def main(argv: list[str] | None = None) -> int:
    """``python -m stages.render.envmap --name sunset --out sunset.hdr``: write a procedural map."""

    def arguments(parser):
        parser.add_argument("--name", required=True, choices=PROCEDURAL)
        parser.add_argument("--out", required=True, type=Path, help="output .hdr")
        parser.add_argument("--height", type=int, default=128)

    def body(args):
        write_hdr(args.out, procedural_envmap(args.name, args.height))
        log.info("wrote %s (%dx%d)", args.out, 2 * args.height, args.height)

    return stage_main("render.envmap", "Write a procedural environment map.", arguments, body, argv)


if __name__ == "__main__":
    raise SystemExit(main())
