"""plan: what a run of a config will do and about how long it will take here, before it starts.

    python -m stages.plan [--configfile config/config.yaml [overlay.yaml ...]] [--cores N] [--no-calibrate] [--json]

Printed by the workflow when it starts (``onstart``) and available alone. It says:

- the cells (meshes x prompts x variants) and the jobs per rule, and how many optimisations are
  already done (their ``optimize/meta.json`` exists under ``results/<experiment>/``);
- the device each torch stage will use;
- an **estimate** of the optimisations' wall time on this machine: iterations x seconds per step,
  the seconds per step taken from an earlier run of the same settings on the same device when
  one is in ``results/`` (its ``seconds_per_iteration``), else measured by a short calibration
  (:mod:`stages.training.calibrate`: a few real steps of these settings on the job's threads;
  cached in ``.cache/tango-plan/`` unless other processes used more than a quarter of the CPU
  meanwhile, which the plan then says; ``TANGO_PLAN_CALIBRATE=0`` skips it at the workflow's
  start); Mitsuba's target jobs from the samples they render (training views, metric views and
  the relit truths) at the rate of a probe render here on the job's threads; every other stage
  per job from the benchmark files of earlier runs when there are any, else from the reference
  table (``benchmarks/figures/stage_seconds.json``, with its conditions); in all, the jobs' CPU
  time spread over the run's cores (:func:`wall_seconds`; on a GPU run, never less than the GPU
  jobs one after another);
- on a CPU with the paper's settings, that it is so, and the faster presets with their
  measured quality cost (``benchmarks/figures/preset_costs.json``) and their time here.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import logging
import math
import os
import statistics
import sys
import time
from pathlib import Path

from .config.choices import COST_KEYS, PRESET_COSTS
from .config.presets import PRESETS
from .config.sections import OptimizeSettings
from .config.workflow import WorkflowConfig, experiment_name, load_config_files
from .core.cli import add_configfile, stage_main
from .core.device import precision_summary, resolve_device
from .core.errors import StageInputError
from .core.provenance import write_json_atomic
from .core.safefiles import read_json, read_text
from .core.threads import cpu_threads, threads_for
from .model.lights.sun import resolve_suns
from .reference.mitsuba import choose_variant
from .reference.targets import probe, target_samples
from .training.calibrate import seconds_per_step

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[1]
#: rules whose jobs are one per cell (besides optimize), and those once per experiment
PER_CELL = ("bake", "export", "relight", "metrics")
PER_EXPERIMENT = ("report", "pack", "html_report")
#: where calibrations are kept (per settings, device and machine)
CACHE = Path(".cache/tango-plan")
#: the rules that run torch (their --device)
TORCH_RULES = ("optimize", "bake", "relight", "metrics", "lod", "roundtrip")
#: the rules besides optimize and target, timed per job from earlier runs' benchmark files (under
#: results/: per cell, per mesh or per experiment), else from the reference table
CELL_RULES = ("bake", "export", "relight", "metrics", "lod", "roundtrip")
MESH_RULES = ("normalize", "decimate", "raycache")
BENCHMARK_GLOBS = {
    **{rule: f"*/*/*/*/benchmarks/{rule}.tsv" for rule in CELL_RULES},
    **{rule: f"meshes/*/*/benchmarks/{rule}.tsv" for rule in MESH_RULES},
    **{rule: f"*/report/benchmarks/{rule}.tsv" for rule in PER_EXPERIMENT},
}
#: seconds per job of each of those rules in a reference run, with its conditions
#: (benchmarks/workflow/stage_seconds.py writes it from a results folder)
STAGE_SECONDS = REPO / "benchmarks" / "figures" / "stage_seconds.json"
#: a calibration during which other processes used more than this share of the CPU is said to be
#: taken under load and not kept (``TANGO_PLAN_BUSY_SHARE`` overrides it; 1: never)
BUSY_SHARE = 0.25


def busy_share() -> float:
    return float(os.environ.get("TANGO_PLAN_BUSY_SHARE", BUSY_SHARE))


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
    add("all", 1)  # the workflow's target rule: Snakemake counts it as a job too
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
            m = read_json(meta)
        except StageInputError as exc:  # a received folder's FIFO, link or bad record: not a figure
            log.warning("an earlier run's record left out of the estimate: %s", exc)
            continue
        if not isinstance(m, dict):
            continue
        s = m.get("settings") if isinstance(m.get("settings"), dict) else {}
        seconds = positive_figure(m.get("seconds_per_iteration"))
        if seconds is None:
            continue
        if str(m.get("device", "")).split(":")[0] == device and _digest(s) == digest:
            found.append(seconds)
    return statistics.median(found) if found else None


def _digest(settings: dict) -> str:
    """The settings that set a step's cost (the seed aside)."""
    text = json.dumps({k: v for k, v in settings.items() if k != "seed"}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


class LoadMeter:
    """The share of the machine's CPU time that *other* processes used while the ``with`` block
    ran (Linux: the busy time of ``/proc/stat`` minus this process's own CPU time, over the wall
    time times the CPUs; None elsewhere): a calibration taken while another run used the cores
    measures that run, not this machine."""

    others_share: float | None = None

    @staticmethod
    def _busy() -> float | None:
        try:
            fields = [float(v) for v in read_text("/proc/stat").splitlines()[0].split()[1:]]
        except (OSError, StageInputError, ValueError, IndexError):
            return None
        idle = fields[3] + (fields[4] if len(fields) > 4 else 0.0)  # idle and iowait
        return (sum(fields[:8]) - idle) / os.sysconf("SC_CLK_TCK")

    @staticmethod
    def _own() -> float:
        t = os.times()
        return t.user + t.system

    def __enter__(self) -> LoadMeter:
        self.t0, self.busy0, self.own0 = time.perf_counter(), self._busy(), self._own()
        return self

    def __exit__(self, *exc) -> None:
        busy = self._busy()
        wall = time.perf_counter() - self.t0
        if busy is None or self.busy0 is None or wall <= 0:
            return
        others = (busy - self.busy0) - (self._own() - self.own0)
        self.others_share = min(1.0, max(0.0, others / (wall * (os.cpu_count() or 1))))

    def note(self) -> str:
        """How busy the machine was, for the source of a figure ("" when idle enough)."""
        if self.others_share is None or self.others_share <= busy_share():
            return ""
        return f"; taken while other processes used {self.others_share:.0%} of the CPU, so not kept: the estimate may be high"


def _cached_measure(cache: Path, key: str, name: str, measure, extra: dict) -> tuple[float, str]:
    """``measure()`` under a :class:`LoadMeter`, kept in ``cache/key.json`` unless the machine was
    busy; returns the figure and what to add to its source."""
    with LoadMeter() as load:
        value = measure()
    if not load.note():
        write_json_atomic(cache / f"{key}.json", {name: value, "others_share": load.others_share, **extra})
    return value, load.note()


@contextlib.contextmanager
def _on_threads(count: int):
    """This process on ``count`` CPU threads (torch's and :func:`~stages.core.threads.cpu_threads`,
    which Mitsuba's follow), as a job of that many threads runs, then as it was: a calibration
    and a probe measure at their job's threads."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        with threads_for(count):
            yield
    finally:
        torch.set_num_threads(before)


def step_seconds(
    settings, raycache, device: str, results: Path, cache: Path, calibrate: bool, threads: int
) -> tuple[float | None, str]:
    """Seconds per optimisation step of a job on ``threads`` threads and where the figure comes from."""
    digest = _digest(settings.to_dict())
    earlier = earlier_step_seconds(results, digest, device)
    if earlier is not None:
        return earlier, "an earlier run of these settings"
    with _on_threads(threads):
        return _calibrated_step(settings, raycache, device, digest, cache, calibrate)


def _calibrated_step(settings, raycache, device: str, digest: str, cache: Path, calibrate: bool) -> tuple[float | None, str]:
    """:func:`step_seconds` from the cache or a calibration (on the threads the caller set)."""
    key = hashlib.sha256(f"{digest}|{_digest(dataclasses.asdict(raycache))}|{device}|{_machine()}".encode()).hexdigest()[:16]
    cached = cache / f"{key}.json"
    if (seconds := _cached(cached, "seconds_per_step")) is not None:
        return seconds, "a calibration of these settings (cached)"
    if not calibrate:
        return None, "not calibrated (--no-calibrate)"
    extra = {"settings": settings.to_dict(), "device": device}
    seconds, note = _cached_measure(cache, key, "seconds_per_step", lambda: seconds_per_step(settings, raycache, device), extra)
    return seconds, "a calibration of these settings (a few real steps" + note + ")"


def mitsuba_rate(target, cache: Path, calibrate: bool, threads: int) -> tuple[float | None, str]:
    """Mitsuba's samples per second for target ``settings`` on this machine on ``threads`` threads
    (the doctor's probe: the target scene on a small sphere, :func:`stages.reference.targets.probe`),
    cached per settings, variant, machine and threads; and where the figure comes from."""
    with _on_threads(threads):
        return _probed_rate(target, cache, calibrate)


def _probed_rate(target, cache: Path, calibrate: bool) -> tuple[float | None, str]:
    """:func:`mitsuba_rate` from this process's probes, the cache or a probe (on the caller's threads)."""
    variant = choose_variant(target.variant)
    key = hashlib.sha256(f"mitsuba|{_digest(target.to_dict())}|{variant}|{_machine()}".encode()).hexdigest()[:16]
    cached = cache / f"{key}.json"
    if key in _MEASURED:
        return _MEASURED[key]
    if (rate := _cached(cached, "samples_per_second")) is not None:
        return rate, f"a probe render in {variant} (cached)"
    if not calibrate:
        return None, "not probed (--no-calibrate)"
    rate, note = _cached_measure(cache, key, "samples_per_second", lambda: probe(target).samples_per_second, {"variant": variant})
    _MEASURED[key] = rate, f"a probe render in {variant}" + note
    return _MEASURED[key]


#: this process's probe rates (one probe per settings, even when a busy machine kept none)
_MEASURED: dict[str, tuple[float, str]] = {}


def _machine() -> str:
    import os
    import platform

    import torch

    cpu = platform.processor() or platform.machine()
    return f"{cpu}|{os.cpu_count()}|{torch.__version__}|{torch.get_num_threads()}|{cpu_threads()}"


def positive_figure(value) -> float | None:
    """``value`` as a positive finite float, or None where a received record holds something
    else there (a text, a bool, NaN, an integer past float's range)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    try:
        value = float(value)
    except OverflowError:
        return None
    return value if math.isfinite(value) and value > 0 else None


def _cached(path: Path, name: str) -> float | None:
    """The figure ``name`` of a cached measurement, or None where there is none (or it is not a
    number: measured again)."""
    if not path.exists() and not path.is_symlink():
        return None
    try:
        return positive_figure(read_json(path).get(name))
    except (StageInputError, AttributeError) as exc:
        log.warning("a cached measurement not used: %s", exc)
        return None


def benchmark_seconds(tsv: Path) -> float | None:
    """The wall seconds a Snakemake ``benchmark:`` file records (its first column), or None."""
    try:
        lines = read_text(tsv).splitlines()
        return float(lines[1].split("\t")[0]) if len(lines) >= 2 else None
    except (StageInputError, ValueError) as exc:
        log.warning("a benchmark file left out of the estimate: %s", exc)
        return None


def other_stage_seconds(results: Path) -> tuple[dict[str, float], str]:
    """Seconds per job of each rule besides optimize and target: the median of earlier runs'
    benchmark files under ``results`` (Snakemake's ``benchmark:``) for the rules that have any, the
    reference table's (:data:`STAGE_SECONDS`) for the others; and where the figures come from."""
    out = {}
    for rule, pattern in BENCHMARK_GLOBS.items():
        times = [t for tsv in Path(results).glob(pattern) if (t := benchmark_seconds(tsv)) is not None]
        if times:
            out[rule] = statistics.median(times)
    sources = [f"medians of earlier runs' benchmark files ({', '.join(out)})"] if out else []
    if STAGE_SECONDS.is_file():
        table = read_json(STAGE_SECONDS)
        rest = {r: s for r, s in table["seconds_per_job"].items() if r not in out}
        if rest:
            out.update(rest)
            sources.append(
                f"the reference table for the rest ({table['conditions']})"
                if sources
                else f"the reference table ({table['conditions']})"
            )
    return out, "; ".join(sources) or "no earlier runs"


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
    cores: int | None = None,
) -> dict:
    """Everything the plan says, as data. ``pending``: the jobs Snakemake will run, as (rule,
    wildcards) (the workflow passes its DAG's); without it, a cell's optimisation counts as done
    when its ``optimize/meta.json`` exists. ``cores``: the run's (Snakemake's ``--cores``; default
    the CPUs this process may use), over which the total spreads the jobs' CPU time
    (:func:`wall_seconds`)."""
    device = torch_device(cfg)
    cores = cores or cpu_threads()
    todo, pending_jobs = _todo(cfg, experiment, results, pending)
    groups = _groups(cfg, todo)
    estimates = [_estimate_row(cfg, entry, device, results, cache, calibrate, cores) for entry in groups.values()]
    timed = all(e["seconds_per_step"] is not None for e in estimates)
    to_run = pending_jobs if pending_jobs is not None else remaining_jobs(cfg, todo)
    targets = target_estimate(cfg, pending, todo, cache, calibrate, cores)
    others, others_source = other_stage_seconds(results)
    other_rules = [r for r in to_run if r not in ("optimize", "target", "all")]
    missing = [r for r in other_rules if r not in others]
    known = timed and targets["seconds"] is not None and not missing
    plan = {
        "experiment": experiment,
        "source": cfg.source,
        "grid": cfg.grid_text(),
        "meshes": len(cfg.grid_meshes),
        "prompts": len({c.prompt for c in cfg.cells}),
        "variants": len(cfg.variants),
        "cells": len(cfg.cells),
        "optimisations_done": len(cfg.cells) - len(todo),
        "jobs": job_counts(cfg),
        "pending_jobs": pending_jobs,
        "device": device,
        "device_setting": cfg.device,
        "optimisation": estimates,
        "optimisation_seconds": sum(e.get("seconds", 0.0) for e in estimates) if timed else None,
        "targets": targets,
        "other_stage_seconds": {r: others[r] for r in others},
        "other_source": others_source,
        "other_jobs": {r: to_run[r] for r in other_rules},
        "other_seconds": sum(others[r] * to_run[r] for r in other_rules if r in others),
        "other_missing": missing,
        "cores": cores,
    }
    plan["total_seconds"] = _total(cfg, plan) if known else None
    if device == "cpu" and any(e["paper"] for e in estimates):
        plan["paper_on_cpu"] = faster_presets(groups, cfg, device, results, cache, calibrate, cores)
    return plan


def _todo(cfg: WorkflowConfig, experiment: str, results: Path, pending) -> tuple[list, dict | None]:
    """The cells whose optimisation is still to run, and the pending jobs per rule (None without
    Snakemake's DAG: a cell counts as done when its ``optimize/meta.json`` exists)."""
    if pending is None:
        cell_dir = results / experiment
        return [c for c in cfg.cells if not (cell_dir / c.mesh / c.prompt / c.variant / "optimize" / "meta.json").is_file()], None
    running = {(w.get("mesh"), w.get("prompt"), w.get("variant")) for rule, w in pending if rule == "optimize"}
    counts: dict[str, int] = {}
    for rule, _ in pending:
        counts[rule] = counts.get(rule, 0) + 1
    return [c for c in cfg.cells if (c.mesh, c.prompt, c.variant) in running], counts


def _groups(cfg: WorkflowConfig, todo: list) -> dict[str, dict]:
    """The cells to optimise grouped by their settings (one calibration each), with a mesh of
    theirs, their job's threads and their count."""
    groups: dict[str, dict] = {}
    for c in todo:
        s = cfg.optimize_settings(c.prompt, c.variant)
        threads = cfg.optimize_threads(c.prompt, c.variant)
        entry = groups.setdefault(_digest(s.to_dict()), {"settings": s, "mesh": c.mesh, "threads": threads, "cells": 0})
        entry["cells"] += 1
    return groups


def _estimate_row(cfg: WorkflowConfig, entry: dict, device: str, results: Path, cache: Path, calibrate: bool, cores: int) -> dict:
    """The plan's row of one group of optimisations: its seconds per step (on its job's threads)
    and in all, where they come from, its guide, precision, suns and bounces."""
    s = entry["settings"]
    raycache = cfg.stage_settings(entry["mesh"], "raycache")
    sec, source = step_seconds(s, raycache, device, results, cache, calibrate, min(entry["threads"], cores))
    row = {
        "cells": entry["cells"],
        "threads": entry["threads"],
        "iterations": s.iterations,
        "seconds_per_step": sec,
        "source": source,
        "paper": is_paper(s),
        "clip_model": s.guidance_mode().plan_label(s),  # what guides it
        "precision": precision_summary(s.bf16, s.bf16_networks, resolve_device(device)),
    }
    if s.suns != 0:  # how many suns, decided as the run will decide it (on the known environment)
        row["suns"] = planned_suns(cfg, entry["mesh"], s)
    if s.bounces != 0:  # decided by the optimisation, on the training views' shadows
        row["bounces"] = {"setting": s.bounces, "every": s.bounce_every, "samples": s.bounce_samples}
    if sec is not None:
        row["seconds"] = sec * s.iterations * entry["cells"]
    return row


def _total(cfg: WorkflowConfig, plan: dict) -> float:
    """The plan's wall time: every job's seconds, threads and count (:func:`wall_seconds` over the
    run's cores); on a GPU run never less than the torch jobs one after another (they share the
    GPU, one at a time under the workflow's profile)."""
    work = [("optimize", row["seconds"] / row["cells"], row["threads"], row["cells"]) for row in plan["optimisation"]]
    t = plan["targets"]
    if t["jobs"]:
        work.append(("target", t["seconds"] / t["jobs"], cfg.job_threads("target"), t["jobs"]))
    per_job = plan["other_stage_seconds"]
    work += [(r, per_job[r], cfg.job_threads(r), n) for r, n in plan["other_jobs"].items()]
    spread = wall_seconds([w[1:] for w in work], plan["cores"])
    if cfg.gpu_jobs():
        return max(spread, sum(seconds * n for rule, seconds, _, n in work if rule in TORCH_RULES))
    return spread


def wall_seconds(work: list[tuple[float, int, int]], cores: int) -> float:
    """The wall time of jobs ``(seconds per job, threads, jobs)`` on ``cores``: their CPU time
    (seconds times threads, at most ``cores`` each) spread over the cores, as Snakemake runs jobs
    side by side where their threads fit; never less than the longest job (one job does not
    split)."""
    spread = sum(seconds * min(threads, cores) * jobs for seconds, threads, jobs in work) / cores
    return max([spread, *(seconds for seconds, _, _ in work)])


def planned_suns(cfg: WorkflowConfig, mesh: str, s) -> dict:
    """``optimize.suns`` as the run will resolve it (:func:`~stages.model.lights.sun.resolve_suns`):
    on the fixed light's map, or the image targets' environment (``target.environment``), with
    the mesh's stored visibility directions."""
    environment = s.light_map if s.light == "fixed" else None
    if environment is None and s.mitsuba_targets():
        environment = cfg.stage_settings(mesh, "target").environment
    raycache = cfg.stage_settings(mesh, "raycache")
    directions = raycache.visibility_directions if raycache.visibility != "off" and s.shadows else 0
    return resolve_suns(s.suns, environment, directions, s.suns_share)[1]


def bounces_text(record: dict) -> str:
    """The plan's line of a group's bounce (``optimize.bounces``): what is modelled, or how auto decides."""
    what = f"one bounce of the mesh's own light, refreshed every {record['every']} steps, {record['samples']} hits per point"
    if record["setting"] == "auto":
        return f"bounces: auto (at the optimisation: {what} where the training hits' median blocked share is high enough)"
    return f"bounces: {record['setting']} ({what})"


def suns_text(record: dict) -> str:
    """The plan's line of a group's suns (:func:`planned_suns`)."""
    if record["setting"] != "auto":
        return f"suns: {record['suns']}"
    if "why" in record:
        return f"suns: auto -> 0 ({record['why']})"
    found = record["candidates"][: record["suns"]]
    figures = "; ".join(f"{c['share']:.0%} of its energy within {c['radius_deg']:.2f} degrees" for c in found)
    return f"suns: auto -> {record['suns']} on {record['environment']}" + (
        f" ({figures})" if figures else " (no region held enough)"
    )


def remaining_jobs(cfg: WorkflowConfig, todo: list) -> dict[str, int]:
    """Without Snakemake's DAG: the jobs of the cells still to optimise (their meshes' work and
    targets counted as not done; the per-experiment rules once when any cell is left)."""
    if not todo:
        return {}
    meshes = {c.mesh for c in todo}
    counts = {"normalize": len(meshes), "decimate": sum(cfg.decimated(m) for m in meshes), "raycache": len(meshes)}
    counts["target"] = len({(c.mesh, m) for c in todo if (m := cfg.target_material(c.prompt, c.variant))})
    counts["optimize"] = len(todo)
    for rule in PER_CELL:
        counts[rule] = len(todo)
    for rule in ("roundtrip", "lod"):
        counts[rule] = sum(cfg.cell_stage_settings(rule, c.prompt, c.variant).enabled for c in todo)
    counts.update({rule: 1 for rule in PER_EXPERIMENT})
    return {r: n for r, n in counts.items() if n}


def target_estimate(cfg: WorkflowConfig, pending, todo: list, cache: Path, calibrate: bool, cores: int) -> dict:
    """The Mitsuba target jobs still to run: their samples (training views, metric views and the
    relit truths: :func:`stages.reference.targets.target_samples`) and seconds at the rate a probe
    render measures here (per target settings)."""

    if pending is not None:
        jobs = sorted({(w.get("mesh"), w.get("material")) for rule, w in pending if rule == "target"})
    else:
        jobs = cfg.target_jobs({c.mesh for c in todo})
    out = {"jobs": len(jobs), "samples": {"training": 0, "metric": 0, "relit": 0}, "seconds": 0.0 if not jobs else None}
    if not jobs:
        return out
    seconds, sources = 0.0, set()
    for mesh, _ in jobs:
        target = cfg.stage_settings(mesh, "target")
        samples = target_samples(cfg.stage_settings(mesh, "raycache"), target)
        for kind, n in samples.items():
            out["samples"][kind] += n
        rate, source = mitsuba_rate(target, cache, calibrate, min(cfg.job_threads("target"), cores))
        sources.add(source)
        seconds = None if rate is None or seconds is None else seconds + sum(samples.values()) / rate
        if rate is not None:
            out["samples_per_second"] = rate
    out.update(seconds=seconds, source="; ".join(sorted(sources)))
    return out


def faster_presets(groups, cfg, device, results, cache, calibrate, cores: int) -> list[dict]:
    """The speed presets applied to the paper-setting cells: their time here and their measured
    quality cost against the paper's settings (``benchmarks/figures/preset_costs.json``)."""
    costs = read_json(PRESET_COSTS) if PRESET_COSTS.is_file() else {}
    paper = [e for e in groups.values() if is_paper(e["settings"])]
    cells = sum(e["cells"] for e in paper)
    out = []
    for name in ("balanced", "fast"):
        seconds = 0.0
        for e in paper:
            preset = {k: tuple(v) if isinstance(v, list) else v for k, v in PRESETS[name].items()}
            s = dataclasses.replace(e["settings"], **preset)
            raycache = cfg.stage_settings(e["mesh"], "raycache")
            sec, _ = step_seconds(s, raycache, device, results, cache, calibrate, min(e["threads"], cores))
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


def _pending(pending: dict[str, int], jobs: dict[str, int]) -> str:
    """The jobs still to run, said against the experiment's (their rules only where some are done)."""
    n = sum(pending.values())
    if pending == jobs:
        return ", all of them to run now"
    return f", {n} of them to run now ({', '.join(f'{r} {k}' for r, k in pending.items())})"


def duration(seconds: float | None) -> str:
    if seconds is None:
        return "not estimated"
    minutes = round(seconds / 60)
    if minutes < 1:
        return f"{seconds:.0f} s"
    return f"{minutes // 60} h {minutes % 60:02d} min" if minutes >= 60 else f"{minutes} min"


def estimate_text(plan: dict) -> str:
    """The wall-time line of the plan: the total and its three parts, each with its source."""
    t, opt = plan["targets"], plan["optimisation_seconds"]
    total = plan["total_seconds"]
    head = f"about {duration(total)} in all" if total is not None else "not estimated in all"
    parts = [f"optimisation {duration(opt)}"]
    if t["jobs"]:
        samples = sum(t["samples"].values())
        rate = t.get("samples_per_second")
        at = f" at {rate / 1e6:.2f} M samples/s from {t['source']}" if rate else f" ({t['source']})"
        parts.append(
            f"Mitsuba's targets {duration(t['seconds'])} ({t['jobs']} job(s), {samples / 1e6:,.0f} M samples, "
            f"{t['samples']['relit'] / 1e6:,.0f} M of them the relit truths{at})"
        )
    if plan["other_jobs"]:
        jobs = sum(plan["other_jobs"].values())
        said = f"the other stages {duration(plan['other_seconds'])} ({jobs} jobs, per job from {plan['other_source']})"
        if plan["other_missing"]:
            said += f"; not estimated: {', '.join(plan['other_missing'])}"
        parts.append(said)
    where = f"on this machine, on {plan['cores']} cores (jobs side by side as their threads allow)"
    return f"Estimated wall time {where}: {head}: {'; '.join(parts)}. An estimate, not a promise."


def plan_text(plan: dict) -> str:
    jobs = plan["jobs"]
    lines = [
        f"Plan of experiment {plan['experiment']} ({plan['source']}): {plan['grid']}; {_jobs(jobs)}"
        + (_pending(plan["pending_jobs"], jobs) if plan.get("pending_jobs") is not None else "")
        + f"; {plan['optimisations_done']} of {plan['cells']} optimisations already done.",
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
        if "suns" in e:
            lines.append(f"    {suns_text(e['suns'])}")
        if "bounces" in e:
            lines.append(f"    {bounces_text(e['bounces'])}")
    if not plan["optimisation"]:
        lines.append("No optimisation to run.")
        return "\n".join(lines) + "\n"
    lines.append(estimate_text(plan))
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
        add_configfile(parser)
        parser.add_argument("--results", type=Path, default=Path("results"))
        parser.add_argument("--no-calibrate", action="store_true", help="no calibration run (estimate from earlier runs only)")
        parser.add_argument("--cache", type=Path, default=CACHE, help="where calibrations are kept")
        parser.add_argument("--json", action="store_true")
        parser.add_argument(
            "--cores", type=int, default=None, help="the cores of the run to estimate (default: the CPUs this process may use)"
        )

    def body(args):
        cfg = load_config_files(args.configfile)
        if args.cores is not None and args.cores < 1:
            raise StageInputError(Path("--cores"), f"must be at least 1, got {args.cores}", "Pass the cores the run will use.")
        name = experiment_name(cfg.raw, args.configfile)
        plan = make_plan(cfg, name, args.results, not args.no_calibrate, args.cache, cores=args.cores)
        if args.json:
            sys.stdout.write(json.dumps(plan, indent=1, default=str) + "\n")
        else:
            sys.stdout.write(plan_text(plan))

    return stage_main("plan", __doc__, arguments, body, argv)


if __name__ == "__main__":
    raise SystemExit(main())
