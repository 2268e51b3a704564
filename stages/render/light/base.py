"""What a light is to the renderer: a sum of components (:class:`Light`), each one kind of light
(:class:`LightComponent`).

A component **shades** a surface with a BRDF object (:class:`~stages.render.brdf.Brdf`) given
the shaded points' normal, view, material, specular lobe model and the component's own
visibility input (the SG lobes: each lobe's visible share), **gives its radiance** in directions
(the environment image, the fits), its **energy**, and **describes** itself (plain figures for
the metadata; the arrays ``light.npz`` holds of it). A sum does each over its components: it
shades as the sum of their :class:`~stages.render.shading.Shading` s and radiates the sum of
their radiance. A sum of one component is that component: the same operations in the same order,
no zero added, so that a light of SG lobes alone shades, compiled or not, exactly as the SG light
did before lights were sums.

A component's visibility input has one row per shaded point (or is None: unshadowed), so that
callers pad, cut and concatenate a light's :data:`Visibility` by rows without knowing the kinds
(:func:`map_visibility`, :func:`cat_visibility`); a component finds its input in the shadows a
caller holds (:meth:`LightComponent.shadowed_by`: the SG lobes ask a
:class:`~stages.model.shadows.ShadowCache` for their shares).
"""

from __future__ import annotations

import functools
import operator
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Protocol

import numpy as np
import torch
from torch import Tensor

from ..distant import DistantLight
from ..envmap import equirect_directions
from ..shading import Shading

#: a light's visibility inputs, one per component in its order (each ``(N, ...)``, one row per
#: shaded point, or None: that component unshadowed); None for the whole: no shadows at all
Visibility = tuple[Tensor | None, ...]


class LightComponent(Protocol):
    """One kind of light to the renderer (the SG lobes: :class:`~stages.render.shading.SGLight`),
    its tensors on one device."""

    #: the kind's name (its registry's key, :mod:`stages.model.lights`)
    kind: ClassVar[str]
    #: how an asset carries it: drawn into the environment image (True), or as distant lights
    #: (:meth:`distant_lights`; False)
    in_environment: ClassVar[bool]

    @property
    def device(self) -> torch.device:
        """The device its tensors are on."""
        ...

    def shade(
        self, brdf: Any, normal: Tensor, view: Tensor, material: Any, lobe: str | None, visibility: Tensor | None
    ) -> Shading:
        """Diffuse and specular radiance ``(N, 3)`` it gives ``material`` (of the BRDF object
        ``brdf``) at unit ``normal`` and ``view (N, 3)`` with the specular lobe model ``lobe``
        (None: the BRDF's own), shadowed by its ``visibility`` input (None: unshadowed)."""
        ...

    def radiance(self, directions: Tensor) -> Tensor:
        """Its radiance ``(..., C)`` arriving from unit ``directions (..., 3)``."""
        ...

    def energy(self) -> Tensor:
        """Its radiant energy per channel ``(C,)``: its radiance integrated over the sphere."""
        ...

    def describe(self) -> dict:
        """Plain figures of it for the metadata, ``kind`` first."""
        ...

    def arrays(self) -> dict[str, np.ndarray]:
        """The arrays ``light.npz`` holds of it, by names no other kind uses."""
        ...

    def distant_lights(self) -> list[DistantLight]:
        """It as distant lights, for a kind an asset does not draw into its environment image
        (``in_environment`` False); empty for one it does."""
        ...

    def shadowed_by(self, shadows: Any, index: Tensor | None) -> Tensor | None:
        """Its visibility input at the points ``index`` (all when None) of ``shadows`` (a
        :class:`~stages.model.shadows.ShadowCache`), one row per point, or None where it takes none."""
        ...

    def like(self, leaf: Callable[..., Tensor]) -> LightComponent:
        """One of its shape with every tensor made from ``leaf(*shape)`` (random, needing a gradient
        as its parameters do): what a compiled graph's first pass shades
        (:mod:`stages.model.compiled`)."""
        ...

    def visibility_like(self, leaf: Callable[..., Tensor], points: int) -> Tensor | None:
        """A visibility input of its shape at ``points`` points from ``leaf(*shape)`` (None where it takes none)."""
        ...

    def to(self, device: torch.device | str) -> LightComponent:
        """The same component on ``device``."""
        ...

    def detach(self) -> LightComponent:
        """The same component without gradients."""
        ...


def summed(values: Sequence):
    """The sum of ``values`` (at least one) in their order, the one value itself where there is
    one (no zero added: a light of one component computes what that component does)."""
    return functools.reduce(operator.add, values)


@dataclass(frozen=True)
class Light:
    """A light: the sum of its ``components`` (at least one; at most one of each kind)."""

    components: tuple[LightComponent, ...]

    @classmethod
    def of(cls, *components: LightComponent) -> Light:
        """The light that is the sum of ``components``."""
        return cls(tuple(components))

    def __post_init__(self) -> None:
        kinds = [c.kind for c in self.components]
        if not kinds or len(set(kinds)) != len(kinds):
            raise ValueError(f"a light is a sum of one or more components of distinct kinds, not {kinds}")

    @property
    def device(self) -> torch.device:
        """The device its components' tensors are on (the first's)."""
        return self.components[0].device

    def shade(
        self,
        brdf: Any,
        normal: Tensor,
        view: Tensor,
        material: Any,
        lobe: str | None = None,
        visibility: Visibility | None = None,
    ) -> Shading:
        """The sum of its components' shading (:meth:`LightComponent.shade`) of ``material`` at
        ``normal`` and ``view (N, 3)``, each shadowed by its entry of ``visibility`` (None: none
        shadowed)."""
        inputs = visibility if visibility is not None else (None,) * len(self.components)
        parts = [c.shade(brdf, normal, view, material, lobe, v) for c, v in zip(self.components, inputs, strict=True)]
        if len(parts) == 1:
            return parts[0]
        return Shading(summed([p.diffuse for p in parts]), summed([p.specular for p in parts]))

    def radiance(self, directions: Tensor) -> Tensor:
        """The sum of its components' radiance ``(..., C)`` from unit ``directions (..., 3)``."""
        return summed([c.radiance(directions) for c in self.components])

    def equirect(self, height: int, width: int) -> Tensor:
        """Its radiance as an equirectangular image ``(height, width, C)``
        (:func:`~stages.render.envmap.equirect_directions`): the environment image it is."""
        dirs = equirect_directions(height, width).to(self.device)
        return self.radiance(dirs.reshape(-1, 3)).reshape(height, width, -1)

    def energy(self) -> Tensor:
        """Its radiant energy per channel ``(C,)``: the sum of its components'."""
        return summed([c.energy() for c in self.components])

    def describe(self) -> list[dict]:
        """Each component's figures (:meth:`LightComponent.describe`), in order."""
        return [c.describe() for c in self.components]

    def arrays(self) -> dict[str, np.ndarray]:
        """What ``light.npz`` holds of its components, their arrays merged (each kind names its own)."""
        out: dict[str, np.ndarray] = {}
        for c in self.components:
            mine = c.arrays()
            clash = sorted(out.keys() & mine.keys())
            if clash:
                raise ValueError(f"the {c.kind} light names arrays another component wrote: {', '.join(clash)}")
            out.update(mine)
        return out

    def environment(self) -> Light | None:
        """Its components an asset draws into its environment image (``in_environment``), or None
        where it has none."""
        kept = tuple(c for c in self.components if c.in_environment)
        return Light(kept) if kept else None

    def distant_lights(self) -> list[DistantLight]:
        """What an asset carries of it as distant lights (its components' that are not drawn into
        the environment image), in order."""
        return [d for c in self.components if not c.in_environment for d in c.distant_lights()]

    def shadowed_by(self, shadows: Any, index: Tensor | None = None) -> Visibility:
        """Each component's visibility input from ``shadows`` at the points ``index`` (all when None)."""
        return tuple(c.shadowed_by(shadows, index) for c in self.components)

    def like(self, leaf: Callable[..., Tensor]) -> Light:
        """A light of its shape from ``leaf`` (:meth:`LightComponent.like`)."""
        return Light(tuple(c.like(leaf) for c in self.components))

    def visibility_like(self, leaf: Callable[..., Tensor], points: int) -> Visibility:
        """Visibility inputs of its shape at ``points`` points from ``leaf``."""
        return tuple(c.visibility_like(leaf, points) for c in self.components)

    def to(self, device: torch.device | str) -> Light:
        return Light(tuple(c.to(device) for c in self.components))

    def detach(self) -> Light:
        return Light(tuple(c.detach() for c in self.components))


def map_visibility(fn: Callable[[Tensor], Tensor], visibility: Visibility | None) -> Visibility | None:
    """``fn`` applied to each input of ``visibility`` (its rows cut, padded, moved), None kept."""
    if visibility is None:
        return None
    return tuple(None if v is None else fn(v) for v in visibility)


def cat_visibility(parts: Sequence[Visibility]) -> Visibility:
    """The visibility inputs of several sets of points as one, in order (by rows)."""
    return tuple(None if any(v is None for v in each) else torch.cat(list(each)) for each in zip(*parts, strict=True))
