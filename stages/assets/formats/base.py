"""What an export format is to the rest of the library: :class:`Exporter`, the base of each
format's object (its row of the table, :class:`~stages.config.layout.ExportFormat`, its writer, its
validator and its summary figures), :class:`AssetInfo` (what every format writes of an asset
beside its geometry), and the check of the validators' reports that stops an export."""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ...config.brdfs import BrdfSpec
from ...config.layout import ExportFormat
from ...config.sections import ExportSettings
from ...core.errors import StageInputError
from ...render.distant import DistantLight
from .mesh import ExportMesh, Level

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class AssetInfo:
    """What every format writes of one asset beside its geometry and textures: the files' unit
    (``meters_per_unit``), the asset's ``name`` (glTF's mesh and node), the ``origin`` record
    (the guidance and weights that made it), the ``brdf`` whose textures the bake wrote (its row:
    the textures, USD's workflow, glTF's extensions), whether the bake wrote an ``occlusion``
    map, the export's ``settings`` (a format's own settings are fields there: ``usdz_root``) and
    the learned light: its environment image beside the asset (``light``) and its suns as distant
    ``lights`` (directions in the asset file's frame)."""

    meters_per_unit: float
    name: str
    origin: dict
    brdf: BrdfSpec
    occlusion: bool = False
    settings: ExportSettings = field(default_factory=ExportSettings)
    light: str = "light.exr"
    lights: tuple[DistantLight, ...] = ()


def recorded_lights(bake_stats: dict, rotation: np.ndarray | None = None) -> tuple[DistantLight, ...]:
    """The learned suns the bake recorded (its ``meta.json`` ``stats.distant_lights``), their
    directions turned by ``rotation (3, 3)`` into the asset file's frame (None: the normalised
    frame's directions, which the export space shares)."""
    lights = tuple(DistantLight.from_record(r) for r in bake_stats.get("distant_lights", []))
    return lights if rotation is None else tuple(light.turned(rotation) for light in lights)


def facing_rotation(direction) -> tuple[float, float, float, float]:
    """The unit quaternion ``(x, y, z, w)`` of the shortest turn taking ``+z`` to the unit
    ``direction`` a distant light comes from: a glTF directional light and a USD ``DistantLight``
    shine along their node's ``-z``, so turned by it they shine along ``-direction``
    (``q = normalise(z x d, 1 + z . d)``; a half turn about ``x`` for ``d = -z``)."""
    d = np.asarray(direction, np.float64)
    d = d / np.linalg.norm(d)
    if d[2] < -1.0 + 1e-12:
        return (1.0, 0.0, 0.0, 0.0)
    q = np.array([-d[1], d[0], 0.0, 1.0 + d[2]])
    q /= np.linalg.norm(q)
    return tuple(float(x) for x in q)


class Exporter(ABC):
    """An export format: its row of the table (``spec``: name, files, what the lod stage, the round
    trip and the report know of it), how it writes an asset's files into a folder and how its
    validator judges them. One object per format, registered by name in
    :mod:`stages.assets.formats`."""

    def __init__(self, spec: ExportFormat) -> None:
        self.spec = spec

    @property
    def name(self) -> str:
        """Its name (its row's, the registry's key)."""
        return self.spec.name

    def files(self, stem: str = "model") -> dict[str, str]:
        """Its files' names by suffix (``{"usda": "model.usda", "usdz": "model.usdz"}``)."""
        return self.spec.files(stem)

    def __repr__(self) -> str:
        return f"<export format {self.name}: {', '.join(self.files().values())}>"

    @abstractmethod
    def write(self, folder: Path, geom: ExportMesh, asset: AssetInfo) -> None:
        """Write its files (:meth:`files`) of the asset ``geom`` into ``folder``, which already
        holds the asset's textures (``textures/``, :meth:`ExportMesh.texture_files`) and its light
        (``asset.light``), each file atomically."""

    @abstractmethod
    def validate(self, folder: Path, stem: str = "model") -> dict[str, dict]:
        """Its validator's report on each of its files in ``folder``, by file name: at least
        ``errors`` and ``warnings`` (counts) and ``messages`` (one line each), or ``{"ran": False,
        "reason": ...}`` where the validator is not installed (:func:`check_reports` reads them)."""

    def write_levels(self, folder: Path, levels: list[Level], asset: AssetInfo, coverage: list[float]) -> None:
        """Every level of detail (finest first, each level's textures in the folder
        ``level.textures`` below ``folder``) in one file of each suffix (``model_lods.<suffix>``:
        :data:`~stages.config.layout.LEVELS_STEM`),
        switching at the screen ``coverage`` per level; for the formats whose row says
        ``levels_in_one_file``."""
        raise NotImplementedError(f"export format {self.name!r} does not hold levels of detail in one file")

    def record(self, reports: dict[str, dict]) -> dict[str, Any]:
        """Its figures of the export's summary record (:class:`~stages.config.records.ExportRecord`'s
        fields) from the validators' ``reports`` (by file name); none by default."""
        return {}


def message_key(message: str) -> str:
    """What a validator message is about, without its particulars: its code and where it points
    (``CODE at /pointer``), so that the same fault of an input and of its asset compare equal."""
    return str(message).split(": ", 1)[0]


def check_reports(reports: dict[str, dict], where: Path, inherited: dict[str, set[str]] | None = None) -> None:
    """Log every validator message of ``reports`` (file name -> its format's report,
    :meth:`Exporter.validate`), one line each, and a warning for each validator that did not run
    (its report's ``validator``, or the file's). ``inherited``: per file name, the faults
    (:func:`message_key`) of the input it hands on (a glTF input's own document): its errors that
    are those are the input's, counted in the report's ``inherited_errors``, not its ``errors``,
    and said in one warning.

    Raises:
        StageInputError: any report has an error of its own (one line: the file, the count, the first message).
    """
    lines = [f"{where.name}/{name}: {one_line(m)}" for name, r in reports.items() for m in r.get("messages", [])]
    for line in lines:
        log.warning("validation: %s", line)
    for name, keys in (inherited or {}).items():
        r = reports.get(name, {})
        errors = r.get("messages", [])[: r.get("errors", 0)]  # errors come first
        theirs = [m for m in errors if message_key(m) in keys]
        if theirs:
            # a list cut short after the validator's first messages, each the input's: the rest are too
            count = r["errors"] if r.get("truncated") and len(theirs) == len(errors) else len(theirs)
            r["inherited_errors"], r["errors"] = count, r["errors"] - count
            r["messages"] = [m for m in r["messages"] if m not in theirs]
            log.warning(
                "%s: %d validator error(s) the input itself has (the first: %s), handed on as they are",
                name,
                len(theirs),
                one_line(theirs[0], 200),
            )
    for name, r in reports.items():
        if r.get("ran") is False:
            log.warning("%s did not run: %s; %s is unchecked", r.get("validator", f"the validator of {name}"), r["reason"], name)
    failed = [(name, r) for name, r in reports.items() if r.get("errors")]
    if failed:
        name, r = failed[0]
        first = f", the first: {one_line(r['messages'][0]).rstrip('.')}" if r.get("messages") else ""
        raise StageInputError(
            Path(where) / name,
            f"failed validation with {r['errors']} error(s){first}",
            f"Every message is in the log above ({sum(x['errors'] for _, x in failed)} error(s) in all).",
        )


def one_line(text, limit: int = 300) -> str:
    """``text`` on one line (line breaks and other control characters as spaces), at most ``limit``
    characters: a validator's message quotes the file it read, whatever that holds."""
    flat = " ".join("".join(" " if ord(c) < 32 or 127 <= ord(c) < 160 else c for c in str(text)).split())
    return flat if len(flat) <= limit else flat[: limit - 3] + "..."
