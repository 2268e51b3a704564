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
``base (N, 3)``,          float16      optional: the truth in glTF's terms, base colour and
``metallic (N, 1)``                    metallic
``env_energy (3,)``       float64      optional: the light's radiant energy ``int L dw``
``description ()``        str          what rendered the targets (the result's weights id)
``environment ()``        str          optional: the environment they are lit by
                                       (``target.environment``; suns start at its suns)
========================  ===========  ========================================================

The relit ground truth (``relit.npz``, :func:`save_relit`) holds the metric views rendered under each
of ``target.relight_environments``, numbered ``j``: ``environment_j``, ``radiance_j``, ``coverage_j``,
``env_energy_j`` and ``noise_psnr_db_j``, with ``count`` and the cache's ``offsets``.

Because the values sit at cached hits, a training step composes target images exactly as it
composes the model's (the same pixels, crops, resizing and backgrounds).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.errors import StageInputError
from ..core.safefiles import DATA_LIMIT, atomic_stream, open_read
from ..geometry.raycache import RayCache

#: ground-truth arrays a target file may carry (metric views)
TRUTH_KEYS = ("albedo", "specular", "roughness", "normal")
#: and the truth in glTF's terms (base colour, metallic), for fields of ``optimize.brdf: gltf``
GLTF_TRUTH_KEYS = ("base", "metallic")
#: the prefix of the truth at the metric cache's face sides in ``metrics.npz`` (what a bounce's
#: ceiling sends: :meth:`TargetSet.senders`)
SENDER_PREFIX = "sender_"
#: a hit whose pixel is at least this covered counts as an object pixel of the figures
FULL_COVERAGE = 0.999


def save_targets(path: str | Path, arrays: dict[str, np.ndarray]) -> None:
    """Write a target file atomically (per-hit arrays as float16, the rest as given)."""
    out = {}
    for key, value in arrays.items():
        value = np.asarray(value)
        out[key] = value.astype(np.float16) if key in ("radiance", "coverage", *TRUTH_KEYS, *GLTF_TRUTH_KEYS) else value
    with atomic_stream(path) as fh:
        np.savez(fh, **out)


def save_relit(path: str | Path, relit: dict, offsets: np.ndarray, description: str) -> None:
    """Write the relit ground truth atomically: for each environment ``j`` (in order) its name
    ``environment_j``, per-hit ``radiance_j`` and ``coverage_j`` (float16, as the targets) and
    ``env_energy_j``; ``relit``: environment -> (:class:`~stages.reference.targets.ViewTargets`,
    energy)."""
    out: dict[str, np.ndarray] = {"offsets": offsets, "description": np.array(description), "count": np.array(len(relit))}
    for j, (env, (t, energy)) in enumerate(relit.items()):
        out[f"environment_{j}"] = np.array(env)
        out[f"radiance_{j}"] = np.asarray(t.radiance).astype(np.float16)
        out[f"coverage_{j}"] = np.asarray(t.coverage).astype(np.float16)
        out[f"env_energy_{j}"] = np.asarray(energy, np.float64)
        out[f"noise_psnr_db_{j}"] = np.array(t.noise_psnr_db)
    with atomic_stream(path) as fh:
        np.savez(fh, **out)


@dataclass(frozen=True)
class RelitTruth:
    """One environment's ground truth of the metric views: per hit ``radiance (N, 3)`` and
    ``coverage (N,)`` (float32), the environment's name and the targets' own noise."""

    environment: str
    radiance: np.ndarray
    coverage: np.ndarray
    noise_psnr_db: float


def load_relit(path: str | Path, cache: RayCache) -> list[RelitTruth]:
    """The relit ground truth of ``cache``'s views (:func:`save_relit`), checked against the cache."""
    path = Path(path)
    if not path.exists() and not path.is_symlink():
        raise StageInputError(path, "relit ground truth not found", "Run the target stage first (snakemake runs it).")
    with open_read(path, DATA_LIMIT, remedy="Run the target stage again.") as fh, np.load(fh) as z:
        arrays = {k: z[k] for k in z.files}
    if not np.array_equal(arrays.get("offsets"), cache.arrays["offsets"]):
        raise StageInputError(
            path,
            f"its ground truth was rendered for another ray cache than {cache.path}",
            "Rerun the target stage for this cache (snakemake --forcerun target).",
        )
    return [
        RelitTruth(
            str(arrays[f"environment_{j}"]),
            arrays[f"radiance_{j}"].astype(np.float32),
            arrays[f"coverage_{j}"].astype(np.float32),
            float(arrays[f"noise_psnr_db_{j}"]),
        )
        for j in range(int(arrays["count"]))
    ]


class TargetSet:
    """A target file checked against the ray cache it belongs to."""

    def __init__(self, path: str | Path, cache: RayCache) -> None:
        self.path = Path(path)
        if not self.path.exists() and not self.path.is_symlink():
            raise StageInputError(self.path, "target file not found", "Run the target stage first (snakemake runs it).")
        with open_read(self.path, DATA_LIMIT, remedy="Run the target stage again.") as fh, np.load(fh) as z:
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
    def environment(self) -> str | None:
        """The environment the targets are lit by (``target.environment``: ``builtin:<name>`` or a
        map's path), None for a file written without it."""
        return str(self.arrays["environment"]) if "environment" in self.arrays else None

    def senders(self, keys: tuple[str, ...]) -> dict[str, np.ndarray] | None:
        """The truth at the metric cache's face sides (rows ``2 f`` and ``2 f + 1``), the ``keys``
        and the shading ``normal``, or None where the targets do not carry them (written before
        they did)."""
        wanted = (*keys, "normal")
        if not all(f"{SENDER_PREFIX}{k}" in self.arrays for k in wanted):
            return None
        return {k: self.arrays[f"{SENDER_PREFIX}{k}"].astype(np.float32) for k in wanted}

    @property
    def has_truth(self) -> bool:
        return all(k in self.arrays for k in TRUTH_KEYS)
