"""The meshes that travel with the project (meshes/*.obj.xz): unpacked where a config names them,
checked against SHA256SUMS, a damaged archive one line with nothing left behind; and every shipped
config names only meshes a user has."""

from __future__ import annotations

import hashlib
import lzma
import re
import shutil
from pathlib import Path

import pytest
import yaml
from conftest import REPO

from stages.core import shipped
from stages.core.errors import StageInputError
from stages.geometry.meshio import load_mesh

MESHES = REPO / "meshes"


def copy_of_meshes(tmp_path: Path, names: tuple[str, ...] | None = None) -> Path:
    folder = tmp_path / "meshes"
    folder.mkdir()
    for f in MESHES.iterdir():
        if f.name.endswith(".xz") and (names is None or f.name.removesuffix(".obj.xz") in names) or f.name == "SHA256SUMS":
            shutil.copy(f, folder / f.name)
    return folder


def sources_table() -> dict[str, int]:
    """``{file: faces}`` as meshes/SOURCES.md states them."""
    rows = re.findall(r"^\| (\w+\.obj) \| ([\d,]+) \|", (MESHES / "SOURCES.md").read_text(), flags=re.M)
    return {name: int(faces.replace(",", "")) for name, faces in rows}


def test_every_archive_unpacks_to_its_listed_checksum_and_its_stated_faces(tmp_path):
    folder = copy_of_meshes(tmp_path)
    listed = shipped.listed_sums(folder)
    table = sources_table()
    assert sorted(listed) == sorted(table) == sorted(p.name.removesuffix(".xz") for p in MESHES.glob("*.obj.xz"))
    for name, digest in listed.items():
        mesh = load_mesh(folder / name)  # unpacks it first
        assert hashlib.sha256((folder / name).read_bytes()).hexdigest() == digest
        assert len(mesh.faces) == table[name], name
    assert (MESHES / "LICENSE-text2mesh.txt").read_text().count("MIT License") == 1


def test_unpacked_once_and_only_what_is_listed(tmp_path):
    folder = copy_of_meshes(tmp_path, ("vase",))
    target = folder / "vase.obj"
    assert shipped.shipped_archive(target) == folder / "vase.obj.xz"
    assert shipped.ensure_unpacked(target) and target.is_file()
    assert not shipped.ensure_unpacked(target)  # there now: left as it is
    shutil.copy(folder / "vase.obj.xz", folder / "other.obj.xz")  # an archive SHA256SUMS does not list
    assert shipped.shipped_archive(folder / "other.obj") is None
    assert not shipped.ensure_unpacked(folder / "other.obj") and not (folder / "other.obj").exists()
    with pytest.raises(StageInputError, match="file not found"):
        load_mesh(folder / "other.obj")


@pytest.mark.parametrize("damage", ["truncated", "other content", "not xz"])
def test_a_damaged_archive_stops_with_one_line_and_leaves_nothing(tmp_path, damage):
    folder = copy_of_meshes(tmp_path, ("vase",))
    archive = folder / "vase.obj.xz"
    data = archive.read_bytes()
    if damage == "truncated":
        archive.write_bytes(data[: len(data) // 2])
    elif damage == "other content":
        archive.write_bytes(lzma.compress(lzma.decompress(data) + b"v 0 0 0\n"))
    else:
        archive.write_bytes(b"not an archive" * 100)
    with pytest.raises(StageInputError) as err:
        load_mesh(folder / "vase.obj")
    message = str(err.value)
    assert str(archive) in message and "git checkout -- " in message and "\n" not in message
    assert sorted(p.name for p in folder.iterdir()) == ["SHA256SUMS", "vase.obj.xz"]  # no file, no temporary


def test_an_archive_past_the_size_bound_stops(tmp_path, monkeypatch):
    folder = copy_of_meshes(tmp_path, ("vase",))
    monkeypatch.setattr(shipped, "MAX_BYTES", 1_000_000)
    with pytest.raises(StageInputError, match="unpacks to more than"):
        shipped.ensure_unpacked(folder / "vase.obj")
    assert not (folder / "vase.obj").exists()


def config_meshes() -> list[tuple[str, str, dict]]:
    out = []
    for config in sorted((REPO / "config").rglob("*.yaml")):
        data = yaml.safe_load(config.read_text()) or {}
        for mesh_id, entry in (data.get("meshes") or {}).items():
            out.append((config.relative_to(REPO).as_posix(), mesh_id, entry or {}))
    return out


def test_every_shipped_config_names_only_meshes_a_user_has():
    """Built-in meshes, meshes that travel with the project, or files in the repository; and no
    config, comments included, points into a developer checkout's ../shared."""
    entries = config_meshes()
    assert len(entries) > 20
    for config, mesh_id, entry in entries:
        if "builtin" in entry:
            continue
        path = entry.get("path")
        assert path and not Path(path).is_absolute(), (config, mesh_id, entry)
        assert shipped.shipped_archive(REPO / path) is not None or (REPO / path).is_file(), (
            f"{config}: mesh {mesh_id!r} names {path}, which a user's clone does not have"
        )
    for config in (REPO / "config").rglob("*"):
        if config.suffix in (".yaml", ".md"):
            assert "../shared" not in config.read_text(), f"{config} names a developer checkout's folder"


def test_the_workflow_takes_the_archive_as_the_mesh_input():
    """Snakemake's input for a shipped mesh is its archive, before and after the first unpacking
    (so that unpacking does not make the normalisation look out of date)."""
    from stages.config.workflow import load_config_files

    cfg = load_config_files([REPO / "config" / "robustness.yaml"])
    assert cfg.mesh_file("lamp") == "meshes/lamp.obj.xz" and cfg.mesh_source("lamp") == "meshes/lamp.obj"
