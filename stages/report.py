"""report: one summary table and one overview image over every grid cell.

``summary.csv`` (pandas): one row per mesh x prompt x variant with the guidance and the weights
that made it (real CLIP weights, "test-only random" for the tiny test CLIP, or the image
targets), iterations, final similarity (CLIP) or held-out PSNR (image targets), faces before and
after decimation, bake fidelity, texture size, and the wall time of every stage.
``overview.png``: rows are cells, columns RGB, diffuse, roughness, specular and predicted normals
from the evaluation view nearest the front, each row labelled.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

from .errors import StageInputError, stage_errors
from .provenance import atomic_path, setup_logging, write_json_atomic

log = logging.getLogger(__name__)

OVERVIEW_KINDS = ("rgb", "diffuse", "roughness", "specular", "normal")
MESH_STAGES = ("normalize", "decimate", "raycache")
CELL_STAGES = ("optimize", "bake", "export", "relight")


def _read(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.is_file() else None


def _need(path: Path) -> dict:
    data = _read(path)
    if data is None:
        raise StageInputError(path, "file not found", "Run the stage that writes it first.")
    return data


def weights_label(meta: dict) -> str:
    if meta.get("test_only_weights"):
        return "test-only random"
    if meta.get("guidance") == "image":
        return f"image-guided ({meta['settings']['target_material']} target)"
    return str(meta.get("weights"))


def summary_rows(results: Path, cells: list[tuple[str, str, str]]) -> list[dict]:
    rows = []
    for mesh, prompt, variant in cells:
        mdir = results / mesh
        cdir = mdir / prompt / variant
        opt = _need(cdir / "optimize" / "meta.json")
        bake = _read(cdir / "bake" / "meta.json") or {}
        export = _read(cdir / "asset" / "meta.json") or {}
        norm = _need(mdir / "normalize" / "meta.json")
        dec = _read(mdir / "decimate" / "meta.json")
        row = {
            "mesh": mesh,
            "prompt": prompt,
            "variant": variant,
            "prompt_text": opt.get("prompt"),
            "guidance": "image-guided (procedural targets)" if opt.get("guidance") == "image" else "CLIP",
            "weights": weights_label(opt),
            "test_only_weights": bool(opt.get("test_only_weights")),
            "iterations": opt["settings"]["iterations"],
            "final_similarity": opt.get("final_similarity"),
            "eval_psnr_db": opt.get("eval_psnr_db"),
            "faces_before": norm["stats"]["faces"],
            "faces_after": dec["stats"]["faces_after"] if dec else norm["stats"]["faces"],
            "decimated": dec is not None,
            "bake_psnr_db": bake.get("stats", {}).get("bake_psnr_db"),
            "texture_size": bake.get("stats", {}).get("texture_size"),
            "usd_validation_errors": export.get("stats", {}).get("usd_validation_errors"),
        }
        for stage in MESH_STAGES:
            meta = _read(mdir / stage / "meta.json")
            row[f"seconds_{stage}"] = meta["timings_s"]["total"] if meta else None
        for stage, folder in zip(CELL_STAGES, ("optimize", "bake", "asset", "relight"), strict=True):
            meta = _read(cdir / folder / "meta.json")
            row[f"seconds_{stage}"] = meta["timings_s"]["total"] if meta else None
        rows.append(row)
    return rows


def overview_image(results: Path, cells: list[tuple[str, str, str]], tile: int = 160) -> np.ndarray:
    """Rows = cells, columns = :data:`OVERVIEW_KINDS`, with a label strip on the left."""
    from PIL import Image, ImageDraw

    label_w = 220
    header = 24
    canvas = Image.new("RGB", (label_w + tile * len(OVERVIEW_KINDS), header + tile * len(cells)), "white")
    draw = ImageDraw.Draw(canvas)
    for j, kind in enumerate(OVERVIEW_KINDS):
        draw.text((label_w + j * tile + 4, 6), kind, fill="black")
    for i, (mesh, prompt, variant) in enumerate(cells):
        opt = _need(results / mesh / prompt / variant / "optimize" / "meta.json")
        sheet = opt["sheet"]
        cols, t, k = sheet["columns"], sheet["tile"], sheet["front_view"]
        r, c = divmod(k, cols)
        y = header + i * tile
        label = f"{mesh} / {prompt} / {variant}\n{weights_label(opt)[:34]}"
        draw.text((4, y + 6), label, fill="black")
        for j, kind in enumerate(OVERVIEW_KINDS):
            img = Image.open(results / mesh / prompt / variant / "optimize" / "renders" / f"{kind}.png")
            crop = img.crop((c * t, r * t, (c + 1) * t, (r + 1) * t)).resize((tile, tile))
            canvas.paste(crop, (label_w + j * tile, y))
    return np.asarray(canvas)


def run(results: Path, cells: list[tuple[str, str, str]], out_dir: Path) -> list[dict]:
    import pandas as pd
    from PIL import Image

    rows = summary_rows(Path(results), cells)
    frame = pd.DataFrame(rows)
    out_dir = Path(out_dir)
    with atomic_path(out_dir / "summary.csv") as tmp:
        frame.to_csv(tmp, index=False)
    with atomic_path(out_dir / "overview.png") as tmp:
        Image.fromarray(overview_image(Path(results), cells)).save(tmp, format="PNG")
    write_json_atomic(out_dir / "summary.json", rows)
    log.info("summary of %d cells written to %s", len(rows), out_dir)
    return rows


def parse_cells(items: list[str]) -> list[tuple[str, str, str]]:
    cells = []
    for item in items:
        parts = item.split("/")
        if len(parts) != 3:
            raise StageInputError(None, f"cell {item!r} is not mesh/prompt/variant")
        cells.append(tuple(parts))
    return cells


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m stages.report", description=__doc__.split("\n")[0])
    parser.add_argument("--results", type=Path, default=Path("results"))
    parser.add_argument("--out-dir", type=Path, default=Path("results/report"))
    parser.add_argument("--cells", nargs="+", required=True, help="mesh/prompt/variant ...")
    parser.add_argument("-v", "--verbose", action="store_true")
    args = parser.parse_args(argv)
    setup_logging(args.verbose)
    with stage_errors("report") as status:
        run(args.results, parse_cells(args.cells), args.out_dir)
    return status.code


if __name__ == "__main__":
    raise SystemExit(main())
