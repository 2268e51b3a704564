"""The dependency floors close the holes of older releases that would read a file from elsewhere
as code or follow it out of its folder (the security page of the documentation), and what is
installed here meets them."""

from __future__ import annotations

import re
import tomllib
from importlib import metadata
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
#: package: (the lowest release without the hole, the hole)
SAFE = {
    "torch": ((2, 6), "torch.load unpickles without restriction by default"),
    "open_clip_torch": ((2, 27), "a clip_checkpoint is unpickled without restriction"),
    "trimesh": ((5, 0), "glTF buffer URIs are followed outside the mesh's folder"),
}


def floors() -> dict[str, tuple[int, ...]]:
    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    found = {}
    for dep in deps:
        m = re.fullmatch(r"([A-Za-z0-9_.-]+)\s*>=\s*([0-9.]+)(?:,.*)?", dep)
        if m:
            found[m[1]] = tuple(int(x) for x in m[2].split("."))
    return found


@pytest.mark.parametrize("package", sorted(SAFE))
def test_floor_is_a_release_without_the_hole(package):
    safe, hole = SAFE[package]
    floor = floors().get(package)
    assert floor is not None, f"{package} has no >= floor in pyproject.toml"
    assert floor >= safe, f"{package}>={'.'.join(map(str, floor))} admits releases where {hole}"


@pytest.mark.parametrize("package", sorted(SAFE))
def test_installed_release_meets_the_floor(package):
    installed = tuple(int(x) for x in re.findall(r"\d+", metadata.version(package))[:2])
    assert installed >= floors()[package][:2], (package, metadata.version(package))
