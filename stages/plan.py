"""plan: what a run of a config will do and about how long it will take here, before it starts.

    python -m stages.plan [--configfile config/config.yaml [overlay.yaml ...]] [--no-calibrate] [--json]

Printed by the workflow when it starts (``onstart``) and available alone. It says:

- the cells (meshes x prompts x variants) and the jobs per rule, and how many optimisations are
  already done (their ``optimize/meta.json`` exists under ``results/<experiment>/``);
- the device each torch stage will use;
- an **estimate** of the optimisations' wall time on this machine: iterations x seconds per step,
  the seconds per step taken from an earlier run of the same settings on the same device when
  one is in ``results/`` (its ``seconds_per_iteration``), else measured by a short calibration
  (:mod:`stages.training.calibrate`: a few real steps of these settings; cached in
  ``.cache/tango-plan/``; ``TANGO_PLAN_CALIBRATE=0`` skips it at the workflow's start), one
  optimisation at a time; the other stages from the benchmark files of earlier runs when there
  are any;
- on a CPU with the paper's settings, that it is so, and the faster presets with their
  measured quality cost (``benchmarks/figures/preset_costs.json``) and their time here.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import statistics
import sys
from pathlib import Path

from .config.presets import PRESETS
from .config.sections import OptimizeSettings
from .config.workflow import WorkflowConfig, experiment_name, load_config_files
from .core.cli import precision_summary, resolve_device, stage_main
from .training.calibrate import seconds_per_step

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[1]
PRESET_COSTS = REPO / "benchmarks" / "figures" / "preset_costs.json"
#: rules whose jobs are one per cell (besides optimize), and those once per experiment
PER_CELL = ("bake", "export", "relight", "metrics")
PER_EXPERIMENT = ("report", "pack", "html_report")
#: the settings that set what an optimisation costs (compared with the paper's, preset ``paper``)
COST_KEYS = ("iterations", "views_per_step", "crops", "width")
#: where calibrations are kept (per settings, device and machine)
CACHE = Path(".cache/tango-plan")
#: the rules that run torch (their --device)
TORCH_RULES = ("optimize", "bake", "relight", "metrics", "lod", "roundtrip")


def job_counts(cfg: WorkflowConfig) -> dict[str, int]:
    """Jobs per rule for the whole experiment (finished ones included), as the workflow plans them."""
    counts: dict[str, int] = {}

    def add(rule: str, n: int) -> None:
        if n:
            counts[rule] = counts.get(rule, 0) + n

    add("normalize", len(cfg.grid_meshes))
    add("decimate", sum(cfg.decimated(m) for m in cfg.grid_meshes))
    add("raycache", len(cfg.grid_meshes))
    add("target", len({(c.mesh, m) for c in cfg.cells if (m := cfg.target_material(c.prompt, c.variant))}))
    add("optimize", len(cfg.cells))
    for rule in PER_CELL:
        add(rule, len(cfg.cells))
    for rule in ("roundtrip", "lod"):
        add(rule, sum(cfg.cell_stage_settings(rule, c.prompt, c.variant).enabled for c in cfg.cells))
    for rule in PER_EXPERIMENT:
        add(rule, 1)
    return counts


def torch_device(cfg: WorkflowConfig) -> str:
    """Where the torch stages will run: what ``--device`` resolves to on this machine."""
    return resolve_device(cfg.device).type


def earlier_step_seconds(results: Path, digest: str, device: str) -> float | None:
    """``seconds_per_iteration`` of an earlier optimisation with these settings on this kind of
    device, anywhere under ``results`` (the median when several ran)."""
    found = []
    for meta in Path(results).glob("*/*/*/*/optimize/meta.json"):
        try:
            m = json.loads(meta.read_text())
        except (OSError, json.JSONDecodeError):
            continue
        s = m.get("settings") or {}
        if m.get("seconds_per_iteration") and str(m.get("device", "")).split(":")[0] == device and _digest(s) == digest:
            found.append(float(m["seconds_per_iteration"]))
    return statistics.median(found) if found else None


def _digest(settings: dict) -> str:
    """The settings that set a step's cost (the seed aside)."""
    text = json.dumps({k: v for k, v in settings.items() if k != "seed"}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def step_seconds(settings, raycache, device: str, results: Path, cache: Path, calibrate: bool) -> tuple[float | None, str]:
    """Seconds per optimisation step and where the figure comes from."""
    digest = _digest(settings.to_dict())
    earlier = earlier_step_seconds(results, digest, device)
    if earlier is not None:
        return earlier, "an earlier run of these settings"
    key = hashlib.sha256(f"{digest}|{_digest(dataclasses.asdict(raycache))}|{device}|{_machine()}".encode()).hexdigest()[:16]
    cached = cache / f"{key}.json"
    if cached.is_file():
        return float(json.loads(cached.read_text())["seconds_per_step"]), "a calibration of these settings (cached)"
    if not calibrate:
        return None, "not calibrated (--no-calibrate)"
    seconds = seconds_per_step(settings, raycache, device)
    cache.mkdir(parents=True, exist_ok=True)
    tmp = cached.with_suffix(".tmp")
    tmp.write_text(json.dumps({"seconds_per_step": seconds, "settings": settings.to_dict(), "device": device}))
    tmp.replace(cached)
    return seconds, "a calibration of these settings (a few real steps)"


def _machine() -> str:
    import os
    import platform

    import torch

    return f"{platform.processor() or platform.machine()}|{os.cpu_count()}|{torch.__version__}|{torch.get_num_threads()}"


def other_stage_seconds(results: Path) -> dict[str, float]:
    """Median wall seconds per job of the per-cell stages after optimize, from the benchmark
    files of earlier runs under ``results`` (Snakemake's ``benchmark:``)."""
    out = {}
    for rule in (*PER_CELL, "roundtrip", "lod"):
        times = []
        for tsv in Path(results).glob(f"*/*/*/*/benchmarks/{rule}.tsv"):
            lines = tsv.read_text().splitlines()
            if len(lines) >= 2:
                try:
                    times.append(float(lines[1].split("\t")[0]))
                except ValueError:
                    continue
        if times:
            out[rule] = statistics.median(times)
    return out


def guidance_label(settings) -> str:
    """What guides an optimisation, as the plan names it."""
    if settings.guidance != "clip":
        return "image targets"
    return "the tiny test CLIP" if settings.clip_tiny_test else settings.clip_model


def is_paper(settings) -> bool:
    """The paper's cost: its schedule, views, crops and width (preset ``paper``) at CLIP's full
    image size (whatever the material presets change besides)."""
    paper = PRESETS["paper"]
    return all(getattr(settings, k) == paper[k] for k in COST_KEYS) and settings.image_size >= OptimizeSettings().image_size


def make_plan(
    cfg: WorkflowConfig,
    experiment: str,
    results: Path = Path("results"),
    calibrate: bool = True,
    cache: Path = CACHE,
    pending: list[tuple[str, dict]] | None = None,
) -> dict:
    """Everything the plan says, as data. ``pending``: the jobs Snakemake will run, as (rule,
    wildcards) (the workflow passes its DAG's); without it, a cell's optimisation counts as done
    when its ``optimize/meta.json`` exists."""
    device = torch_device(cfg)
    if pending is not None:
        running = {(w.get("mesh"), w.get("prompt"), w.get("variant")) for rule, w in pending if rule == "optimize"}
        todo = [c for c in cfg.cells if (c.mesh, c.prompt, c.variant) in running]
    else:
        cell_dir = results / experiment
        todo = [c for c in cfg.cells if not (cell_dir / c.mesh / c.prompt / c.variant / "optimize" / "meta.json").is_file()]
    done = [c for c in cfg.cells if c not in todo]
    pending_jobs = None
    if pending is not None:
        pending_jobs = {}
        for rule, _ in pending:
            pending_jobs[rule] = pending_jobs.get(rule, 0) + 1
    groups: dict[str, dict] = {}
    for c in todo:
        s = cfg.optimize_settings(c.prompt, c.variant)
        entry = groups.setdefault(_digest(s.to_dict()), {"settings": s, "mesh": c.mesh, "cells": 0})
        entry["cells"] += 1
    estimates, total = [], 0.0
    for entry in groups.values():
        s = entry["settings"]
        sec, source = step_seconds(s, cfg.stage_settings(entry["mesh"], "raycache"), device, results, cache, calibrate)
        row = {
            "cells": entry["cells"],
            "iterations": s.iterations,
            "seconds_per_step": sec,
            "source": source,
            "paper": is_paper(s),
            "clip_model": guidance_label(s),
            "precision": precision_summary(s.bf16, s.bf16_networks, resolve_device(device)),
        }
        if sec is not None:
            row["seconds"] = sec * s.iterations * entry["cells"]
            total += row["seconds"]
        estimates.append(row)
    others = other_stage_seconds(results)
    other_total = sum(others.get(rule, 0.0) * len(todo) for rule in PER_CELL)
    plan = {
        "experiment": experiment,
        "source": cfg.source,
        "meshes": len(cfg.grid_meshes),
        "prompts": len({c.prompt for c in cfg.cells}),
        "variants": len(cfg.variants),
        "cells": len(cfg.cells),
        "optimisations_done": len(done),
        "jobs": job_counts(cfg),
        "pending_jobs": pending_jobs,
        "device": device,
        "device_setting": cfg.device,
        "optimisation": estimates,
        "optimisation_seconds": total if all(e["seconds_per_step"] is not None for e in estimates) else None,
        "other_stage_seconds": {r: others[r] for r in others},
        "other_seconds": other_total if others else None,
    }
    if device == "cpu" and any(e["paper"] for e in estimates):
        plan["paper_on_cpu"] = faster_presets(groups, cfg, device, results, cache, calibrate)
    return plan


def faster_presets(groups, cfg, device, results, cache, calibrate) -> list[dict]:
    """The speed presets applied to the paper-setting cells: their time here and their measured
    quality cost against the paper's settings (``benchmarks/figures/preset_costs.json``)."""
    costs = json.loads(PRESET_COSTS.read_text()) if PRESET_COSTS.is_file() else {}
    paper = [e for e in groups.values() if is_paper(e["settings"])]
    cells = sum(e["cells"] for e in paper)
    out = []
    for name in ("balanced", "fast"):
        seconds = 0.0
        for e in paper:
            preset = {k: tuple(v) if isinstance(v, list) else v for k, v in PRESETS[name].items()}
            s = dataclasses.replace(e["settings"], **preset)
            sec, _ = step_seconds(s, cfg.stage_settings(e["mesh"], "raycache"), device, results, cache, calibrate)
            seconds = None if sec is None or seconds is None else seconds + sec * s.iterations * e["cells"]
        measured = costs.get("presets", {})
        out.append(
            {
                "preset": name,
                "cells": cells,
                "seconds": seconds,
                "psnr_db": dict(zip(costs.get("meshes", []), measured.get(name, {}).get("psnr_db", []), strict=False)),
                "paper_psnr_db": dict(zip(costs.get("meshes", []), measured.get("paper", {}).get("psnr_db", []), strict=False)),
                "measured": f"{costs.get('measured', '?')}; {costs.get('conditions', '')}; {costs.get('command', '')}",
            }
        )
    return out


def _jobs(counts: dict[str, int]) -> str:
    return f"{sum(counts.values())} jobs ({', '.join(f'{r} {n}' for r, n in counts.items())})"


def duration(seconds: float | None) -> str:
    if seconds is None:
        return "not estimated"
    minutes = round(seconds / 60)
    if minutes < 1:
        return f"{seconds:.0f} s"
    return f"{minutes // 60} h {minutes % 60:02d} min" if minutes >= 60 else f"{minutes} min"


def plan_text(plan: dict) -> str:
    jobs = plan["jobs"]
    lines = [
        f"Plan of experiment {plan['experiment']} ({plan['source']}): {plan['meshes']} meshes x {plan['prompts']} prompts x "
        f"{plan['variants']} variants = {plan['cells']} cells, {sum(jobs.values())} jobs "
        f"({', '.join(f'{r} {n}' for r, n in jobs.items())}); {plan['optimisations_done']} of {plan['cells']} optimisations "
        "already done." + (f" To run now: {_jobs(plan['pending_jobs'])}." if plan.get("pending_jobs") is not None else ""),
        f"Torch stages ({', '.join(r for r in TORCH_RULES if r in jobs)}) run on {plan['device']} "
        f"(device: {plan['device_setting']}).",
    ]
    for e in plan["optimisation"]:
        per = f"{e['seconds_per_step']:.2f} s per step" if e["seconds_per_step"] is not None else "unknown per step"
        lines.append(
            f"  {e['cells']} optimisation(s) of {e['iterations']} steps ({e['clip_model']}): {per} from {e['source']} "
            f"-> {duration(e.get('seconds'))}"
        )
        lines.append(f"    precision: {e['precision']}")
    if not plan["optimisation"]:
        lines.append("No optimisation to run.")
        return "\n".join(lines) + "\n"
    opt, other = plan["optimisation_seconds"], plan["other_seconds"]
    est = f"Estimated wall time on this machine: {duration(opt)} of optimisation, one at a time"
    if other is not None:
        est += f", plus about {duration(other)} for the other per-cell stages (medians of earlier runs' benchmark files)"
    else:
        est += "; the other stages are not estimated (no earlier benchmark files in results/)"
    lines.append(est + ". An estimate, not a promise.")
    if plan.get("paper_on_cpu"):
        lines.append(
            f"{plan['paper_on_cpu'][0]['cells']} of these optimisations run the paper's settings (1,500 iterations, "
            "224-pixel CLIP images, 4 crops, width 256) on a CPU. Faster presets (preset: balanced or fast on a variant "
            "or a prompt):"
        )
        for p in plan["paper_on_cpu"]:
            paper = p["paper_psnr_db"]
            quality = ", ".join(f"{m} {db:.1f} dB (paper {paper.get(m, float('nan')):.1f})" for m, db in p["psnr_db"].items())
            here = f"{duration(p['seconds'])} here for the same {p['cells']} cell(s)"
            lines.append(f"  {p['preset']}: {here}; measured quality: {quality}")
        if plan["paper_on_cpu"]:
            lines.append(f"  (quality: {plan['paper_on_cpu'][0]['measured']})")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    def arguments(parser):
        parser.add_argument("--configfile", type=Path, nargs="+", default=[Path("config/config.yaml")])
        parser.add_argument("--results", type=Path, default=Path("results"))
        parser.add_argument("--no-calibrate", action="store_true", help="no calibration run (estimate from earlier runs only)")
        parser.add_argument("--cache", type=Path, default=CACHE, help="where calibrations are kept")
        parser.add_argument("--json", action="store_true")

    def body(args):
        cfg = load_config_files(args.configfile)
        plan = make_plan(cfg, experiment_name(cfg.raw, args.configfile), args.results, not args.no_calibrate, args.cache)
        if args.json:
            sys.stdout.write(json.dumps(plan, indent=1, default=str) + "\n")
        else:
            sys.stdout.write(plan_text(plan))

    return stage_main("plan", __doc__, arguments, body, argv)


if __name__ == "__main__":
    raise SystemExit(main())
