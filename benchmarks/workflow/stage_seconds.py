"""Seconds per job of every rule of a finished run, from Snakemake's benchmark files: the reference
table the plan and the doctor fall back on where a machine has no earlier run of its own
(``benchmarks/figures/stage_seconds.json``, read by :func:`stages.plan.other_stage_seconds`).

    python -m benchmarks.workflow.stage_seconds results/demo                      # print the table
    python -m benchmarks.workflow.stage_seconds results/demo --out benchmarks/figures/stage_seconds.json \\
        --command "snakemake --cores 2 --configfile config/demo.yaml"

Per rule: the median wall seconds of its jobs in the experiment (its cells' ``benchmarks/``, its
meshes' under ``results/meshes/<mesh>/`` that the cells used, the report's), and the count of jobs.
The table records the date, the machine (CPU model and cores), the commit and the command, which
the plan quotes with every figure it takes from it (all but the commit, kept for provenance).
"""

from __future__ import annotations

import argparse
import datetime
import json
import statistics
from pathlib import Path

from benchmarks.common import rule_seconds
from benchmarks.records import commit, machine


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("experiment", type=Path, help="results/<experiment> of a finished run")
    parser.add_argument("--out", type=Path, help="write the table here (JSON)")
    parser.add_argument("--command", default="", help="the command that made the run (recorded)")
    args = parser.parse_args()
    if not args.experiment.is_dir():
        parser.error(f"{args.experiment}: no such results folder")
    times = rule_seconds(args.experiment)
    if not times:
        parser.error(f"{args.experiment}: no benchmark files (a run's rules write them under benchmarks/)")
    print(f"{'rule':<14}{'jobs':>6}{'median s':>10}{'total s':>10}")
    for rule, values in sorted(times.items(), key=lambda kv: -sum(kv[1])):
        print(f"{rule:<14}{len(values):>6}{statistics.median(values):>10.1f}{sum(values):>10.1f}")
    print(f"{'all':<14}{sum(len(v) for v in times.values()):>6}{'':>10}{sum(sum(v) for v in times.values()):>10.1f}")
    if args.out:
        date = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d")
        table = {
            "seconds_per_job": {r: round(statistics.median(v), 2) for r, v in sorted(times.items())},
            "jobs": {r: len(v) for r, v in sorted(times.items())},
            # what the plan prints (no commit: the plan speaks to users), and the commit for provenance
            "conditions": f"{args.command or args.experiment}, {date}, {machine()}",
            "commit": commit(),
        }
        tmp = args.out.with_suffix(".tmp")
        tmp.write_text(json.dumps(table, indent=1) + "\n")
        tmp.replace(args.out)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
