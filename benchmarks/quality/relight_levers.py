"""The relighting levers side by side over their seed replicates: per cell and configuration (a
variant and its ``_seed<N>`` replicates), the training-light figure and the relit figures under
each graded environment, raw and after the best scale per channel, and the per-channel factors'
spread, as mean ± half the range over the seeds (a Markdown table).

    python -m benchmarks.quality.relight_levers results/ablations-relight
    python -m benchmarks.quality.relight_levers results/ablations-relight --order base,mesh_normals,known_light

Reads each cell's ``metrics/metrics.json`` (``image_target.psnr_db``: held-out metric views under
the training light) and ``relight/meta.json`` (``stats.ground_truth``: against Mitsuba's relit
truth); a cell without both is left out. The factors' spread is the largest factor over the
smallest, minus 1, averaged over the seeds.
"""

from __future__ import annotations

import argparse
import json
import re
import statistics
from pathlib import Path


def cells(results: Path) -> dict[tuple[str, str], list[dict]]:
    """(mesh/prompt, configuration) -> one record per replicate."""
    out: dict[tuple[str, str], list[dict]] = {}
    for relight in sorted(results.glob("*/*/*/relight/meta.json")):
        cell = relight.parents[1]
        metrics = cell / "metrics" / "metrics.json"
        if not metrics.is_file():
            continue
        graded = json.loads(relight.read_text())["stats"].get("ground_truth") or []
        if not graded:
            continue
        record = {"training": json.loads(metrics.read_text())["image_target"]["psnr_db"], "envs": {}}
        for g in graded:
            factors = [float(x) for x in (g["scale"].split(",") if isinstance(g["scale"], str) else g["scale"])]
            name = Path(g["environment"]).name if not g["environment"].startswith("builtin:") else g["environment"]
            record["envs"][name] = (g["psnr_db"], g["psnr_scaled_db"], max(factors) / min(factors) - 1)
        key = (f"{cell.parents[1].name}/{cell.parent.name}", re.sub(r"_seed\d+$", "", cell.name))
        out.setdefault(key, []).append(record)
    return out


def spread(values: list[float]) -> str:
    mean = statistics.mean(values)
    return f"{mean:.2f} ± {(max(values) - min(values)) / 2:.2f}" if len(values) > 1 else f"{mean:.2f}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results", type=Path, help="results/<experiment> with graded relight stages")
    parser.add_argument("--order", help="configurations in this order (comma-separated; default: as found)")
    args = parser.parse_args()
    found = cells(args.results)
    if not found:
        parser.error(f"{args.results}: no cell with a graded relight stage and metrics")
    envs = sorted({e for rs in found.values() for r in rs for e in r["envs"]})
    order = args.order.split(",") if args.order else sorted({c for _, c in found}, key=lambda c: (c != "base", c))
    head = " | ".join(f"{e}: raw / scaled" for e in envs)
    print(f"| cell | variant | seeds | training | {head} | factors' spread ({' / '.join(envs)}) |")
    print("| --- | --- | ---: | ---: | " + " | ".join("---:" for _ in envs) + " | ---: |")
    for cell in sorted({c for c, _ in found}):
        for conf in order:
            rs = found.get((cell, conf))
            if not rs:
                continue
            figs = " | ".join(f"{spread([r['envs'][e][0] for r in rs])} / {spread([r['envs'][e][1] for r in rs])}" for e in envs)
            spreads = " / ".join(f"{statistics.mean(r['envs'][e][2] for r in rs) * 100:.0f}%" for e in envs)
            training = spread([r["training"] for r in rs])
            print(f"| {cell.replace('/', ' / ')} | {conf} | {len(rs)} | {training} | {figs} | {spreads} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
