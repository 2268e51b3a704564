"""Build the Blender add-on's zip, which Blender's installer takes (Edit > Preferences > Get
Extensions > Install from Disk; Blender 4.2 or later):

    python scripts/build_blender_addon.py [dist]

writes ``dist/tango_stylize-<version>.zip`` (the version of ``blender/tango_stylize/blender_manifest.toml``,
which must be the project's) and prints its path."""

from __future__ import annotations

import sys
import tomllib
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ADDON = ROOT / "blender" / "tango_stylize"


def build(out_dir: Path) -> Path:
    """The zip in ``out_dir``: the add-on's folder (its manifest and modules, no caches)."""
    manifest = tomllib.loads((ADDON / "blender_manifest.toml").read_text(encoding="utf-8"))
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]["version"]
    if manifest["version"] != project:
        raise SystemExit(f"the add-on's manifest says version {manifest['version']}, the project {project}: make them one")
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"{manifest['id']}-{manifest['version']}.zip"
    tmp = path.with_name(path.name + ".part")
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as z:
        for file in sorted(ADDON.rglob("*")):
            if file.is_file() and "__pycache__" not in file.parts:
                z.write(file, Path(ADDON.name) / file.relative_to(ADDON))
    tmp.replace(path)
    return path


if __name__ == "__main__":
    print(build(Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT / "dist"))
