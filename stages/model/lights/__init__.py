"""The kinds of light, found by name: each one module here whose component module
(:class:`~stages.model.lights.base.LightComponentModule`) this registry lists, and a field's
light the sum of those its settings ask for (:func:`build_light`, a
:class:`~stages.model.lights.base.LightModule`).

The kinds: ``sg`` (:mod:`stages.model.lights.sg`, the SG lobes every field has), ``sun``
(:mod:`stages.model.lights.sun`, sharp lights where ``optimize.suns`` asks for them) and ``bounce``
(:mod:`stages.model.lights.bounce`, the mesh's own light, one bounce, where ``optimize.bounces``
asks for it). To add a light,
write its module (its renderer component, :class:`~stages.render.light.LightComponent`, and its
component module: ``build`` from the field settings, ``forward``, ``fit``, and what only it does
behind the methods every kind has) and list its class in :data:`_KINDS`;
``tests/model/test_light_components.py`` shows it on a toy kind (:func:`registered` adds one for a
test), and that a field's render under a sum is the sum of its renders under each component.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch

from ...config.sections import FieldSettings
from ...render.envmap import load_env
from ...render.light import Light
from .base import LightComponentModule, LightModule, Pruned
from .bounce import BounceModule
from .sg import SGLightModule, fit_sg_light
from .sun import SunLightModule, sun_criterion

#: each kind's component module by name, in the order a light holds them
_KINDS: dict[str, type[LightComponentModule]] = {kind.kind: kind for kind in (SGLightModule, SunLightModule, BounceModule)}

__all__ = [
    "BounceModule",
    "LightComponentModule",
    "LightModule",
    "Pruned",
    "SGLightModule",
    "SunLightModule",
    "build_light",
    "fit_environment",
    "fit_environment_like",
    "get",
    "names",
    "registered",
]


def names() -> tuple[str, ...]:
    """The kinds' names, in the order a light holds its components."""
    return tuple(_KINDS)


def get(name: str) -> type[LightComponentModule]:
    """The component module of the kind ``name``; a ValueError naming the kinds for any other."""
    if name not in _KINDS:
        raise ValueError(f"unknown light component {name!r}; the kinds are {', '.join(_KINDS)}")
    return _KINDS[name]


@contextmanager
def registered(*kinds: type[LightComponentModule]) -> Iterator[None]:
    """The ``kinds`` registered (after the others) while the block runs, then gone: a kind a test
    defines, built into every field made inside the block where its ``build`` says so."""
    clash = [k.kind for k in kinds if k.kind in _KINDS]
    if clash:
        raise ValueError(f"light components already registered: {', '.join(clash)}")
    _KINDS.update({k.kind: k for k in kinds})
    try:
        yield
    finally:
        for k in kinds:
            _KINDS.pop(k.kind, None)


def fit_environment(spec: str, lobes: int, iterations: int, suns: int = 0, samples: int = 8) -> tuple[Light, dict]:
    """The light that brings the environment ``spec`` (``builtin:<name>`` or a map's path) into the
    renderer: ``lobes`` SG lobes fitted to it (:func:`~stages.model.lights.sg.fit_sg_light`, in
    ``iterations`` steps) or, with ``suns``, that many suns found in it
    (:func:`~stages.model.lights.sun.find_suns`, ``samples`` directions each) and the lobes fitted
    to what they leave (:meth:`LightModule.hold`). Returns the light and the fit's record
    (``sg_fit_relative_rms``, and the suns found)."""
    if suns == 0:
        fitted, rel = fit_sg_light(load_env(spec), lobes, iterations)
        return Light.of(fitted), {"sg_fit_relative_rms": rel}
    module = LightModule([SGLightModule(lobes), SunLightModule(suns, samples=samples)])
    record = module.hold(spec, iterations)
    with torch.no_grad():
        light = module()
    return light.detach(), {k: v for k, v in record.items() if k not in ("map", "lobes", "sha256")}


def fit_environment_like(light: LightModule, spec: str, lobes: int, iterations: int, directions: int) -> tuple[Light, dict]:
    """:func:`fit_environment` with the transport of a trained ``light`` (a :class:`LightModule`;
    anything else counts as SG lobes alone): suns where it has them
    and the environment ``spec`` holds any by the criterion it was trained with
    (:func:`~stages.model.lights.sun.sun_criterion`, with the cached visibility's ``directions``:
    a sunset relit without a sun, a sunny sky with one), else its SG lobes alone. The relight
    stage's and the relighting budget's light for each environment (and its ceiling's)."""
    sun = dict(light.named_children()).get(SunLightModule.kind) if isinstance(light, torch.nn.Module) else None
    if sun is None:
        return fit_environment(spec, lobes, iterations)
    count, decided = sun_criterion(load_env(spec, SunLightModule.fit_height), directions, sun.share, sun.suns)
    fitted, record = fit_environment(spec, lobes, iterations, count, sun.samples)
    return fitted, {**record, "suns": decided}


def build_light(settings: FieldSettings) -> LightModule:
    """The light of a field of ``settings``: every registered kind's component that its ``build``
    makes, in the registry's order (each drawing from the global RNG as the field seeded it)."""
    return LightModule(c for kind in _KINDS.values() if (c := kind.build(settings)) is not None)
