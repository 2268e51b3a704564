"""The kinds of light, found by name: each one module here whose component module
(:class:`~stages.model.lights.base.LightComponentModule`) this registry lists, and a field's
light the sum of those its settings ask for (:func:`build_light`, a
:class:`~stages.model.lights.base.LightModule`).

The kinds: ``sg`` (:mod:`stages.model.lights.sg`, the SG lobes every field has). To add a light,
write its module (its renderer component, :class:`~stages.render.light.LightComponent`, and its
component module: ``build`` from the field settings, ``forward``, ``fit``, and what only it does
behind the methods every kind has) and list its class in :data:`_KINDS`;
``tests/model/test_light_components.py`` shows it on a toy kind (:func:`registered` adds one for a
test), and that a field's render under a sum is the sum of its renders under each component.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from ...config.sections import FieldSettings
from .base import LightComponentModule, LightModule, Pruned
from .sg import SGLightModule

#: each kind's component module by name, in the order a light holds them
_KINDS: dict[str, type[LightComponentModule]] = {kind.kind: kind for kind in (SGLightModule,)}

__all__ = ["LightComponentModule", "LightModule", "Pruned", "SGLightModule", "build_light", "get", "names", "registered"]


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


def build_light(settings: FieldSettings) -> LightModule:
    """The light of a field of ``settings``: every registered kind's component that its ``build``
    makes, in the registry's order (each drawing from the global RNG as the field seeded it)."""
    return LightModule(c for kind in _KINDS.values() if (c := kind.build(settings)) is not None)
