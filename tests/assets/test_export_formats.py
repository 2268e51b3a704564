"""An export format is a row and an object: the torch-free table of :mod:`stages.config.layout`
(its files and what the workflow, the lod stage, the round trip and the report know of it) and
its writer and validator in :mod:`stages.assets.formats`, one registry for both; no stage names an
export file but through the table; and a toy format, registered for one block, is written,
validated and recorded by the export stage like the real ones (the first step of adding one)."""

from __future__ import annotations

import ast
import json
import re
from pathlib import Path

import pytest
from conftest import REPO

from stages import export
from stages.assets import formats
from stages.assets.formats import AssetInfo, Exporter, ExportMesh
from stages.config.layout import (
    BLENDER_IMPORTS,
    EXPORT_FILES,
    EXPORT_FORMATS,
    LEVELS_STEM,
    LOD_FILES,
    VIEWER_FILE,
    ExportFormat,
    export_files,
    export_format_of,
)
from stages.config.sections import ROUNDTRIP_FORMATS, ExportSettings
from stages.core.errors import StageInputError

#: where an export file's name may be spelt out: the table and the format's own modules
TABLE = ("stages/config/layout.py", "stages/assets/formats/")


class ToyFormat(Exporter):
    """A text file of the asset's counts (``model.txt``), its validator reporting an error where
    told to."""

    def __init__(self, errors: int = 0) -> None:
        super().__init__(ExportFormat(name="toy", suffixes=("txt",), description="the asset's counts as text"))
        self.errors, self.validated = errors, []

    def write(self, folder: Path, geom: ExportMesh, asset: AssetInfo) -> None:
        (name,) = self.files().values()
        text = f"{asset.name}: {len(geom.positions)} vertices, {len(geom.indices)} faces, {asset.brdf.name} BRDF\n"
        (Path(folder) / name).write_text(text)

    def validate(self, folder: Path, stem: str = "model") -> dict[str, dict]:
        (name,) = self.files(stem).values()
        text = (Path(folder) / name).read_text()
        self.validated.append(name)
        messages = [f"toy: {self.errors} made-up error(s)"] if self.errors else []
        return {name: {"errors": self.errors, "warnings": 0, "messages": messages, "lines": len(text.splitlines())}}


def test_the_table_and_the_writers_are_one_registry():
    """Each row has its object, each object its row; the workflow's files, the lod stage's, the
    round trip's choices and the viewer's file all come from the rows."""
    assert formats.names() == EXPORT_FORMATS.names() == ("gltf", "usd")
    for exporter in formats.exporters():
        assert exporter.spec is EXPORT_FORMATS[exporter.name] and formats.get(exporter.name) is exporter
    assert EXPORT_FILES == export_files() == {"glb": "model.glb", "usda": "model.usda", "usdz": "model.usdz"}
    assert {k: v for k, v in LOD_FILES.items() if k in EXPORT_FILES} == export_files(LEVELS_STEM, levels=True)
    assert ROUNDTRIP_FORMATS == BLENDER_IMPORTS == ("glb", "usdz")
    assert VIEWER_FILE == "model.glb" and export_format_of("usdz").name == "usd"
    with pytest.raises(ValueError, match="no export format writes"):
        export_format_of("fbx")


def _spelt_file_names(path: Path) -> list[int]:
    """Lines of ``path`` whose code (not a docstring or comment) spells an export file's name, or
    ``model.`` before a formatted suffix."""
    names = set(EXPORT_FILES.values()) | set(export_files(LEVELS_STEM).values())
    tree = ast.parse(path.read_text(encoding="utf-8"))
    docstrings = {
        id(node.body[0].value)
        for node in ast.walk(tree)
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef)
        and node.body
        and isinstance(node.body[0], ast.Expr)
        and isinstance(node.body[0].value, ast.Constant)
    }
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and id(node) not in docstrings and node.value in names:
            found.append(node.lineno)
        elif isinstance(node, ast.JoinedStr):
            parts = [v.value for v in node.values if isinstance(v, ast.Constant)]
            if any(str(p).endswith(("model.", "model_lods.")) for p in parts):
                found.append(node.lineno)
    return found


def test_no_stage_names_an_export_file():
    """Outside the table and the formats' modules, the stages and the rules ask the table for an
    export file's name (``EXPORT_FILES["glb"]``, ``export_files()``, ``VIEWER_FILE``); the
    module of the input's own document names the one file it stands in for, through the table."""
    found = []
    for path in sorted((REPO / "stages").rglob("*.py")):
        rel = path.relative_to(REPO).as_posix()
        if not rel.startswith(TABLE):
            found += [f"{rel}:{line}" for line in _spelt_file_names(path)]
    for path in [REPO / "Snakefile", *sorted((REPO / "workflow").rglob("*.smk"))]:
        for k, line in enumerate(path.read_text().splitlines(), start=1):
            if re.search(r"model(_lods)?\.(glb|usda|usdz)", line.split("#")[0]):
                found.append(f"{path.relative_to(REPO).as_posix()}:{k}")
    assert found == []


def test_a_temporary_format_comes_and_goes():
    """:func:`formats.temporarily` adds the object and its row for the block and removes both
    after it, also when the block raises; a taken name or suffix is refused."""
    toy = ToyFormat()
    with pytest.raises(RuntimeError), formats.temporarily(toy):
        assert formats.names()[-1] == "toy" and EXPORT_FORMATS["toy"] is toy.spec
        assert export_files()["txt"] == "model.txt" and export_format_of("txt") is toy.spec
        raise RuntimeError("the block fails")
    assert "toy" not in formats.names() and "toy" not in EXPORT_FORMATS and "txt" not in export_files()
    clash = ToyFormat()
    clash.spec = ExportFormat(name="glb2", suffixes=("glb",), description="a second GLB")
    with pytest.raises(ValueError, match="both write"), formats.temporarily(clash):
        pass
    taken = ToyFormat()
    taken.spec = ExportFormat(name="usd", suffixes=("usdx",), description="a second USD")
    with pytest.raises(ValueError, match="already registered"), formats.temporarily(taken):
        pass
    assert formats.names() == EXPORT_FORMATS.names() == ("gltf", "usd")


def _export(cell: Path, out: Path) -> dict:
    bake = cell / "bake"
    return export.run(cell / "mesh.ply", cell / "transform.json", bake, bake / "preview.png", out, ExportSettings())


def test_a_toy_format_is_written_validated_and_recorded_by_the_export(trained_cell, tmp_path):
    """Registered for the block, a format that writes a text file goes through the export stage's
    writer loop like glTF and USD: its file is written beside theirs, its validator runs on it,
    its report, size and time are in the metadata; the real formats' files are the same bytes as
    without it. A validator error stops the export in one line, with nothing committed."""
    toy = ToyFormat()
    with formats.temporarily(toy):
        stats = _export(trained_cell, tmp_path / "export")
    out = tmp_path / "export"
    assert (out / "model.txt").read_text().startswith(f"model: {stats['vertices_exported']} vertices")
    assert toy.validated == ["model.txt"]
    assert stats["validation"]["model.txt"]["lines"] == 1 and set(stats["validation"]) == {*EXPORT_FILES.values(), "model.txt"}
    assert stats["file_bytes"]["model.txt"] == (out / "model.txt").stat().st_size
    meta = json.loads((out / "meta.json").read_text())
    assert meta["outputs"]["model.txt"].endswith("export/model.txt") and "toy" in meta["timings_s"]
    for name in EXPORT_FILES.values():
        if name != "model.usdz":  # a zip: its entries' times differ
            assert (out / name).read_bytes() == (trained_cell / "export" / name).read_bytes(), name
    failing = ToyFormat(errors=2)
    with formats.temporarily(failing), pytest.raises(StageInputError, match=r"model.txt: failed validation with 2 error\(s\)"):
        _export(trained_cell, tmp_path / "failed")
    assert not (tmp_path / "failed" / "meta.json").exists() and not (tmp_path / "failed" / "model.txt").exists()
