"""Procedural equirectangular environment maps (no downloads) and SG fits of environment maps.

``sunset``: a warm low sun, an orange-to-blue sky and a dim ground; ``overcast``: a soft, bright,
nearly uniform sky; ``night``: the same layout as sunset at a twentieth of the brightness (for
checks that a darker environment darkens a render). Rows run from the zenith (row 0) to the
nadir; columns follow the cameras' azimuth (see :func:`stages.networks.equirect_directions`).
"""

from __future__ import annotations

import argparse
import logging
import math
from pathlib import Path

import numpy as np
import torch

from .errors import stage_errors
from .hdrio import write_hdr
from .networks import equirect_directions
from .provenance import setup_logging
from .render.shading import SGLight

log = logging.getLogger(__name__)
PROCEDURAL = ("sunset", "overcast", "night")


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
    else:
        raise ValueError(f"unknown procedural environment {name!r}; choose one of {', '.join(PROCEDURAL)}")
    return img.astype(np.float32)


def fit_sg_light(env: np.ndarray, lobes: int = 64, iterations: int = 400, seed: int = 0) -> tuple[SGLight, float]:
    """Fit ``lobes`` RGB SG lobes to an equirectangular ``env (H, W, 3)`` by least squares
    weighted by solid angle (Adam). Returns the light and the relative RMS error of the fit."""
    from .networks import SGLightModule

    h, w, _ = env.shape
    dirs = equirect_directions(h, w).reshape(-1, 3)
    el = math.pi / 2 - math.pi * (torch.arange(h) + 0.5) / h
    weight = torch.cos(el)[:, None].expand(h, w).reshape(-1, 1)
    target = torch.from_numpy(env.reshape(-1, 3).astype(np.float32))
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        energy = float((target * weight).sum(0).mean() * (2 * math.pi / w) * (math.pi / h))
        module = SGLightModule(lobes, rgb=True, total_energy=max(energy, 1e-6))
        # start a quarter of the lobes, sharper, on the brightest directions (suns, windows)
        order = torch.argsort((target * weight).sum(-1), descending=True)
        with torch.no_grad():
            k = max(lobes // 4, 1)
            picks, taken = [], []
            for idx in order.tolist():
                d = dirs[idx]
                if all(float(d @ t) < 0.95 for t in taken):
                    picks.append(idx)
                    taken.append(d)
                if len(picks) == k:
                    break
            module.axis_raw[: len(picks)] = dirs[picks]
            module.sharpness_raw[: len(picks)] = 100.0
    opt = torch.optim.Adam(module.parameters(), lr=0.03)
    scale = target.abs().max().clamp(min=1e-12)
    for _ in range(iterations):
        light = module()
        err = ((light.radiance(dirs) - target) / scale) ** 2 * weight
        loss = err.mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        light = module()
        diff = (light.radiance(dirs) - target) ** 2 * weight
        rel = math.sqrt(float(diff.sum() / ((target**2) * weight).sum().clamp(min=1e-30)))
    return SGLight(light.axis.detach(), light.sharpness.detach(), light.amplitude.detach()), rel


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m stages.envmap", description="Write a procedural environment map.")
    parser.add_argument("--name", required=True, choices=PROCEDURAL)
    parser.add_argument("--out", required=True, type=Path, help="output .hdr")
    parser.add_argument("--height", type=int, default=128)
    args = parser.parse_args(argv)
    setup_logging()
    with stage_errors("envmap") as status:
        write_hdr(args.out, procedural_envmap(args.name, args.height))
        log.info("wrote %s (%dx%d)", args.out, 2 * args.height, args.height)
    return status.code


if __name__ == "__main__":
    raise SystemExit(main())
