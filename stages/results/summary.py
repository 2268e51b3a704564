"""Reading a results tree: per-cell summary rows, origin checks, each cell's quality figure and
time (what the comparisons of :mod:`stages.results.compare` group), the overview image and the
front view of a cell."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from ..core.errors import StageInputError
from ..core.provenance import ORIGIN_KEY, read_origin
from ..core.safefiles import require_plain_file

log = logging.getLogger(__name__)

OVERVIEW_KINDS = ("rgb", "diffuse", "roughness", "specular", "normal")
MESH_STAGES = ("normalize", "decimate", "raycache")
CELL_STAGES = ("optimize", "bake", "export", "relight", "metrics")


def _read(path: Path) -> dict | None:
    """A stage's JSON record, or None where there is none; a link or a FIFO in its place is one
    line (a received results folder is data)."""
    if not path.exists() and not path.is_symlink():
        return None
    return json.loads(require_plain_file(path, remedy="Rerun the stage that writes it.").read_text())


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
    """One row per cell. ``mesh_dirs``: mesh id -> stage -> folder of the mesh-level work the
    cell used (the workflow's shared ``results/meshes/<mesh>/<key>/<stage>``); a stage not
    named there is read from ``results/<mesh>/<stage>``."""
    rows = []
    for mesh, prompt, variant in cells:
        mesh_work = (mesh_dirs or {}).get(mesh, {})

        def stage_dir(stage: str, mesh: str = mesh, mesh_work: dict = mesh_work) -> Path:
            return Path(mesh_work[stage]) if stage in mesh_work else results / mesh / stage

        cdir = results / mesh / prompt / variant
        opt = _need(cdir / "optimize" / "meta.json")
        # levels of detail: only where the run makes them (a folder left from a run with them on is not read)
        with_lod = lod_cells is None or (mesh, prompt, variant) in set(lod_cells)
        origin = check_origins(cdir, () if with_lod else ("lod",))
        bake = _read(cdir / "bake" / "meta.json") or {}
        export = _read(cdir / "export" / "meta.json") or {}
        norm = _need(stage_dir("normalize") / "meta.json")
        dec = _read(stage_dir("decimate") / "meta.json") if not mesh_work or "decimate" in mesh_work else None
        row = {
            "mesh": mesh,
            "prompt": prompt,
            "variant": variant,
            "prompt_text": opt.get("prompt"),
            "guidance": "image-guided (procedural targets)" if opt.get("guidance") == "image" else "CLIP",
            "weights": weights_label(opt),
            "test_only_weights": bool(origin["test_only"]),
            "image_guided": bool(origin["image_guided"]),
            ORIGIN_KEY: origin["label"],
            "iterations": opt["settings"]["iterations"],
            "final_similarity": opt.get("final_similarity"),
            "eval_psnr_db": opt.get("eval_psnr_db"),
            "faces_before": norm["stats"]["faces"],
            "faces_after": dec["stats"]["faces_after"] if dec else norm["stats"]["faces"],
            "decimated": dec is not None,
            "bake_psnr_db": bake.get("stats", {}).get("bake_psnr_db"),
            "texture_size": bake.get("stats", {}).get("texture_size"),
            "usd_validators": export.get("stats", {}).get("usd_validators"),
            "usd_validation_errors": export.get("stats", {}).get("usd_validation_errors"),
            "usd_validation_warnings": export.get("stats", {}).get("usd_validation_warnings"),
            "gltf_validation_errors": export.get("stats", {}).get("gltf_validation_errors"),
            "gltf_validation_warnings": export.get("stats", {}).get("gltf_validation_warnings"),
        }
        if dec:
            row["decimation_target"] = dec["stats"].get("target_faces")
            row["decimation_target_reached"] = dec["stats"].get("target_reached")
            row["decimation_shortfall"] = dec["stats"].get("target_shortfall_reason")
        metrics = _read(cdir / "metrics" / "metrics.json") or {}
        ev = metrics.get("evaluation") or {}
        it = metrics.get("image_target") or {}
        gd = metrics.get("guidance") or {}
        row.update(
            {
                "guidance_similarity": gd.get("similarity"),
                "eval_weights": ev.get("weights"),
                "eval_test_only": ev.get("test_only"),
                "clip_score": ev.get("clip_score"),
                "r_precision": ev.get("r_precision"),
                "r_precision_candidates": ev.get("candidates"),
                "target_psnr_db": it.get("psnr_db"),
                "target_ssim": it.get("ssim"),
                "target_renderer": it.get("target_renderer"),
                "target_albedo_rmse": (it.get("material") or {}).get("albedo_rmse"),
                "target_albedo_rmse_scaled": (it.get("material") or {}).get("albedo_rmse_scaled"),
                "target_roughness_mae": (it.get("material") or {}).get("roughness_mae"),
                "target_normal_angle_deg": (it.get("material") or {}).get("normal_angle_deg_mean"),
            }
        )
        relit = ((_read(cdir / "relight" / "meta.json") or {}).get("stats") or {}).get("ground_truth") or []
        row.update(
            {
                # one entry per environment of target.relight_environments, "/"-separated (the
                # environments " | "-separated: a path holds slashes)
                "relit_environments": " | ".join(g["environment"] for g in relit) or None,
                "relit_psnr_db": "/".join(f"{g['psnr_db']:.2f}" for g in relit) or None,
                "relit_psnr_scaled_db": "/".join(f"{g['psnr_scaled_db']:.2f}" for g in relit if "psnr_scaled_db" in g) or None,
                "relit_ceiling_psnr_db": "/".join(f"{g['ceiling_psnr_db']:.2f}" for g in relit if "ceiling_psnr_db" in g) or None,
                # the per-channel factors of the scaled figures, "r,g,b" per environment: unequal
                # factors mean the light's colour went into the base colour
                "relit_scale": "/".join(",".join(f"{x:.2f}" for x in g["scale"]) for g in relit if "scale" in g) or None,
            }
        )
        rt = _read(cdir / "roundtrip" / "meta.json") or {}
        rts = rt.get("stats", {})
        row.update(
            {
                "roundtrip_glb_psnr_db": rts.get("glb_psnr_db"),
                "roundtrip_usdz_psnr_db": rts.get("usdz_psnr_db"),
                "roundtrip_glb_diffuse_psnr_db": rts.get("glb_diffuse_psnr_db"),
                "roundtrip_glb_lobes_summed_psnr_db": rts.get("glb_lobes_summed_psnr_db"),
                "roundtrip_problems": rts.get("problems"),
                "roundtrip_transport": rts.get("transport"),
                "seconds_roundtrip": rt["timings_s"]["total"] if rt else None,
            }
        )
        lod = (_read(cdir / "lod" / "meta.json") or {}).get("stats", {}).get("levels", []) if with_lod else []
        row.update(
            {
                # one entry per level (lod0 = the full mesh), "/"-separated
                "lod_faces": "/".join(str(r["faces"]) for r in lod) or None,
                "lod_glb_bytes": "/".join(str(r["file_bytes"]["model.glb"]) for r in lod) or None,
                "lod_fidelity_psnr_db": "/".join(f"{r['fidelity_psnr_db']:.2f}" for r in lod) or None,
            }
        )
        for stage in MESH_STAGES:
            meta = _read(stage_dir(stage) / "meta.json")
            row[f"seconds_{stage}"] = meta["timings_s"]["total"] if meta else None
            if stage == "raycache":
                # the share of the hemisphere the mesh's surface sees blocked (its self-shadowing)
                occ = (meta or {}).get("self_occlusion") or {}
                row["self_occlusion_median"] = occ.get("median")
                row["self_occlusion_p95"] = occ.get("p95")
        for stage, folder in zip(CELL_STAGES, ("optimize", "bake", "export", "relight", "metrics"), strict=True):
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
        y = header + i * tile
        draw.text((4, y + 6), f"{mesh} / {prompt} / {variant}\n{weights_label(opt)[:34]}", fill="black")
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
        if bench.is_file():
            import pandas as pd

            # Snakemake writes "-" where it measured nothing (a very short job)
            value = pd.to_numeric(pd.read_csv(bench, sep="\t")["max_rss"], errors="coerce").iloc[0]
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
    with Image.open(path) as img:
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
