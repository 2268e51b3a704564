"""The SG lobes (kind ``sg``): ``K`` learnable spherical-Gaussian lobes, the light TANGO learns
(:class:`SGLightModule`, its renderer's component :class:`~stages.render.shading.SGLight`), and
SG fits of environment maps, how the relight stage brings any map into the renderer and the
known-light mode holds the lobes (:func:`fit_sg_light`)."""

from __future__ import annotations

import hashlib
import math

import numpy as np
import torch
from torch import Tensor, nn

from ...config.sections import LIGHT_INITS, FieldSettings
from ...render.envmap import equirect_directions, radiant_energy
from ...render.sg import one_minus_exp_neg2x_over_x, sg_integral
from ...render.shading import SGLight
from .base import LightComponentModule, Pruned


def fibonacci_sphere(k: int) -> Tensor:
    """``k`` nearly uniform unit directions ``(k, 3)`` on a Fibonacci spiral (y up)."""
    i = torch.arange(k, dtype=torch.float64) + 0.5
    polar = torch.acos(1.0 - 2.0 * i / k)
    azim = math.pi * (1.0 + 5.0**0.5) * i
    return torch.stack([torch.cos(azim) * torch.sin(polar), torch.cos(polar), torch.sin(azim) * torch.sin(polar)], dim=-1).float()


#: the range a lobe's sharpness is kept in: from nearly constant to a sun of 0.5 degrees radius
#: (the L2-best SG of a disc of radius r has sharpness 1.2564 / (1 - cos r), about 33,000 there)
SHARPNESS_RANGE = (1e-4, 1e5)
#: a lobe's energy is kept below exp(this) (a bound that no scene reaches, far from float32's overflow)
LOG_ENERGY_MAX = 30.0


def broad_sharpness(lobes: int) -> float:
    """The sharpness at which neighbouring lobes of a ``lobes``-point Fibonacci sphere (spacing
    ``sqrt(4 pi / lobes)``) overlap at half maximum: ``ln 2 / (1 - cos spacing)`` (1.9 for 16 lobes)."""
    spacing = math.sqrt(4.0 * math.pi / lobes)
    return math.log(2.0) / (1.0 - math.cos(spacing))


def initial_sharpness(lobes: int, init: str = "broad", sharpness: float | None = None, max_sharpness: float = 1000.0) -> Tensor:
    """Each lobe's starting sharpness ``(lobes, 1)`` for the initialisation ``init`` (LIGHT_INITS).

    ``broad``: ``sharpness``, or :func:`broad_sharpness`; ``tango``: ``20 + |z| 100`` with ``z`` drawn
    from the global RNG (the caller seeds it); ``spread``: ``lo (max_sharpness / lo)^t_k`` with
    ``lo`` the broad sharpness and ``t_k = frac(k phi)`` (``phi`` the golden ratio), so that the
    sharpnesses cover ``[lo, max_sharpness]`` evenly in the log and neighbours on the Fibonacci
    sphere (consecutive indices) differ."""
    lo = float(sharpness) if sharpness is not None else broad_sharpness(lobes)
    if init == "broad":
        return torch.full((lobes, 1), lo)
    if init == "tango":
        return 20.0 + torch.randn(lobes, 1).abs() * 100.0
    if init == "spread":
        t = torch.remainder(torch.arange(lobes, dtype=torch.float64) * (math.sqrt(5.0) - 1.0) / 2.0, 1.0)
        hi = max(float(max_sharpness), lo)
        return (lo * (hi / lo) ** t)[:, None].float()
    raise ValueError(f"unknown light initialisation {init!r}; choose one of {', '.join(LIGHT_INITS)}")


#: the light module's parameters, in the order :meth:`SGLightModule.keep` returns them
LIGHT_PARAMETERS = ("axis_raw", "log_sharpness", "log_energy")


def colour_spread(log_energy: Tensor) -> Tensor:
    """How far a light is from white: per lobe the variance over the channels of its log energy
    ``log_energy (K, C)``, weighted by the lobe's share of the light's energy (the weights held
    constant), -> ``()``. Zero for a light whose every lobe is grey whatever its brightness; 2/3 of
    ``(ln r)^2`` for a light whose lobes are all ``(r, 1, 1/r)``-coloured. The prior of
    ``optimize.light_neutral`` (nvdiffrec holds its light towards white per texel, in linear
    radiance; in log energy a lobe's colour is held at any brightness). Finite for any energy the
    parametrisation reaches (``log_energy`` is clamped there)."""
    centred = log_energy - log_energy.mean(-1, keepdim=True)
    with torch.no_grad():
        e = torch.exp(log_energy - log_energy.max()).sum(-1)
        w = e / e.sum().clamp(min=torch.finfo(e.dtype).tiny)
    return (w * centred.pow(2).mean(-1)).sum()


class SGLightModule(LightComponentModule):
    """The light component of kind ``sg``: ``K`` learnable SG lobes on a Fibonacci sphere, with
    sharpnesses from :func:`initial_sharpness` and equal energies summing to ``total_energy``
    (``E = sum_k int G_k``, the true SG integral; TANGO's eq. 7 divides by ``1 - exp(-2 lam)``
    where the integral multiplies, which we do not follow). ``rgb=False`` learns one energy per
    lobe (monochrome light).

    Parametrisation (multiplicative, so that an Adam step, about the learning rate in each raw
    parameter, changes sharpness and energy by a *factor*: 400 steps at 0.02 can sharpen a lobe
    from 2 to about 6000, where an additive softplus moved it by at most 8): unit axes
    ``u / |u|``; sharpness ``exp(s)`` with ``s`` clamped to ``log SHARPNESS_RANGE``; per channel the
    lobe's energy ``exp(e)`` (``e <= LOG_ENERGY_MAX``), from which the amplitude follows,
    ``mu = E / (2 pi (1 - exp(-2 lam)) / lam)`` (:func:`~stages.render.sg.sg_integral` inverted,
    stable for every sharpness). Parametrising energy rather than amplitude keeps a lobe's
    brightness when it sharpens, so the gradient in ``s`` sees the lobe's shape alone.

    With ``E = 2 pi`` (TANGO initialises 6.25), a uniform environment has radiance 0.5, so a white
    diffuse surface renders at 0.5.
    """

    kind = "sg"

    def __init__(
        self,
        lobes: int = 32,
        *,
        rgb: bool = True,
        total_energy: float = 6.25,
        init: str = "broad",
        init_sharpness: float | None = None,
        max_init_sharpness: float = 1000.0,
    ) -> None:
        super().__init__()
        channels = 3 if rgb else 1
        lam = initial_sharpness(lobes, init, init_sharpness, max_init_sharpness).clamp(*SHARPNESS_RANGE)
        self.axis_raw = nn.Parameter(fibonacci_sphere(lobes))
        self.log_sharpness = nn.Parameter(torch.log(lam))
        self.log_energy = nn.Parameter(torch.full((lobes, channels), math.log(total_energy / lobes)))

    def forward(self) -> SGLight:
        axis = self.axis_raw / torch.linalg.vector_norm(self.axis_raw, dim=-1, keepdim=True)
        lo, hi = (math.log(x) for x in SHARPNESS_RANGE)
        lam = torch.exp(self.log_sharpness.clamp(lo, hi))
        energy = torch.exp(self.log_energy.clamp(max=LOG_ENERGY_MAX))
        amp = energy / (2.0 * math.pi * one_minus_exp_neg2x_over_x(lam))
        if amp.shape[-1] == 1:
            amp = amp.expand(-1, 3)
        return SGLight(axis, lam, amp)

    @classmethod
    def build(cls, settings: FieldSettings) -> SGLightModule:
        """Every field has its SG lobes: ``light_lobes`` of them, started as ``light_init`` says
        with ``light_energy`` in all (RGB unless ``light_rgb`` is off)."""
        return cls(
            settings.light_lobes,
            rgb=settings.light_rgb,
            total_energy=settings.light_energy,
            init=settings.light_init,
            init_sharpness=settings.light_init_sharpness,
            max_init_sharpness=settings.light_init_max_sharpness,
        )

    def fit(self, env: np.ndarray, iterations: int) -> dict:
        """Its lobes at the SG fit of ``env`` (:func:`fit_sg_light` with its number of lobes, RGB
        only): the lobes and the fit's relative RMS error."""
        if self.log_energy.shape[1] != 3:
            raise ValueError("a fixed light needs an RGB light (optimize.light_rgb: true)")
        fitted, rel = fit_sg_light(env, self.lobes, iterations)
        energy = sg_integral(fitted.sharpness, fitted.amplitude)
        self.set_lobes(torch.arange(self.lobes), fitted.axis, fitted.sharpness, energy)
        return {"lobes": self.lobes, "sg_fit_relative_rms": rel}

    @torch.no_grad()
    def set_lobes(self, index: Tensor, axis: Tensor, sharpness: Tensor, energy: Tensor | None = None) -> None:
        """Put lobes ``index`` at unit ``axis (n, 3)`` with ``sharpness (n, 1)`` (and per-channel
        ``energy (n, C)`` when given) in the parametrisation's terms."""
        self.axis_raw[index] = axis.to(self.axis_raw)
        lo, hi = SHARPNESS_RANGE
        self.log_sharpness[index] = torch.log(sharpness.to(self.log_sharpness).clamp(lo, hi))
        if energy is not None:
            self.log_energy[index] = torch.log(energy.to(self.log_energy).clamp(min=1e-30))

    def colour_spread(self) -> Tensor:
        """The light's departure from white (:func:`colour_spread`), differentiable in its energies."""
        return colour_spread(self.log_energy.clamp(max=LOG_ENERGY_MAX))

    def lobe_energy(self) -> Tensor:
        """Each lobe's energy per channel ``(K, 3)``: its sphere integral (:func:`sg_integral`)."""
        light = self()
        return sg_integral(light.sharpness, light.amplitude)

    def negligible(self, share: float) -> Tensor:
        """``(K,)`` bool: lobes whose energy is below ``share`` of the light's total in every
        channel (never all of them: the brightest lobe always stays)."""
        with torch.no_grad():
            e = self.lobe_energy()
            small = (e < share * e.sum(0, keepdim=True)).all(-1)
            small[e.sum(-1).argmax()] = False
        return small

    def keep(self, index: Tensor) -> list[tuple[nn.Parameter, nn.Parameter]]:
        """Keep only the lobes ``index`` (indices into the current ``K``), as new parameters;
        returns the ``(old, new)`` parameter pairs so that an optimiser can follow them."""
        pairs = []
        for name in LIGHT_PARAMETERS:
            old = getattr(self, name)
            new = nn.Parameter(old.detach()[index.to(old.device)].clone())
            setattr(self, name, new)
            pairs.append((old, new))
        return pairs

    def prune(self, share: float) -> Pruned:
        """Keep the lobes that are not :meth:`negligible` at ``share`` (:meth:`keep`; the
        parameters stay where none is dropped)."""
        small = self.negligible(share)
        index = torch.nonzero(~small).flatten()
        dropped = int(small.sum())
        return Pruned(index, self.keep(index) if dropped else [], len(index), dropped)

    def match_state(self, state: dict, prefix: str, parent: str) -> None:
        """Its parameters as ``state`` holds them: under ``parent`` itself where the state was
        written before lights were sums (``field.pt`` format 2: ``light.axis_raw``), moved under
        ``prefix``; and a light whose lobes were pruned (``light_prune_after``) shrunk to the saved
        number of lobes first (its parameters are new objects then)."""
        for name in LIGHT_PARAMETERS:
            if parent + name in state and prefix + name not in state:
                state[prefix + name] = state.pop(parent + name)
        saved = state.get(prefix + "axis_raw")
        if saved is not None and saved.shape[0] < self.lobes:
            self.keep(torch.arange(saved.shape[0]))

    @property
    def lobes(self) -> int:
        """Its number of lobes ``K``."""
        return int(self.axis_raw.shape[0])


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
