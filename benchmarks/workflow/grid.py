"""How the total time of a grid grows with meshes, prompts and variants.

Each point runs the whole workflow (``snakemake --cores 2``) from scratch in a temporary folder on
a tiny offline grid (the tiny test-only CLIP, few iterations, small images; the built-in meshes),
and reports the wall time, the number of jobs and the time per grid cell. Mesh-level stages run
once per mesh, so adding prompts or variants adds cells but no ray tracing.

    python -m benchmarks.workflow.grid
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

from benchmarks.common import REPO

MESHES = ["vase", "candle", "knot"]
PROMPTS = {"wood": "a {object} made of wood", "gold": "a {object} made of gold", "ice": "a {object} made of ice"}


def config(meshes: int, prompts: int, variants: int) -> dict:
    smoke = yaml.safe_load((REPO / "tests" / "smoke" / "config.yaml").read_text())
    smoke["meshes"] = {m: {"builtin": m} for m in MESHES[:meshes]}
    smoke["prompts"] = dict(list(PROMPTS.items())[:prompts])
    smoke["variants"] = {f"v{i}": {"optimize": {"seed": i}} for i in range(variants)}
    return smoke


def run(meshes: int, prompts: int, variants: int) -> tuple[float, int]:
    with tempfile.TemporaryDirectory() as d:
        cfg = Path(d) / "grid.yaml"
        cfg.write_text(yaml.safe_dump(config(meshes, prompts, variants)))
        env = dict(os.environ, XDG_CACHE_HOME=str(Path(d) / ".cache"))
        env["PATH"] = str(Path(sys.executable).parent) + os.pathsep + env["PATH"]
        t0 = time.perf_counter()
        out = subprocess.run(
            [
                sys.executable,
                "-m",
                "snakemake",
                "--snakefile",
                str(REPO / "Snakefile"),
                "--directory",
                d,
                "--cores",
                "2",
                "--configfile",
                str(cfg),
            ],
            capture_output=True,
            text=True,
            check=True,
            env=env,
        )
        wall = time.perf_counter() - t0
        jobs = len(re.findall(r"Finished job", out.stdout + out.stderr))
    return wall, jobs


def main() -> None:
    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args()
    points = [(1, 1, 1), (3, 1, 1), (1, 3, 1), (1, 1, 3), (3, 3, 2)]
    print(f"{'meshes':>7}{'prompts':>8}{'variants':>9}{'cells':>6}{'jobs':>6}{'wall s':>8}{'s/cell':>8}")
    kv = {}
    for m, p, v in points:
        wall, jobs = run(m, p, v)
        cells = m * p * v
        print(f"{m:>7}{p:>8}{v:>9}{cells:>6}{jobs:>6}{wall:>8.1f}{wall / cells:>8.1f}")
        kv[f"wall_s_{m}x{p}x{v}"] = wall
    print(" ".join(f"{k}={val:.4g}" for k, val in kv.items()))


if __name__ == "__main__":
    main()
