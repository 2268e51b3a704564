"""Lights as the renderer sees them: a :class:`Light` is a sum of components
(:class:`LightComponent`), each one kind of light that shades a surface with a BRDF object, gives
its radiance in directions and describes itself (:mod:`stages.render.light.base`).

The kinds: ``sg``, :class:`~stages.render.shading.SGLight` (``K`` spherical-Gaussian lobes,
whose closed-form integrals the BRDFs' ``shade`` computes), and ``sun``,
:class:`~stages.render.light.sun.SunLight` (discs of uniform radiance, shaded by the BRDF at
directions inside them, each shadowed by its own ray). A kind is found by name where it is
learned (:mod:`stages.model.lights`: its module, its fit to an environment map, its files); its
math for the renderer is its own module here (the SG lobes', being what every BRDF integrates,
live in :mod:`stages.render.shading`).
"""

from __future__ import annotations

from ..shading import SGLight
from .base import DistantLight, Light, LightComponent, Visibility, cat_visibility, map_visibility, summed
from .sun import SunLight

__all__ = [
    "DistantLight",
    "Light",
    "LightComponent",
    "SGLight",
    "SunLight",
    "Visibility",
    "cat_visibility",
    "map_visibility",
    "summed",
]
