"""html_report: the report as HTML pages (:mod:`stages.results.site`).

By default a folder beside the summary: ``index.html`` (the summary, sortable and filterable,
thumbnails, links and the figures), ``cells/<mesh>/<prompt>/<variant>/index.html`` (one page per
cell with its renders, material maps, loss curve, metrics, relighting and its 3D viewer, every
asset beside it by relative path) and ``viewer/`` (the bundled model-viewer and the pages' script).
With ``report.single_file: true``: one self-contained ``index.html`` (for small grids).

Without Node.js's packages (``node_modules/@google/model-viewer``, installed by ``npm ci`` in
``scripts/setup.sh`` when npm is available) the pages are still written, with each cell's static
preview in place of the 3D viewer, a warning in the log and a notice on the pages.
"""

from __future__ import annotations

import logging
from pathlib import Path

from .config.sections import ReportSettings
from .core.cli import stage_main
from .core.tools import MODEL_VIEWER
from .results.cells import parse_cells
from .results.site import write_folder, write_single_file
from .results.summary import front_tile

log = logging.getLogger(__name__)


def run(
    results: Path,
    report_dir: Path,
    cells: list[tuple[str, str, str]],
    settings: ReportSettings | None = None,
    model_viewer: Path | None = None,
) -> dict:
    """Write ``report_dir/index.html`` (and, as a folder, its cell pages); returns the number of
    cells, of 3D viewers (0 without model-viewer) and the index's size in bytes."""
    settings = settings or ReportSettings()
    model_viewer = MODEL_VIEWER if model_viewer is None else Path(model_viewer)
    if not model_viewer.is_file():
        log.warning(
            "%s not found: the report shows static previews instead of 3D viewers. Install Node.js and run "
            "'npm ci' in the repository (scripts/setup.sh does when npm is available), then rerun the report.",
            model_viewer,
        )
    report_dir = Path(report_dir)
    if settings.single_file:
        return write_single_file(results, report_dir, cells, report_dir / "index.html", model_viewer)

    def thumbnail(cell):
        return front_tile(Path(results), cell, size=settings.thumbnail_size)

    return write_folder(results, report_dir, cells, model_viewer, thumbnail)


def main(argv: list[str] | None = None) -> int:
    def arguments(parser):
        parser.add_argument("--results", type=Path, required=True, help="the experiment's folder (results/<experiment>)")
        parser.add_argument("--report-dir", type=Path, required=True, help="where summary.csv and figures/ are")
        parser.add_argument("--cells", nargs="+", required=True)
        parser.add_argument("--settings", default=None, help="JSON: the config's report section")

    def body(args):
        run(args.results, args.report_dir, parse_cells(args.cells), ReportSettings.from_json(args.settings))

    return stage_main("html_report", __doc__, arguments, body, argv)


if __name__ == "__main__":
    raise SystemExit(main())
