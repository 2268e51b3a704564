"""Fitting SG lobes to an environment map (how relighting brings any map into the renderer)."""

from __future__ import annotations

import hashlib
import math

import numpy as np
import torch

from ..core.provenance import sha256_of
from ..render.envmap import equirect_directions, load_env, radiant_energy
from ..render.sg import sg_integral
from ..render.shading import SGLight
from .networks import SGLightModule

#: fits already made in this process: (the map's digest, shape, lobes, iterations, seed) -> the
#: light's parameters and the fit's error (a few hundred numbers each; the oldest dropped first)
_FITS: dict[tuple, tuple[tuple[torch.Tensor, ...], float]] = {}
_FITS_KEPT = 16


def fit_sg_light(env: np.ndarray, lobes: int = 64, iterations: int = 400, seed: int = 0) -> tuple[SGLight, float]:
    """Fit ``lobes`` RGB SG lobes to an equirectangular ``env (H, W, 3)`` by least squares
    weighted by solid angle (Adam), the lobes carrying the map's radiant energy per channel
    exactly. Returns the light and the relative RMS error of the fit.

    The fit is a function of its arguments alone: seeded, with a stable order of the brightest
    directions, on one thread (a sum split over threads rounds differently, and 400 Adam steps
    carry the difference into the lobes) and its error summed in float64, so every job and process
    on a machine gets the same bits for the same map; gradients are on whatever the caller's mode
    (a caller under ``torch.no_grad`` still fits). One process fits a map once: a second call with
    the same map (by content), lobes, iterations and seed returns a copy of the first result (the
    relight stage fits its map for the figures and again to grade it)."""
    arr = np.ascontiguousarray(env, dtype=np.float32)
    key = (hashlib.sha256(arr.tobytes()).hexdigest(), arr.shape, int(lobes), int(iterations), int(seed))
    if key not in _FITS:
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            with torch.enable_grad():
                light, rel = _fit(arr, lobes, iterations, seed)
        finally:
            torch.set_num_threads(threads)
        while len(_FITS) >= _FITS_KEPT:
            _FITS.pop(next(iter(_FITS)))
        _FITS[key] = ((light.axis, light.sharpness, light.amplitude), rel)
    params, rel = _FITS[key]
    return SGLight(*(t.clone() for t in params)), rel


def with_energy(light: SGLight, energy: torch.Tensor) -> SGLight:
    """``light`` with its amplitudes scaled per channel so that its radiant energy, the sum of its
    lobes' sphere integrals, is ``energy (3,)`` (a channel without energy stays dark)."""
    have = sg_integral(light.sharpness, light.amplitude).sum(0)
    factor = torch.where(have > 0, energy / have.clamp(min=torch.finfo(have.dtype).tiny), torch.zeros_like(have))
    return SGLight(light.axis, light.sharpness, light.amplitude * factor)


def _fit(env: np.ndarray, lobes: int, iterations: int, seed: int) -> tuple[SGLight, float]:
    """:func:`fit_sg_light`'s work, uncached: least squares under the constraint that the lobes
    carry the map's radiant energy per channel (:func:`with_energy`). Unconstrained, the fit of
    ``builtin:sun_sky`` carried 19-43% too much energy, more in red than in blue (a sun sharper than
    the map's pixels leaves a sharp lobe's energy free): a light too bright and too red in every
    ceiling and in the known-light mode."""
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
        order = torch.argsort((target * weight).sum(-1), descending=True, stable=True)
        k = max(lobes // 4, 1)
        picks, taken = [], []
        for idx in order.tolist():
            d = dirs[idx]
            if all(float(d @ t) < 0.95 for t in taken):
                picks.append(idx)
                taken.append(d)
            if len(picks) == k:
                break
        module.set_lobes(torch.arange(len(picks)), dirs[picks], torch.full((len(picks), 1), 100.0))
    opt = torch.optim.Adam(module.parameters(), lr=0.03)
    scale = target.abs().max().clamp(min=1e-12)
    goal_energy = torch.from_numpy(radiant_energy(env)).float()
    for _ in range(iterations):
        light = with_energy(module(), goal_energy)
        err = ((light.radiance(dirs) - target) / scale) ** 2 * weight
        loss = err.mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        light = with_energy(module(), goal_energy)
        fit, goal, w = (x.double().numpy() for x in (light.radiance(dirs), target, weight))
        rel = math.sqrt(float(((fit - goal) ** 2 * w).sum()) / max(float((goal**2 * w).sum()), 1e-30))
    return SGLight(light.axis.detach(), light.sharpness.detach(), light.amplitude.detach()), rel


def hold_environment(module: SGLightModule, spec: str, iterations: int = 400) -> dict:
    """The known-light mode (``optimize.light: fixed``): put ``module``'s lobes at the SG fit of the
    environment ``spec`` (``builtin:<name>`` or an .hdr/.exr path; :func:`fit_sg_light` with the
    module's number of lobes) and stop them learning (``requires_grad`` off). Returns what the
    metadata records: the map, its lobes, the fit's relative RMS error and, for a file, its sha256."""
    if module.log_energy.shape[1] != 3:
        raise ValueError("a fixed light needs an RGB light (optimize.light_rgb: true)")
    fitted, rel = fit_sg_light(load_env(spec), module.lobes, iterations)
    energy = sg_integral(fitted.sharpness, fitted.amplitude)
    index = torch.arange(module.lobes)
    module.set_lobes(index, fitted.axis, fitted.sharpness, energy)
    for p in module.parameters():
        p.requires_grad_(False)
    record = {"map": spec, "lobes": module.lobes, "sg_fit_relative_rms": rel}
    if not spec.startswith("builtin:"):  # a file: what it held (a resumed run checks it is the same)
        record["sha256"] = sha256_of(spec)
    return record
