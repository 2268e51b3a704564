"""The HTML report at scale: a folder (index + one page per cell) against the single self-contained
file, on a synthetic grid (scripts/synthetic_results.py: generated inputs with real GLBs, no
optimisation), measured side by side in one run.

Printed for each grid size: the time of the report stage (tables and figures) and of the HTML
stage in both forms; the index's size, the whole folder's size, the largest cell page with its own
assets, and the single file's size; then, in headless Chromium (Node.js, Debian's chromium and
playwright-core), the index's time to interactive (ms after navigation start, when its script has
made the table sortable and filterable) and load, a cell page's time until its 3D viewer has loaded
its model (ms after navigation start), and the single file's time until every viewer, scrolled
into view one by one, has loaded.

    python -m benchmarks.workflow.report_scale                 # 15 and 150 cells
    python -m benchmarks.workflow.report_scale --meshes 30 --prompts 5 --no-browser
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import REPO


def folder_bytes(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def browser(mode: str, page: Path, shot: Path) -> tuple[dict, float]:
    t0 = time.perf_counter()
    out = subprocess.run(
        ["node", str(REPO / "scripts" / "check_report.mjs"), mode, str(page), str(shot)],
        capture_output=True,
        text=True,
        check=True,
        timeout=600,
    )
    return json.loads(out.stdout.strip().splitlines()[-1]), time.perf_counter() - t0


def measure(work: Path, meshes: int, prompts: int, with_browser: bool) -> None:
    from stages import html_report, report
    from stages.config.sections import ReportSettings

    results = work / f"r{meshes}x{prompts}"
    subprocess.run(
        [
            sys.executable,
            str(REPO / "scripts" / "synthetic_results.py"),
            str(results),
            "--meshes",
            str(meshes),
            "--prompts",
            str(prompts),
            "--decimated",
            str(min(2, meshes // 2)),
        ],
        check=True,
        capture_output=True,
    )
    cells = [tuple(line.split("/")) for line in (results / "cells.txt").read_text().split()]
    decimated = json.loads((results / "decimated.json").read_text())
    t0 = time.perf_counter()
    report.run(results, cells, results / "report", decimated)
    t_report = time.perf_counter() - t0
    single_dir = results / "single"
    shutil.copytree(results / "report", single_dir)
    t0 = time.perf_counter()
    html_report.run(results, results / "report", cells)
    t_folder = time.perf_counter() - t0
    t0 = time.perf_counter()
    html_report.run(results, single_dir, cells, ReportSettings(single_file=True))
    t_single = time.perf_counter() - t0
    d = results / "report"
    pages = [d.joinpath("cells", *c) for c in cells]
    largest = max(folder_bytes(p) for p in pages)
    print(f"\n{len(cells)} cells ({meshes} meshes x {prompts} prompts x 5 variants)")
    print(f"  report stage (tables, figures): {t_report:6.1f} s")
    print(f"  html: folder {t_folder:6.2f} s, single file {t_single:6.2f} s")
    index, single = (d / "index.html").stat().st_size, (single_dir / "index.html").stat().st_size
    print(f"  index.html {index / 1e6:6.3f} MB (budget 2 MB); single file {single / 1e6:7.2f} MB", end="")
    print(f" = {single / index:5.0f} x the index")
    print(f"  whole folder {folder_bytes(d) / 1e6:7.1f} MB; largest cell page with its assets {largest / 1e6:5.2f} MB")
    if not with_browser:
        return
    r, wall = browser("index", d / "index.html", work / "index.png")
    print(
        f"  index in Chromium: interactive at {r['interactive_ms']} ms (budget 1000 ms), load {r['load_ms']} ms, "
        f"{r['rows']} rows, {len(r['errors'])} console errors"
    )
    r, wall = browser("cell", pages[0] / "index.html", work / "cell.png")
    print(
        f"  a cell page: viewer {r['loaded']}/{r['viewers']} had its model {r['viewer_ms']} ms after navigation start, "
        f"{len(r['requests'])} requests, {len(r['errors'])} console errors"
    )
    r, wall = browser("single", single_dir / "index.html", work / "single.png")
    print(
        f"  single file: {r['loaded']}/{r['viewers']} viewers loaded (scrolled into view one by one) in {wall:5.1f} s, "
        f"{len(r['errors'])} console errors"
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--meshes", type=int, nargs="+", default=[1, 10])
    parser.add_argument("--prompts", type=int, default=3)
    parser.add_argument("--no-browser", action="store_true")
    args = parser.parse_args()
    print(f"report_scale: {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
    with tempfile.TemporaryDirectory() as tmp:
        for m in args.meshes:
            measure(Path(tmp), m, args.prompts, not args.no_browser)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
