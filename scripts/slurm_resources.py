"""Per-rule Slurm resources from the benchmark files a run wrote (Snakemake's ``benchmark:``
TSVs: wall seconds ``s`` and peak resident memory ``max_rss`` in MB), for the ``set-resources``
of a Slurm profile (profiles/slurm/config.yaml).

    python scripts/slurm_resources.py results/ [--runtime-margin 3] [--mem-margin 2]

reads every ``benchmarks/<rule>.tsv`` below the folders given (``target-<material>.tsv`` counts
as ``target``), prints per rule the number of jobs, the largest wall time and peak memory, and a
YAML ``set-resources`` block: runtime = margin x the largest wall time (minutes, at least
``--min-runtime``), mem_mb = margin x the largest peak memory (rounded up to 256 MB, at least
``--min-mem-mb``). Run a pilot cell of the experiment with the settings it will use, then paste
the block into the profile: an optimisation's time grows with its iterations and image sizes.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from collections import defaultdict
from pathlib import Path


def rule_of(tsv: Path) -> str:
    return tsv.stem.split("-", 1)[0]


def measure(roots: list[Path]) -> dict[str, dict[str, float]]:
    """Rule -> jobs, largest wall seconds, largest peak RSS (MB)."""
    found: dict[str, dict[str, float]] = defaultdict(lambda: {"jobs": 0, "s": 0.0, "max_rss": 0.0})
    for root in roots:
        for tsv in sorted(root.rglob("benchmarks/*.tsv")):
            with open(tsv) as fh:
                rows = list(csv.DictReader(fh, delimiter="\t"))
            for row in rows:
                entry = found[rule_of(tsv)]
                entry["jobs"] += 1
                entry["s"] = max(entry["s"], float(row["s"]))
                rss = row.get("max_rss", "NA")
                if rss not in ("NA", "-", ""):
                    entry["max_rss"] = max(entry["max_rss"], float(rss))
    return dict(found)


def suggest(measured: dict[str, dict[str, float]], runtime_margin: float, mem_margin: float, min_runtime: int, min_mem_mb: int):
    out = {}
    for rule, m in sorted(measured.items()):
        runtime = max(min_runtime, math.ceil(runtime_margin * m["s"] / 60))
        mem = max(min_mem_mb, 256 * math.ceil(mem_margin * m["max_rss"] / 256))
        out[rule] = {"runtime": runtime, "mem_mb": mem}
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("roots", nargs="+", type=Path, help="results folders to read benchmark files from")
    parser.add_argument("--runtime-margin", type=float, default=3.0)
    parser.add_argument("--mem-margin", type=float, default=2.0)
    parser.add_argument("--min-runtime", type=int, default=10, help="minutes")
    parser.add_argument("--min-mem-mb", type=int, default=2048)
    args = parser.parse_args(argv)
    measured = measure(args.roots)
    if not measured:
        sys.stderr.write(f"no benchmarks/*.tsv below {', '.join(map(str, args.roots))}: run the workflow first\n")
        return 1
    sys.stdout.write(f"{'rule':<12} {'jobs':>5} {'max s':>9} {'max RSS MB':>11}\n")
    for rule, m in sorted(measured.items()):
        sys.stdout.write(f"{rule:<12} {m['jobs']:>5} {m['s']:>9.1f} {m['max_rss']:>11.0f}\n")
    sys.stdout.write(f"\nset-resources:  # runtime x{args.runtime_margin:g}, memory x{args.mem_margin:g}\n")
    for rule, r in suggest(measured, args.runtime_margin, args.mem_margin, args.min_runtime, args.min_mem_mb).items():
        sys.stdout.write(f"  {rule}: {{runtime: {r['runtime']}, mem_mb: {r['mem_mb']}}}\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
