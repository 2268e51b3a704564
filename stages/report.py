"""report: one summary table and one overview image over every grid cell.

``summary.csv`` (pandas): one row per mesh x prompt x variant with the guidance and the weights
that made it (real CLIP weights, "test-only random" for the tiny test CLIP, or the image
targets), iterations, final similarity (CLIP) or held-out PSNR (image targets), faces before and
after decimation, bake fidelity, texture size, and the wall time of every stage.
``overview.png``: rows are cells, columns RGB, diffuse, roughness, specular and predicted normals
from the evaluation view nearest the front, each row labelled.
``speed_accuracy.csv`` and ``figures/``: comparisons of like with like only
(:mod:`stages.results.compare`): per mesh x prompt across variants, against the reference
variant; a figure with nothing to compare is listed in ``figures.json`` with the reason.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import pandas as pd
from PIL import Image

from .config.records import text_row
from .config.sections import ReportSettings
from .core.cli import stage_main
from .core.provenance import atomic_path, write_json_atomic
from .core.safefiles import clear
from .results.cells import parse_cells
from .results.compare import cell_settings, comparison_groups, trade_off
from .results.figures import (
    ablation_figures,
    loss_figures,
    relit_text,
    robustness_figure,
    speed_accuracy_figures,
    variant_grids,
)
from .results.spreadsheet import spreadsheet_rows
from .results.summary import front_tile, overview_image, quality_text, speed_accuracy, summary_rows

log = logging.getLogger(__name__)


def run(
    results: Path,
    cells: list[tuple[str, str, str]],
    out_dir: Path,
    decimated: dict | None = None,
    lod_cells: list[tuple[str, str, str]] | None = None,
    mesh_dirs: dict[str, dict[str, str]] | None = None,
    settings: ReportSettings | None = None,
) -> list[dict]:
    """Write summary.csv/json, overview.png, speed_accuracy.csv (one row per configuration of
    each mesh x prompt) and the figures (``out_dir/figures/*.png``, listed with captions, or with
    the reason one is not drawn, in ``figures.json``). ``decimated``: decimated mesh id -> the id
    of the same source at full resolution (for the robustness figure). ``lod_cells``: the cells
    whose levels of detail are read (None: every cell that has them). ``mesh_dirs``: mesh id ->
    stage -> the folder of its mesh-level work (the workflow's results/meshes/<mesh>/<key>/<stage>;
    default: ``results/<mesh>/<stage>``)."""
    settings = settings or ReportSettings()
    results = Path(results)
    rows = summary_rows(results, cells, lod_cells, mesh_dirs)
    out_dir = Path(out_dir)
    with atomic_path(out_dir / "summary.csv") as tmp:  # lists as one text; text a spreadsheet would evaluate is quoted
        pd.DataFrame(spreadsheet_rows([text_row(r) for r in rows])).to_csv(tmp, index=False)
    with atomic_path(out_dir / "overview.png") as tmp:
        Image.fromarray(overview_image(results, cells)).save(tmp, format="PNG")
    write_json_atomic(out_dir / "summary.json", rows)  # every value as the records give it, lists as lists

    timed = speed_accuracy(rows, results)
    variants = list(dict.fromkeys(c[2] for c in cells))
    per_cell = {c: cell_settings(results.joinpath(*c)) for c in cells}
    groups = comparison_groups(timed, per_cell, variants, settings.reference, settings.ablations)
    trade = [t for g in groups for t in trade_off(g)]
    with atomic_path(out_dir / "speed_accuracy.csv") as tmp:
        pd.DataFrame(spreadsheet_rows(trade)).to_csv(tmp, index=False)

    figures_dir = out_dir / "figures"
    clear(figures_dir, "*.png")  # figures of an earlier, larger grid (refused where the folder is a link)
    figures_dir.mkdir(parents=True, exist_ok=True)
    faces = {r["mesh"]: int(r["faces_after"]) for r in rows}
    quality = {(t["mesh"], t["prompt"], t["variant"]): quality_text(t["quality"], t["quality_name"]) for t in timed}
    relit = {(r["mesh"], r["prompt"], r["variant"]): relit_text(r) for r in rows}

    kinds = {
        (r["mesh"], r["prompt"], r["variant"]): r["guidance"] + (", TEST ONLY" if r["test_only_weights"] else "") for r in rows
    }

    def tile(cell, size):
        return front_tile(results, cell, size=size)

    panels = settings.panels_per_figure
    entries = (
        speed_accuracy_figures(figures_dir, groups, panels)
        + ablation_figures(figures_dir, groups, panels)
        + loss_figures(figures_dir, results, cells, panels, kinds)
        + robustness_figure(figures_dir, results, cells, decimated or {}, faces, quality, tile, relit)
        + variant_grids(figures_dir, cells, tile)
    )
    for e in entries:
        if "file" in e:
            e["file"] = f"figures/{e['file']}"
        else:
            log.info("figure %r not drawn: %s", e["title"], e["skipped"])
    group_list = [
        {
            "group": g.label,
            "mesh": g.mesh,
            "prompt": g.prompt,
            "quality_name": g.quality_name,
            "test_only": g.test_only,
            "reference": g.reference,
            "configurations": g.configurations(),
            "factors": g.factor,
            "ablations": g.ablations,
            "duplicates": g.duplicates,
        }
        for g in groups
    ]
    write_json_atomic(out_dir / "figures.json", {"figures": entries, "groups": group_list})
    log.info("summary of %d cells written to %s (%d figures)", len(rows), out_dir, sum("file" in e for e in entries))
    return rows


def main(argv: list[str] | None = None) -> int:
    def arguments(parser):
        parser.add_argument("--results", type=Path, default=Path("results"))
        parser.add_argument("--out-dir", type=Path, default=Path("results/report"))
        parser.add_argument("--cells", nargs="+", required=True, help="mesh/prompt/variant ...")
        parser.add_argument("--decimated", default="{}", help="JSON: decimated mesh id -> full-resolution mesh id")
        parser.add_argument(
            "--mesh-dirs", default="{}", help="JSON: mesh id -> stage -> folder of its mesh-level work (normalize, ...)"
        )
        parser.add_argument(
            "--lod-cells", nargs="*", default=None, help="the cells with levels of detail (default: any that has them)"
        )
        parser.add_argument("--settings", default=None, help="JSON: the config's report section")

    def body(args):
        lod = None if args.lod_cells is None else parse_cells(args.lod_cells)
        run(
            args.results,
            parse_cells(args.cells),
            args.out_dir,
            json.loads(args.decimated),
            lod,
            json.loads(args.mesh_dirs),
            ReportSettings.from_json(args.settings),
        )

    return stage_main("report", __doc__, arguments, body, argv)


if __name__ == "__main__":
    raise SystemExit(main())
