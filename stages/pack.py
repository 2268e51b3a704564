"""pack: zip every grid cell's asset folder into one asset pack with an index.

``asset_pack.zip`` holds ``<mesh>/<prompt>/<variant>/{model.usdz, model.usda, model.glb,
textures/*.png, light.exr, light.hdr, preview.png, meta.json}`` and ``index.csv``; the same index
is written beside it as ``asset_index.csv`` (columns: mesh, prompt, variant, files, texture_size,
faces).
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import logging
import zipfile
from pathlib import Path

from .errors import StageInputError, stage_errors
from .provenance import atomic_path, setup_logging
from .report import parse_cells

log = logging.getLogger(__name__)


def run(results: Path, cells: list[tuple[str, str, str]], out_zip: Path, out_index: Path) -> list[dict]:
    rows = []
    entries = []
    for mesh, prompt, variant in cells:
        asset = Path(results) / mesh / prompt / variant / "asset"
        meta_path = asset / "meta.json"
        if not meta_path.is_file():
            raise StageInputError(meta_path, "file not found", "Run the export stage first.")
        meta = json.loads(meta_path.read_text())
        files = sorted(p for p in asset.rglob("*") if p.is_file() and not p.name.startswith("."))
        rel = [str(p.relative_to(asset)) for p in files]
        entries += [(p, f"{mesh}/{prompt}/{variant}/{r}") for p, r in zip(files, rel, strict=True)]
        rows.append(
            {
                "mesh": mesh,
                "prompt": prompt,
                "variant": variant,
                "files": ";".join(rel),
                "texture_size": meta["stats"]["texture_size"],
                "faces": meta["stats"]["faces"],
            }
        )
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]) if rows else ["mesh"])
    writer.writeheader()
    writer.writerows(rows)
    with atomic_path(out_zip) as tmp:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED) as z:
            z.writestr("index.csv", buf.getvalue())
            for path, arc in entries:
                z.write(path, arc)
    with atomic_path(out_index) as tmp:
        tmp.write_text(buf.getvalue())
    log.info("packed %d cells (%d files) into %s", len(rows), len(entries), out_zip)
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m stages.pack", description=__doc__.split("\n")[0])
    parser.add_argument("--results", type=Path, default=Path("results"))
    parser.add_argument("--zip", required=True, type=Path)
    parser.add_argument("--index", required=True, type=Path)
    parser.add_argument("--cells", nargs="+", required=True)
    args = parser.parse_args(argv)
    setup_logging()
    with stage_errors("pack") as status:
        run(args.results, parse_cells(args.cells), args.zip, args.index)
    return status.code


if __name__ == "__main__":
    raise SystemExit(main())
