"""The learnable side of a light: :class:`LightModule`, the sum of component modules
(:class:`LightComponentModule`), each of one kind (:mod:`stages.model.lights`).

A component module holds its kind's parameters and makes its renderer's component
(:class:`~stages.render.light.LightComponent`) from them (``forward``); it is built from the field
settings or not at all (:meth:`LightComponentModule.build`), fits itself to an environment map
(:meth:`LightComponentModule.fit`: the known-light mode), describes itself, and carries what only
its kind does (the SG lobes: pruning, the colour prior) behind methods every kind has, which
do nothing for a kind without it. The sum does each over its components; with one component, what
that component does, no more.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterable
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch
from torch import Tensor, nn

from ...config.sections import FieldSettings
from ...core.provenance import sha256_of
from ...render.envmap import downsample, load_env
from ...render.light import Light, LightComponent, summed


@dataclass(frozen=True)
class Pruned:
    """What pruning did to a component: the rows ``index`` it kept of each parameter it replaced,
    the ``(old, new)`` parameter pairs (none where nothing was dropped) so that an optimiser can
    carry their moments, and how many elements it kept and dropped."""

    index: Tensor
    pairs: list[tuple[nn.Parameter, nn.Parameter]]
    kept: int
    dropped: int


class LightComponentModule(nn.Module, ABC):
    """One kind of light, learnable: registered by name in :mod:`stages.model.lights`."""

    #: its kind's name: the registry's key, its place in the light's state (``light.<kind>.``)
    #: and its renderer component's ``kind``
    kind: ClassVar[str]
    #: its SG lobes (what a compiled graph's shapes and the records count): none for other kinds
    lobes: int = 0
    #: where it is fitted among a light's components (:meth:`LightModule.hold`: lowest first, each
    #: taking what those before it left of the map)
    fit_order: ClassVar[int] = 0
    #: the rows of a procedural map its fit reads (:func:`~stages.render.envmap.load_env`)
    fit_height: ClassVar[int] = 128

    @classmethod
    @abstractmethod
    def build(cls, settings: FieldSettings) -> LightComponentModule | None:
        """The component a field of ``settings`` has, built (the global RNG as the field's
        constructor seeded it), or None where it has none of this kind."""

    @abstractmethod
    def forward(self) -> LightComponent:
        """Its renderer component (:class:`~stages.render.light.LightComponent`) from its parameters."""

    @abstractmethod
    def fit(self, env: np.ndarray, iterations: int) -> dict:
        """Put its parameters at its fit of the equirectangular radiance ``env (H, W, 3)`` (the
        known-light mode, :meth:`LightModule.hold`), in ``iterations`` steps where it fits
        iteratively; what the metadata records of the fit."""

    def left_of(self, env: np.ndarray) -> np.ndarray:
        """What is left of the equirectangular ``env (H, W, 3)`` once its fit is taken out, for the
        components fitted after it: the map less its radiance, held at zero."""
        with torch.no_grad():
            carried = Light.of(self()).equirect(*env.shape[:2]).cpu().numpy()
        return np.clip(env - carried, 0.0, None).astype(np.float32)

    def energy(self) -> Tensor:
        """Its radiant energy per channel ``(3,)``."""
        return self().energy()

    def colour_spread(self) -> Tensor | None:
        """Its departure from white, differentiable (the prior ``optimize.light_neutral``), or
        None where its kind has no colour to hold."""
        return None

    def prune(self, share: float) -> Pruned | None:
        """Drop its elements below ``share`` of its energy (``optimize.light_prune_after``), or
        None where its kind prunes nothing."""
        return None

    def match_state(self, state: dict, prefix: str, parent: str) -> None:
        """Make its parameters fit the saved ``state`` (a copy the caller owns: it may rename
        keys) under ``prefix`` (``light.<kind>.``; ``parent``: the light's own, ``light.``) before
        it is loaded: nothing to do unless its shapes change during a run."""

    def describe(self) -> dict:
        """Its renderer component's figures (:meth:`~stages.render.light.LightComponent.describe`)
        and whether it learns."""
        with torch.no_grad():
            figures = self().describe()
        return {**figures, "learns": any(p.requires_grad for p in self.parameters())}


class LightModule(nn.Module):
    """A light of ``components`` (one module per kind, in the registry's order): called, the
    renderer's :class:`~stages.render.light.Light` of them. Each component is its child named by
    its kind (its parameters ``light.<kind>.<name>`` in a field's state)."""

    def __init__(self, components: Iterable[LightComponentModule]) -> None:
        super().__init__()
        for component in components:
            if component.kind in self._modules:
                raise ValueError(f"a light holds one component of each kind: {component.kind} twice")
            self.add_module(component.kind, component)
        if not self._modules:
            raise ValueError("a light needs at least one component")

    @property
    def components(self) -> tuple[LightComponentModule, ...]:
        """Its component modules, in order."""
        return tuple(self.children())  # type: ignore[arg-type]

    def forward(self) -> Light:
        return Light(tuple(component() for component in self.components))

    @property
    def lobes(self) -> int:
        """The SG lobes of its components (:attr:`LightComponentModule.lobes`)."""
        return sum(component.lobes for component in self.components)

    def energy(self) -> Tensor:
        """Its radiant energy per channel ``(3,)``: the sum of its components'."""
        return summed([component.energy() for component in self.components])

    def colour_spread(self) -> Tensor:
        """Its departure from white: the sum of its components' (:meth:`LightComponentModule.colour_spread`;
        zero where none has a colour to hold)."""
        spreads = [s for component in self.components if (s := component.colour_spread()) is not None]
        if not spreads:
            return torch.zeros((), device=next(self.parameters()).device)
        return summed(spreads)

    def prune(self, share: float) -> list[Pruned]:
        """Each pruning component's :meth:`~LightComponentModule.prune` at ``share``."""
        return [p for component in self.components if (p := component.prune(share)) is not None]

    def match_state(self, state: dict, prefix: str) -> dict:
        """A copy of ``state`` (a field's, this light's parameters under ``prefix``) that this
        light's components fit (:meth:`LightComponentModule.match_state`), for loading."""
        state = dict(state)
        for component in self.components:
            component.match_state(state, f"{prefix}{component.kind}.", prefix)
        return state

    def hold(self, spec: str, iterations: int = 400) -> dict:
        """The known-light mode (``optimize.light: fixed``): put the components at their fit of the
        environment ``spec`` (``builtin:<name>`` or an .hdr/.exr path), each fitting what those
        fitted before it left of the map (:attr:`LightComponentModule.fit_order`; a procedural map
        drawn at the first's :attr:`~LightComponentModule.fit_height`, and brought down to a later
        one's by :func:`~stages.render.envmap.downsample`), and stop them learning
        (``requires_grad`` off). Returns what the metadata records: the map, each component's
        record of its fit and, for a file, its sha256."""
        components = sorted(self.components, key=lambda c: c.fit_order)
        env = load_env(spec, components[0].fit_height)
        record: dict = {"map": spec}
        for i, component in enumerate(components):
            if i and env.shape[0] > component.fit_height and env.shape[0] % component.fit_height == 0:
                env = downsample(env, env.shape[0] // component.fit_height)
            record.update(component.fit(env, iterations))
            if i + 1 < len(components):
                env = component.left_of(env)
        for p in self.parameters():
            p.requires_grad_(False)
        if not spec.startswith("builtin:"):  # a file: what it held (a resumed run checks it is the same)
            record["sha256"] = sha256_of(spec)
        return record

    def describe(self) -> list[dict]:
        """Each component's figures (:meth:`LightComponentModule.describe`), in order."""
        return [component.describe() for component in self.components]
