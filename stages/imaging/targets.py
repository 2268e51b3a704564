"""Image targets stored per cached hit, aligned with a ray cache (written by the target stage).

A target file holds, for every hit of one ray-cache file (same order, same per-view offsets):

========================  ===========  ========================================================
array                     dtype        meaning
========================  ===========  ========================================================
``radiance (N, 3)``       float16      linear radiance of the hit's pixel, unpremultiplied
``coverage (N,)``         float16      the pixel's covered fraction (Mitsuba's alpha)
``offsets (V+1,)``        int64        the cache's offsets (checked on reading)
``albedo, specular``      float16      optional ground truth (metric views): TANGO-equivalent
``(N, 3)``, ``roughness``              diffuse albedo, specular colour, roughness and the world
``(N, 1)``, ``normal``                 shading normal (facing the viewer)
``env_energy (3,)``       float64      optional: the light's radiant energy ``int L dw``
``description ()``        str          what rendered the targets (the result's weights id)
========================  ===========  ========================================================

Because the values sit at cached hits, a training step composes target images exactly as it
composes the model's (the same pixels, crops, resizing and backgrounds).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..core.errors import StageInputError
from ..core.provenance import atomic_path
from ..geometry.raycache import RayCache

#: ground-truth arrays a target file may carry (metric views)
TRUTH_KEYS = ("albedo", "specular", "roughness", "normal")
#: a hit whose pixel is at least this covered counts as an object pixel of the figures
FULL_COVERAGE = 0.999


def save_targets(path: str | Path, arrays: dict[str, np.ndarray]) -> None:
    """Write a target file atomically (per-hit arrays as float16, the rest as given)."""
    out = {}
    for key, value in arrays.items():
        value = np.asarray(value)
        out[key] = value.astype(np.float16) if key in ("radiance", "coverage", *TRUTH_KEYS) else value
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **out)


class TargetSet:
    """A target file checked against the ray cache it belongs to."""

    def __init__(self, path: str | Path, cache: RayCache) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise StageInputError(self.path, "target file not found", "Run the target stage first (snakemake runs it).")
        with np.load(self.path) as z:
            self.arrays = {k: z[k] for k in z.files}
        offsets = cache.arrays["offsets"]
        if not np.array_equal(self.arrays.get("offsets"), offsets):
            raise StageInputError(
                self.path,
                f"its targets were rendered for another ray cache than {cache.path}",
                "Rerun the target stage for this cache (snakemake --forcerun target).",
            )
        self.offsets = offsets

    def __len__(self) -> int:
        return len(self.offsets) - 1

    def view(self, i: int, key: str = "radiance") -> np.ndarray:
        """``key`` at the hits of view ``i`` as float32."""
        lo, hi = self.offsets[i], self.offsets[i + 1]
        return self.arrays[key][lo:hi].astype(np.float32)

    @property
    def description(self) -> str:
        return str(self.arrays.get("description", f"targets of {self.path}"))

    @property
    def has_truth(self) -> bool:
        return all(k in self.arrays for k in TRUTH_KEYS)
