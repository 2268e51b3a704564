"""The documentation's pictures and examples, made from the current demo run by one command:

* ``docs/demo.png``: the demo's overview (``report/overview.png``: a row per cell);
* ``docs/report_index.png``, ``docs/report_cell.png``: the first screen of the report's index and
  of a cell page, in headless Chromium (``scripts/check_report.mjs``);
* ``docs/examples/doctor.md``, ``docs/examples/plan.md``: the doctor's and the plan's output on
  the demo's config, as the admonition blocks getting-started.md includes.

Each PNG carries the commit it was made at in a text chunk (``tango-stylize:commit``), and
``docs/pictures.json`` records, per file, the commit, the date, the machine and the paths whose
changes it shows; tests/docs/test_pictures.py fails when one of those paths changed after it.

    snakemake --cores 2 --configfile config/demo.yaml
    python -m benchmarks.workflow.doc_pictures results/demo
"""

from __future__ import annotations

import argparse
import datetime
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.records import commit, machine

REPO = Path(__file__).resolve().parents[2]
DOCS = REPO / "docs"
MANIFEST = DOCS / "pictures.json"
#: each made file, with the paths whose changes it shows (a change there makes it stale)
SHOWS = {
    "demo.png": ["stages/results/summary.py", "stages/optimize.py", "stages/training", "stages/model", "config/demo.yaml"],
    "report_index.png": ["stages/results", "stages/html_report.py", "stages/report.py", "config/demo.yaml"],
    "report_cell.png": ["stages/results", "stages/html_report.py", "config/demo.yaml"],
    "examples/doctor.md": ["stages/doctor.py", "config/demo.yaml"],
    "examples/plan.md": [
        "stages/plan.py",
        "stages/config/choices.py",
        "benchmarks/figures/preset_costs.json",
        "benchmarks/figures/stage_seconds.json",
        "config/config.yaml",
    ],
}
CELL = ("vase", "wood", "base")


def stamped_png(src: Path, dst: Path, made: str) -> None:
    """Copy the PNG ``src`` to ``dst`` with the commit it was made at in a text chunk."""
    from PIL import Image, PngImagePlugin

    info = PngImagePlugin.PngInfo()
    info.add_text("tango-stylize:commit", made)
    with Image.open(src) as img:
        img.save(dst, format="PNG", pnginfo=info)


def screenshot(mode: str, page: Path, shot: Path, *args: str) -> None:
    node = shutil.which("node")
    if node is None:
        raise SystemExit("Node.js is needed for the screenshots (and npm ci's playwright-core, and Chromium)")
    subprocess.run([node, str(REPO / "scripts" / "check_report.mjs"), mode, str(page), str(shot), *args], check=True)


def example(title: str, command: list[str]) -> str:
    """A collapsed admonition block with ``command``'s output and, in its title, when and where."""
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", *command], cwd=REPO, capture_output=True, text=True)
    took = time.perf_counter() - t0
    if proc.returncode not in (0, 1):  # the doctor's 1: a piece is missing, which the example shows
        raise SystemExit(f"{' '.join(command)} failed:\n{proc.stderr[-3000:]}")
    body = "\n".join("    " + line if line else "" for line in ["```", *proc.stdout.rstrip().splitlines(), "```"])
    when = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d")
    shown = f"python -m {' '.join(command)}"
    return f'??? example "{title} ({when}, {machine()}, commit {commit()}; it took {took:.0f} s)"\n\n    `{shown}`\n\n{body}\n'


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results", type=Path, help="the demo's results folder (results/demo of config/demo.yaml)")
    args = parser.parse_args(argv)
    report = args.results / "report"
    if not (report / "index.html").is_file():
        parser.error(f"{report}/index.html missing: run snakemake --cores 2 --configfile config/demo.yaml first")
    if subprocess.run(
        ["git", "status", "--porcelain", "--", *sorted({p for v in SHOWS.values() for p in v})],
        cwd=REPO,
        capture_output=True,
        text=True,
    ).stdout.strip():
        parser.error("what the pictures show has uncommitted changes: commit them first (the pictures record the commit)")
    made = commit()
    with tempfile.TemporaryDirectory() as tmp:
        stamped_png(report / "overview.png", DOCS / "demo.png", made)
        screenshot("index", report / "index.html", Path(tmp) / "index.png")
        stamped_png(Path(tmp) / "index.png", DOCS / "report_index.png", made)
        cell = report / "cells" / Path(*CELL) / "index.html"
        screenshot("cell", cell, Path(tmp) / "viewer.png", "--page-shot", str(Path(tmp) / "cell.png"))
        stamped_png(Path(tmp) / "cell.png", DOCS / "report_cell.png", made)
    (DOCS / "examples" / "doctor.md").write_text(
        example("The doctor on the demo's config", ["stages.doctor", "--configfile", "config/demo.yaml"])
    )
    (DOCS / "examples" / "plan.md").write_text(example("The plan of the default config", ["stages.plan"]))
    when = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    entries = {name: {"commit": made, "date": when, "machine": machine(), "shows": shows} for name, shows in SHOWS.items()}
    MANIFEST.write_text(json.dumps(entries, indent=1) + "\n")
    print(f"made {', '.join(SHOWS)} at {made}; commit them")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
