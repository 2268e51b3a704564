"""The export formats, one module each (``gltf.py``, ``usd.py``) with one object of
:class:`~stages.assets.formats.base.Exporter`, found by name: :func:`get`, :func:`exporters`.

The names are the rows of :data:`stages.config.layout.EXPORT_FORMATS` (each format's files and,
as data, what the workflow, the lod stage, the Blender round trip and the report know of it,
without torch); the object is the row's writer and validator. The export stage and each level of
the lod stage write an asset with :func:`write_asset_files`, a loop over the registered formats;
the lod stage's files that hold every level are each such format's :meth:`Exporter.write_levels`.
A new format is one row there and one module here whose object this registry lists
(``tests/assets/test_export_formats.py`` holds the two to each other), so the files of the
registered formats are the table's (:func:`~stages.config.layout.export_files`); :func:`temporarily`
adds one, object and row, for a block (a test's toy format, the first step of adding one)."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager, nullcontext
from pathlib import Path

from ...config.layout import EXPORT_FORMATS, check_format
from ...core.registry import Registry
from .base import AssetInfo, Exporter, check_reports, message_key, one_line, recorded_lights
from .gltf import GLTF
from .mesh import ATLAS_KEYS, ExportMesh, Level, export_mesh, read_atlas
from .usd import USD

#: each format's object by name, in the table's order
_EXPORTERS: Registry[Exporter] = Registry("export format")
for _exporter in (GLTF, USD):
    _EXPORTERS.register(_exporter.name, _exporter)

__all__ = [
    "ATLAS_KEYS",
    "AssetInfo",
    "ExportMesh",
    "Exporter",
    "Level",
    "check_reports",
    "message_key",
    "export_mesh",
    "exporters",
    "get",
    "names",
    "one_line",
    "read_atlas",
    "recorded_lights",
    "temporarily",
    "write_asset_files",
]


def get(name: str) -> Exporter:
    """The object of the export format ``name``; a ValueError naming the formats for any other."""
    return _EXPORTERS[name]


def names() -> tuple[str, ...]:
    """The registered formats' names, in the order the export writes them."""
    return _EXPORTERS.names()


def exporters() -> tuple[Exporter, ...]:
    """The registered formats' objects, in the order the export writes them."""
    return _EXPORTERS.entries()


@contextmanager
def temporarily(exporter: Exporter) -> Iterator[Exporter]:
    """``exporter`` registered for the block, its row in the table
    (:data:`~stages.config.layout.EXPORT_FORMATS`) too, both removed after it: a test's toy
    format, or a new format tried before it has its row. Refused (ValueError) where its name is
    taken or another format writes a file of its suffixes."""
    spec = check_format(exporter.spec, EXPORT_FORMATS.values())
    with EXPORT_FORMATS.temporarily(spec.name, spec), _EXPORTERS.temporarily(exporter.name, exporter):
        yield exporter


def write_asset_files(
    folder: Path,
    geom: ExportMesh,
    asset: AssetInfo,
    timer=None,
    instead: Mapping[str, Callable[[Path], None]] | None = None,
    inherited: dict[str, set[str]] | None = None,
) -> dict[str, dict]:
    """Write one asset in every registered format into ``folder`` (which already holds its
    textures, ``textures/*.png``, and its light), each file atomically, and validate every file
    (``instead``: per format name, a function that writes that format's files into ``folder`` in
    its writer's place, as the export stage writes a glTF input's own document). Returns every
    validator's report by file name. Warnings are logged; any validator error raises
    (:func:`check_reports`; the folder is the caller's staging folder, so nothing half-checked is
    committed), but those the input itself has (``inherited``, per file name) are only said.
    ``timer`` (a :class:`~stages.core.provenance.Timer`) times each format's writing, under its
    name, and the ``validate`` part."""

    def part(key):
        return timer(key) if timer is not None else nullcontext()

    folder = Path(folder)
    for exporter in exporters():
        with part(exporter.name):
            if instead and exporter.name in instead:
                instead[exporter.name](folder)
            else:
                exporter.write(folder, geom, asset)
    with part("validate"):
        reports = {name: r for exporter in exporters() for name, r in exporter.validate(folder).items()}
    check_reports(reports, folder, inherited)
    return reports
