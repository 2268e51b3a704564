"""report: one summary table and one overview image over every grid cell.

``summary.csv`` (pandas): one row per mesh x prompt x variant with the guidance and the weights
that made it (real CLIP weights, "test-only random" for the tiny test CLIP, or the image
targets), iterations, final similarity (CLIP) or held-out PSNR (image targets), faces before and
after decimation, bake fidelity, texture size, and the wall time of every stage.
``overview.png``: rows are cells, columns RGB, diffuse, roughness, specular and predicted normals
from the evaluation view nearest the front, each row labelled.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import pandas as pd
from PIL import Image

from .core.cli import stage_main
from .core.provenance import atomic_path, write_json_atomic
from .results.cells import parse_cells
from .results.summary import (
    overview_image,
    plot_bars,
    plot_losses,
    plot_pareto,
    speed_accuracy,
    summary_rows,
    write_grids,
)

log = logging.getLogger(__name__)


def run(
    results: Path,
    cells: list[tuple[str, str, str]],
    out_dir: Path,
    decimated: dict | None = None,
    lod_cells: list[tuple[str, str, str]] | None = None,
    mesh_dirs: dict[str, dict[str, str]] | None = None,
) -> list[dict]:
    """Write summary.csv/json, overview.png, the speed/accuracy table and plot, ablation bars,
    loss curves and image grids into ``out_dir``. ``decimated``: decimated mesh id -> the id of
    the same source at full resolution (for the robustness grid). ``lod_cells``: the cells whose
    levels of detail are read (None: every cell that has them). ``mesh_dirs``: mesh id -> stage
    -> the folder of its mesh-level work (the workflow's results/meshes/<mesh>/<key>/<stage>;
    default: ``results/<mesh>/<stage>``)."""
    results = Path(results)
    rows = summary_rows(results, cells, lod_cells, mesh_dirs)
    frame = pd.DataFrame(rows)
    out_dir = Path(out_dir)
    with atomic_path(out_dir / "summary.csv") as tmp:
        frame.to_csv(tmp, index=False)
    with atomic_path(out_dir / "overview.png") as tmp:
        Image.fromarray(overview_image(results, cells)).save(tmp, format="PNG")
    write_json_atomic(out_dir / "summary.json", rows)
    sa = speed_accuracy(rows, results)
    with atomic_path(out_dir / "speed_accuracy.csv") as tmp:
        pd.DataFrame(sa).to_csv(tmp, index=False)
    plot_pareto(out_dir / "pareto.png", sa)
    plot_bars(out_dir / "ablation_bars.png", rows)
    plot_losses(out_dir / "loss_curves.png", results, cells)
    grids = write_grids(results, cells, out_dir, decimated or {})
    write_json_atomic(out_dir / "figures.json", {"grids": grids})
    log.info("summary of %d cells written to %s", len(rows), out_dir)
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

    def body(args):
        lod = None if args.lod_cells is None else parse_cells(args.lod_cells)
        run(args.results, parse_cells(args.cells), args.out_dir, json.loads(args.decimated), lod, json.loads(args.mesh_dirs))

    return stage_main("report", __doc__, arguments, body, argv)


if __name__ == "__main__":
    raise SystemExit(main())
