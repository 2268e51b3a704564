"""A light from a disc of directions as an asset file carries it (:class:`DistantLight`), without
torch: the export reads it from the bake's record, the renderer's suns make it."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class DistantLight:
    """A light from a disc of directions, as an asset file carries it: the unit ``direction`` it
    comes from ``(3,)``, the ``irradiance`` per channel it gives a surface facing it unshadowed
    (the environment image's units), and its angular ``radius`` (radians; 0: a directional light).
    A glTF ``KHR_lights_punctual`` directional light, a USD ``DistantLight`` (whose ``angle`` is
    the diameter), a Blender sun."""

    direction: tuple[float, float, float]
    irradiance: tuple[float, ...]
    radius: float

    def record(self) -> dict:
        """As plain figures: ``direction``, ``irradiance``, ``radius_deg``."""
        return {
            "direction": [float(x) for x in self.direction],
            "irradiance": [float(x) for x in self.irradiance],
            "radius_deg": math.degrees(self.radius),
        }

    @classmethod
    def from_record(cls, record: dict) -> DistantLight:
        """The light :meth:`record` wrote (its direction normalised again)."""
        d = np.asarray(record["direction"], np.float64)
        d = d / np.linalg.norm(d)
        return cls(tuple(float(x) for x in d), tuple(float(x) for x in record["irradiance"]), math.radians(record["radius_deg"]))

    def turned(self, rotation: np.ndarray) -> DistantLight:
        """The same light with its direction ``rotation (3, 3) @ direction``."""
        d = np.asarray(rotation, np.float64) @ np.asarray(self.direction, np.float64)
        return DistantLight(tuple(float(x) for x in d), self.irradiance, self.radius)
