"""Reading a results tree: per-cell summary rows, origin checks, each cell's quality figure and
time (what the comparisons of :mod:`stages.results.compare` group), the overview image and the
front view of a cell."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..config.records import CELL_RECORDS, MESH_RECORDS, Column, OptimizeRecord, StageRecord, column
from ..core.errors import StageInputError
from ..core.provenance import ORIGIN_KEY, read_origin
from ..core.safefiles import IMAGE_LIMIT, open_read, read_json, require_plain_file
from .spreadsheet import read_csv

log = logging.getLogger(__name__)

OVERVIEW_KINDS = ("rgb", "diffuse", "roughness", "specular", "normal")


def _read(path: Path) -> dict | None:
    """A stage's JSON record, or None where there is none; a link or a FIFO in its place is one
    line (a received results folder is data)."""
    if not path.exists() and not path.is_symlink():
        return None
    return read_json(path, "Rerun the stage that writes it.")


def _need(path: Path) -> dict:
    data = _read(path)
    if data is None:
        raise StageInputError(path, "file not found", "Run the stage that writes it first.")
    return data


#: a cell's per-stage outputs that repeat the optimisation's origin (folder, file)
ORIGIN_FILES = (
    ("optimize", "meta.json"),
    ("bake", "meta.json"),
    ("export", "meta.json"),
    ("relight", "meta.json"),
    ("metrics", "meta.json"),
    ("metrics", "metrics.json"),
    ("roundtrip", "meta.json"),
    ("lod", "meta.json"),
)


def check_origins(cell_dir: Path, skip: tuple[str, ...] = ()) -> dict:
    """The cell's origin (from its optimisation), after checking that every downstream output that
    exists repeats it (except the folders in ``skip``, outputs of stages the run does not use): a
    mismatch means outputs of different runs were mixed."""
    origin = read_origin(cell_dir / "optimize" / "meta.json")
    for folder, name in ORIGIN_FILES[1:]:
        if folder in skip:
            continue
        path = cell_dir / folder / name
        if path.is_file() and read_origin(path) != origin:
            raise StageInputError(
                path,
                f"says it was made by {read_origin(path)['label']!r} but the cell's optimisation says {origin['label']!r}",
                "Outputs of different runs are mixed: rerun the cell (snakemake --forcerun optimize).",
            )
    return origin


def summary_rows(
    results: Path,
    cells: list[tuple[str, str, str]],
    lod_cells: list[tuple[str, str, str]] | None = None,
    mesh_dirs: dict[str, dict[str, str]] | None = None,
) -> list[dict]:
    """One row per cell: the cell's origin, then each stage's record (:mod:`stages.config.records`)
    and time, mesh-level stages first. ``mesh_dirs``: mesh id -> stage -> folder of the mesh-level
    work the cell used (the workflow's shared ``results/meshes/<mesh>/<key>/<stage>``); a stage not
    named there is read from ``results/<mesh>/<stage>``. ``lod_cells``: the cells the run makes
    levels of detail for (a lod folder left from a run with them on is not read)."""
    rows = []
    for mesh, prompt, variant in cells:
        mesh_work = (mesh_dirs or {}).get(mesh, {})
        folders = {r.stage: Path(mesh_work[r.stage]) if r.stage in mesh_work else results / mesh / r.stage for r in MESH_RECORDS}
        if mesh_work and "decimate" not in mesh_work:
            folders.pop("decimate")  # the run does not decimate this mesh: an old folder is not read
        cell = results / mesh / prompt / variant
        with_lod = lod_cells is None or (mesh, prompt, variant) in set(lod_cells)
        folders.update({r.stage: cell / r.stage for r in CELL_RECORDS if r.stage != "lod" or with_lod})
        origin = check_origins(cell, () if with_lod else ("lod",))
        row = {
            "mesh": mesh,
            "prompt": prompt,
            "variant": variant,
            "test_only_weights": bool(origin["test_only"]),
            "image_guided": bool(origin["image_guided"]),
            ORIGIN_KEY: origin["label"],
        }
        for record in (*MESH_RECORDS, *CELL_RECORDS):
            row.update(_record_columns(record, folders.get(record.stage)))
        if row["faces_after"] is None:  # not decimated: the mesh as read
            row.update(faces_after=row["faces_before"], decimated=False)
        rows.append(row)
    return rows


#: the summary's columns before the records': the cell and its origin
CELL_COLUMNS = (
    column("mesh", "the mesh's id"),
    column("prompt", "the prompt's id"),
    column("variant", "the variant's id"),
    column("test_only_weights", "made with the tiny random test CLIP: not a real stylisation"),
    column("image_guided", "fitted to image targets: not stylised from its prompt"),
    column(ORIGIN_KEY, "what made the cell (guidance and weights), as each of its outputs says"),
)


def summary_columns() -> list[Column]:
    """Every column of a summary row, in order (:func:`summary_rows`): the cell's, then each
    record's columns and its stage's wall time (``seconds_<stage>``)."""
    out = list(CELL_COLUMNS)
    for record in (*MESH_RECORDS, *CELL_RECORDS):
        out += record.columns()
        heading = "optimise" if record.stage == "optimize" else record.stage
        out.append(column(f"seconds_{record.stage}", f"wall time of the {record.stage} stage", "s", heading=heading))
    return out


#: the records a cell cannot do without (the others belong to stages a run may leave out)
REQUIRED = ("normalize", "optimize")


def _record_columns(record: type[StageRecord], folder: Path | None) -> dict:
    """A stage's columns and its time (``seconds_<stage>``) from its folder; empty where the stage
    did not run (a required one is an error)."""
    meta = None if folder is None else (_need if record.stage in REQUIRED else _read)(folder / "meta.json")
    data = meta if record.file == "meta.json" or meta is None else _read(folder / record.file)
    columns = record.from_meta(data).row() if data is not None else record.empty_row()
    return {**columns, f"seconds_{record.stage}": meta["timings_s"]["total"] if meta else None}


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
        opt = OptimizeRecord.from_meta(_need(results / mesh / prompt / variant / "optimize" / "meta.json"))
        y = header + i * tile
        draw.text((4, y + 6), f"{mesh} / {prompt} / {variant}\n{opt.weights_label()[:34]}", fill="black")
        for j, kind in enumerate(OVERVIEW_KINDS):
            canvas.paste(front_tile(results, (mesh, prompt, variant), kind, tile), (label_w + j * tile, y))
    return np.asarray(canvas)


def quality_of(row: dict) -> tuple[float | None, str]:
    """The quality number of a row and its name: held-out target PSNR for image-guided runs,
    else the evaluation CLIP score."""
    if row.get("target_psnr_db") is not None and not _nan(row["target_psnr_db"]):
        return float(row["target_psnr_db"]), "target PSNR (dB, held-out metric views)"
    if row.get("clip_score") is not None and not _nan(row["clip_score"]):
        return float(row["clip_score"]), f"CLIP score ({row.get('eval_weights')})"
    return None, ""


def quality_text(value: float, name: str) -> str:
    """A quality figure as a short label: ``24.31 dB`` (target PSNR) or ``CLIP 0.312``."""
    return f"{value:.2f} dB" if name.startswith("target PSNR") else f"CLIP {value:.3f}"


def _nan(x) -> bool:
    return isinstance(x, float) and x != x


def speed_accuracy(rows: list[dict], results: Path) -> list[dict]:
    """Per cell with a quality figure and an optimisation time: the wall time, the peak memory
    (Snakemake's benchmark file, when there is one) and the quality, with the cell's ids, the
    quality's name and whether test-only weights made it (what :mod:`stages.results.compare`
    groups on)."""
    out = []
    for r in rows:
        q, qname = quality_of(r)
        if q is None or r.get("seconds_optimize") is None:
            continue
        bench = results / r["mesh"] / r["prompt"] / r["variant"] / "benchmarks" / "optimize.tsv"
        peak = None
        if bench.exists() or bench.is_symlink():
            import pandas as pd

            # Snakemake writes "-" where it measured nothing (a very short job)
            table = read_csv(bench, "Rerun the cell's optimisation.", sep="\t", usecols=["max_rss"])
            value = pd.to_numeric(table["max_rss"], errors="coerce").iloc[0] if len(table) else float("nan")
            peak = None if pd.isna(value) else float(value)
        out.append(
            {
                "mesh": r["mesh"],
                "prompt": r["prompt"],
                "variant": r["variant"],
                "seconds": float(r["seconds_optimize"]),
                "peak_mb": peak,
                "quality": q,
                "quality_name": qname,
                "weights": r.get("eval_weights") or r.get("weights"),
                "test_only": bool(r.get("test_only_weights") or r.get("eval_test_only")),
            }
        )
    return out


def front_tile(results: Path, cell: tuple[str, str, str], kind: str = "rgb", size: int = 160):
    from PIL import Image

    mesh, prompt, variant = cell
    meta = results / mesh / prompt / variant / "optimize" / "meta.json"
    sh = _need(meta).get("sheet")
    path = require_plain_file(results / mesh / prompt / variant / "optimize" / "renders" / f"{kind}.png", results)
    with open_read(path, IMAGE_LIMIT, results) as fh, Image.open(fh) as img:
        sheet = sh if isinstance(sh, dict) else {}
        columns, tile, front = sheet.get("columns"), sheet.get("tile"), sheet.get("front_view")
        if not all(isinstance(x, int) and not isinstance(x, bool) for x in (columns, tile, front)) or min(columns, tile) < 1:
            raise StageInputError(meta, f"its sheet ({sh!r:.120}) is not whole numbers of views and pixels", "Rerun the cell.")
        r, c = divmod(front, columns)
        if front < 0 or (c + 1) * tile > img.width or (r + 1) * tile > img.height:
            raise StageInputError(
                meta, f"its sheet (tile {tile}, view {front}) lies outside its {img.width}x{img.height} render", "Rerun the cell."
            )
        return img.crop((c * tile, r * tile, (c + 1) * tile, (r + 1) * tile)).resize((size, size))
