"""pack: zip every grid cell's asset folder into one asset pack with an index.

``asset_pack.zip`` holds ``<mesh>/<prompt>/<variant>/{model.glb, model.usda, model.usdz (the
export formats' files: :data:`stages.config.layout.EXPORT_FILES`), textures/*.png, light.exr,
light.hdr, preview.png, meta.json}``, ``index.csv`` and a short
``README.txt`` that says, per cell, which guidance and weights made it (and, first of all, when
any asset was made with the test-only random CLIP or fitted to image targets). The same index is
written beside the zip as ``asset_index.csv`` (columns: mesh, prompt, variant, guidance, weights,
test_only, image_guided, origin, files, texture_size, faces, the validation counts of the export's
record, :class:`~stages.config.records.ExportRecord`, and the levels of detail).
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import logging
import os
import shutil
import time
import zipfile
from pathlib import Path

from .config.layout import EXPORT_FORMATS, LEVELS_STEM, export_files
from .config.records import ExportRecord
from .core.cli import stage_main
from .core.errors import StageInputError
from .core.provenance import ORIGIN_KEY, atomic_path, read_origin, shareable_meta
from .core.safefiles import DATA_LIMIT, open_read, reached_without_link, read_json
from .results.cells import parse_cells
from .results.spreadsheet import spreadsheet_rows

log = logging.getLogger(__name__)


def pack_readme(rows: list[dict]) -> str:
    """The pack's ``README.txt``: a warning first when any asset is test-only or image-guided,
    then one line per cell with the guidance and weights that made it."""
    test = [r for r in rows if r["test_only"]]
    image = [r for r in rows if r["image_guided"] and not r["test_only"]]
    lines = ["tango-stylize asset pack", ""]
    if test:
        lines += [
            f"WARNING: TEST ONLY. {len(test)} of {len(rows)} assets were made with a tiny CLIP with random",
            "weights (a test model): they are not real stylisations of their prompts.",
            "",
        ]
    if image:
        lines += [
            f"NOTE: {len(image)} of {len(rows)} assets are IMAGE-GUIDED: fitted to renders of procedural",
            "target materials (a verification run without CLIP), not stylised from their prompts.",
            "",
        ]
    files, suffixes = export_files(), ",".join(export_files())
    lines += [
        f"Each folder <mesh>/<prompt>/<variant>/ holds {', '.join(files.values())}, textures/,",
        "light.exr/.hdr (the learned environment light), preview.png and meta.json (full provenance).",
        *(f"  {', '.join(f.files().values())}: {f.description}" for f in EXPORT_FORMATS.values()),
        f"Where levels of detail were made, lod/ holds lodK/model.{{{suffixes}}} per level and",
        f"{', '.join(export_files(LEVELS_STEM, levels=True).values())} with all of them.",
        "The origin is also inside each model: glTF asset.extras.tango_stylize, USD customLayerData.",
        "",
        "Assets and what made them:",
    ]
    lines += [f"- {r['mesh']}/{r['prompt']}/{r['variant']}: {r[ORIGIN_KEY]}" for r in rows]
    return "\n".join(lines) + "\n"


def linked_folder(folder: Path, results: Path) -> None:
    """Refuse a cell folder reached through a symbolic link: the pack copies only what lies in
    the results folder itself."""
    if folder.exists() and not reached_without_link(folder, results):
        raise StageInputError(
            folder,
            f"is reached through a symbolic link (to {folder.resolve()})",
            "The pack copies only files inside the results folder: copy the cell's files there.",
        )


def regular_files(folder: Path) -> list[Path]:
    """The files under ``folder`` a pack may hold: regular files, not hidden, reached without
    following a symbolic link (a link in a results folder could point anywhere on the machine;
    each one skipped is logged)."""
    found = []
    for root, dirs, names in os.walk(folder, followlinks=False):
        base = Path(root)
        for name in [d for d in dirs if (base / d).is_symlink()]:
            log.warning("not packing %s: a symbolic link", base / name)
            dirs.remove(name)
        for name in names:
            path = base / name
            if path.is_symlink():
                log.warning("not packing %s: a symbolic link", path)
            elif not name.startswith(".") and path.is_file():
                found.append(path)
    return sorted(found)


def run(
    results: Path, cells: list[tuple[str, str, str]], out_zip: Path, out_index: Path, lod_cells: list[tuple[str, str, str]] = ()
) -> list[dict]:
    """Pack the export folder of every cell (and the ``lod`` folder of each of ``lod_cells``)."""
    rows = []
    entries = []
    for mesh, prompt, variant in cells:
        asset = Path(results) / mesh / prompt / variant / "export"
        linked_folder(asset, Path(results))
        meta_path = asset / "meta.json"
        if not meta_path.is_file():
            raise StageInputError(meta_path, "file not found", "Run the export stage first.")
        meta = read_json(meta_path)
        origin = read_origin(meta_path)
        files = regular_files(asset)
        rel = [str(p.relative_to(asset)) for p in files]
        entries += [(p, f"{mesh}/{prompt}/{variant}/{r}") for p, r in zip(files, rel, strict=True)]
        levels = ""
        if (mesh, prompt, variant) in set(lod_cells):
            lod = asset.parent / "lod"
            linked_folder(lod, Path(results))
            lod_meta = lod / "meta.json"
            if not lod_meta.is_file():
                raise StageInputError(lod_meta, "file not found", "Run the lod stage first.")
            rows_lod = read_json(lod_meta)["stats"]["levels"]
            # the stage's own files and the folders of the levels it lists (nothing left by older runs)
            folders = {r["level"] for r in rows_lod}
            lod_files = [p for p in regular_files(lod) if p.parent == lod or p.relative_to(lod).parts[0] in folders]
            lod_rel = [f"lod/{p.relative_to(lod)}" for p in lod_files]
            entries += [(p, f"{mesh}/{prompt}/{variant}/{r}") for p, r in zip(lod_files, lod_rel, strict=True)]
            rel += lod_rel
            levels = ";".join(f"{r['level']}:{r['faces']}" for r in rows_lod)
        rows.append(
            {
                "mesh": mesh,
                "prompt": prompt,
                "variant": variant,
                "guidance": origin["guidance"],
                "weights": origin["weights"],
                "test_only": origin["test_only"],
                "image_guided": origin["image_guided"],
                ORIGIN_KEY: origin["label"],
                "files": ";".join(rel),
                "texture_size": meta["stats"]["texture_size"],
                "faces": meta["stats"]["faces"],
                # the export's record: each format's validation counts (config/records.py)
                **{f.name: meta["stats"][f.name] for f in dataclasses.fields(ExportRecord)},
                "lod_levels": levels,
            }
        )
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]) if rows else ["mesh"])
    writer.writeheader()
    writer.writerows(spreadsheet_rows(rows))  # prompt text a spreadsheet would evaluate is quoted
    with atomic_path(out_zip) as tmp:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED) as z:
            z.writestr("README.txt", pack_readme(rows))
            z.writestr("index.csv", buf.getvalue())
            for path, arc in entries:
                if path.name == "meta.json":  # provenance without the host and the command line
                    z.writestr(arc, json.dumps(shareable_meta(read_json(path)), indent=2))
                else:  # streamed from the handle the gate opened (a file swapped for a link is not followed)
                    with open_read(path, DATA_LIMIT) as src:
                        stamp = time.localtime(os.fstat(src.fileno()).st_mtime)[:6]
                        with z.open(
                            zipfile.ZipInfo(arc, date_time=max(stamp, (1980, 1, 1, 0, 0, 0))), "w", force_zip64=True
                        ) as dst:
                            shutil.copyfileobj(src, dst)
    with atomic_path(out_index) as tmp:
        tmp.write_text(buf.getvalue())
    log.info("packed %d cells (%d files) into %s", len(rows), len(entries), out_zip)
    return rows


def main(argv: list[str] | None = None) -> int:
    def arguments(parser):
        parser.add_argument("--results", type=Path, default=Path("results"))
        parser.add_argument("--zip", required=True, type=Path, help="the asset pack to write (.zip)")
        parser.add_argument("--index", required=True, type=Path, help="the pack's index to write (JSON)")
        parser.add_argument("--cells", nargs="+", required=True)
        parser.add_argument("--lod-cells", nargs="*", default=[], help="cells whose lod folder is packed too")

    def body(args):
        run(args.results, parse_cells(args.cells), args.zip, args.index, parse_cells(args.lod_cells))

    return stage_main("pack", __doc__, arguments, body, argv)


if __name__ == "__main__":
    raise SystemExit(main())
