"""A run from scratch against the plan's estimate of it: the wall time of a config's whole run in a
fresh clone of this checkout (no results, no Snakemake records, no cached calibrations), beside
what ``python -m stages.plan`` estimated there just before, in all and per rule.

    python -m benchmarks.workflow.plan_accuracy --configfile config/demo.yaml
    python -m benchmarks.workflow.plan_accuracy --configfile config/demo-offline.yaml --keep /tmp/demo-run

Prints the estimate's parts (optimisation, Mitsuba's targets, the other rules per job and where
each figure came from), the run's wall time and peak memory, their ratio, and per rule the
estimate against the sum of the run's benchmark files. The clone uses this checkout's committed
state and the current Python environment; the machine should be otherwise idle (the plan says
when its calibration was taken under load).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import REPO, rule_seconds
from stages.config.workflow import experiment_name, load_config_files


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--configfile", default="config/demo.yaml", help="the config to run (relative to the repository)")
    parser.add_argument("--cores", type=int, default=2)
    parser.add_argument("--keep", type=Path, help="clone here and keep it (default: a temporary folder, removed)")
    parser.add_argument("--out", type=Path, help="write the figures here (JSON)")
    parser.add_argument(
        "--record",
        action="store_true",
        help="write the records the documentation quotes: <experiment>.wall_time, .peak_memory, .disk and .psnr",
    )
    args = parser.parse_args()
    if not (REPO / args.configfile).is_file():
        parser.error(f"{args.configfile}: no such config in {REPO}")
    root = args.keep or Path(tempfile.mkdtemp(prefix="plan-accuracy-"))
    clone = root / "clone"
    if clone.exists():
        parser.error(f"{clone} exists: name an empty folder with --keep")
    subprocess.run(["git", "clone", "--quiet", "--local", str(REPO), str(clone)], check=True)
    for installed in ("node_modules", ".venv-blender"):  # what the set-up installs beside the code
        if (REPO / installed).is_dir():
            (clone / installed).symlink_to(REPO / installed)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "TANGO_PLAN_CALIBRATE")}
    env["XDG_CACHE_HOME"] = str(root / "cache")
    try:
        plan = json.loads(
            subprocess.run(
                [sys.executable, "-m", "stages.plan", "--configfile", args.configfile, "--cores", str(args.cores), "--json"],
                cwd=clone,
                env=env,
                capture_output=True,
                text=True,
                check=True,
            ).stdout
        )
        t0 = time.perf_counter()
        proc = subprocess.run(
            [sys.executable, "-m", "snakemake", "--cores", str(args.cores), "--configfile", args.configfile],
            cwd=clone,
            env=env,
            capture_output=True,
            text=True,
        )
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            sys.stderr.write(proc.stderr[-4000:])
            return 1
        peak_gb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1e6
        cfg = load_config_files([clone / args.configfile])
        actual = rule_seconds(clone / "results" / experiment_name(cfg.raw, [Path(args.configfile)]))
        report(plan, wall, peak_gb, actual)
        if args.record:
            results = clone / "results" / experiment_name(cfg.raw, [Path(args.configfile)])
            record_run(args.configfile, results, plan, wall, peak_gb, actual)
        if args.out:
            figures = {"estimate": plan, "wall_seconds": wall, "peak_rss_gb": peak_gb, "rule_seconds": actual}
            args.out.write_text(json.dumps(figures, indent=1, default=str) + "\n")
    finally:
        if args.keep is None:
            shutil.rmtree(root, ignore_errors=True)
    return 0


#: an experiment's records by another name (the id its pages quote) and their page; the others
#: are named after the experiment, on the demo's page
RECORDS = {"demo-offline": ("offline_demo", "speed.md#the-offline-demo")}


def _duration(seconds: float) -> str:
    minutes, s = divmod(round(seconds), 60)
    return f"{minutes} min {s} s" if minutes else f"{s} s"


def record_run(configfile: str, results: Path, plan: dict, wall: float, peak_gb: float, actual: dict) -> None:
    """The run's records (benchmarks/figures/records): its wall time (with the plan's estimate), the peak
    resident memory of one job, the results' disk, and each cell's held-out PSNR."""
    import pandas as pd

    from benchmarks.records import disk_bytes, write_record

    name, page = RECORDS.get(results.name, (results.name, "demo.md"))
    command = (
        f"`python -m benchmarks.workflow.plan_accuracy --configfile {configfile} --record` "
        f"(runs `snakemake --cores 2 --configfile {configfile}` in a fresh clone)"
    )
    jobs = sum(len(v) for v in actual.values())
    estimate = plan.get("total_seconds")
    said = f" the plan estimated {_duration(estimate)} ({estimate / wall:.2f} of the run)" if estimate else ""
    write_record(
        f"{name}.wall_time",
        f"`{configfile}`: wall time from a fresh clone",
        _duration(wall),
        command,
        page,
        f"({jobs} jobs;{said})",
    )
    write_record(f"{name}.peak_memory", f"`{configfile}`: peak resident memory of one job", f"{peak_gb:.1f} GB", command, page)
    write_record(f"{name}.disk", f"`{configfile}`: the results' disk", f"{disk_bytes(results) / 1e6:.0f} MB", command, page)
    summary = pd.read_csv(results / "report" / "summary.csv")
    cells = "; ".join(
        f"{r.mesh} / {r.prompt} {r.target_psnr_db:.2f} dB" for r in summary.itertuples() if r.target_psnr_db == r.target_psnr_db
    )
    if cells:
        write_record(
            f"{name}.psnr", f"`{configfile}`: held-out PSNR per cell (object pixels, metric views)", cells, command, page
        )


def report(plan: dict, wall: float, peak_gb: float, actual: dict[str, list[float]]) -> None:
    total = plan["total_seconds"]
    t = plan["targets"]
    print(f"plan: {plan['optimisation_seconds']:.0f} s optimisation, {t['seconds'] or 0:.0f} s targets ({t.get('source')}),")
    print(f"      {plan['other_seconds']:.0f} s other rules ({plan['other_source']})")
    print(f"run:  {wall:.0f} s wall ({wall / 60:.1f} min), peak resident memory of one job {peak_gb:.2f} GB")
    if total:
        print(f"estimate / run: {total:.0f} / {wall:.0f} s = {total / wall:.2f}")
    per_job = plan["other_stage_seconds"]
    jobs = {**plan["other_jobs"], "target": t["jobs"]}
    print(f"{'rule':<14}{'jobs':>6}{'estimate s':>12}{'run s':>10}   (job seconds, side by side on {plan['cores']} cores)")
    estimated = 0.0
    for rule, values in sorted(actual.items(), key=lambda kv: -sum(kv[1])):
        if rule == "optimize":
            est = plan["optimisation_seconds"]
        elif rule == "target":
            est = t["seconds"]
        else:
            est = per_job.get(rule, float("nan")) * jobs.get(rule, 0)
        estimated += est if est is not None and est == est else 0.0  # (a rule without a figure: nan)
        print(f"{rule:<14}{len(values):>6}{est:>12.1f}{sum(values):>10.1f}")
    jobs_run, seconds_run = sum(len(v) for v in actual.values()), sum(map(sum, actual.values()))
    print(f"{'all jobs':<14}{jobs_run:>6}{estimated:>12.1f}{seconds_run:>10.1f}")


if __name__ == "__main__":
    raise SystemExit(main())
