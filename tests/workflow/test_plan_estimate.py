"""The plan's and the doctor's wall-time estimate counts every job a run makes: Mitsuba's targets
by the samples they render (the training views, the metric views and the relit truths under every
``target.relight_environments`` entry), the optimisations by calibrated steps, every other rule
per job; and a calibration taken while other processes use the CPU says so and is not kept.

(How close the estimate comes to a real run is measured, not asserted here: the suite's parallel
workers share the CPU with any run a test would time; ``benchmarks/workflow/plan_accuracy.py``.)"""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest
from conftest import REPO

from stages import plan as plan_mod
from stages.config.sections import OptimizeSettings, RaycacheSettings
from stages.config.workflow import load_config_files
from stages.doctor import target_samples

DEMO = REPO / "config" / "demo.yaml"
THREE = REPO / "config" / "demo-offline.yaml"


def test_target_samples_count_the_relit_truths():
    """Written out from the config files' numbers: 32 training views of 128^2 pixels at 16 spp, and
    8 x 3 metric views of 224^2 pixels (the metric views' default size) at metric_spp, rendered once
    under the training light and once more per relight environment (two in the three-cell demo,
    one in the first demo)."""
    three = load_config_files([THREE])
    assert target_samples(three, "vase") == 32 * 128**2 * 16 + 24 * 224**2 * 128 * (1 + 2)
    demo = load_config_files([DEMO])
    assert target_samples(demo, "candle") == 32 * 128**2 * 16 + 24 * 224**2 * 64 * (1 + 1)


@pytest.mark.slow(minutes=0.5)
def test_the_estimate_counts_every_rule_to_run(tmp_path):
    """The first demo in an empty results folder: the targets' samples are the two target jobs',
    every rule Snakemake would run besides optimize and target has a figure per job (the reference
    table's, as no earlier run exists), and the total is the jobs' CPU time over the run's cores
    (on one core, the sum of the three parts)."""
    cfg = load_config_files([DEMO])
    env_cache = tmp_path / "cache"
    p = plan_mod.make_plan(cfg, "demo", tmp_path / "results", True, env_cache, cores=2)
    t = p["targets"]
    assert t["jobs"] == 2 and t["samples"]["relit"] == 2 * 24 * 224**2 * 64
    assert sum(t["samples"].values()) == sum(target_samples(cfg, m) for m, _ in cfg.target_jobs())
    counts = plan_mod.job_counts(cfg)
    assert p["other_jobs"] == {r: n for r, n in counts.items() if r not in ("optimize", "target", "all")}
    assert p["other_missing"] == [] and p["other_source"].startswith("the reference table (")
    table = p["other_stage_seconds"]
    others = sum(table[r] * n for r, n in p["other_jobs"].items())
    assert p["other_seconds"] == pytest.approx(others)
    # the demo's optimisations take one thread each, its targets two: on two cores the jobs' CPU
    # time over the two cores
    assert [row["threads"] for row in p["optimisation"]] == [1, 1] and p["cores"] == 2
    cpu = (
        p["optimisation_seconds"]
        + 2 * t["seconds"]
        + sum(table[r] * n * (2 if r == "raycache" else 1) for r, n in p["other_jobs"].items())
    )
    assert p["total_seconds"] == pytest.approx(cpu / 2)
    text = plan_mod.plan_text(p)
    assert "of them the relit truths" in text and "Estimated wall time on this machine, on 2 cores (jobs" in text
    one = plan_mod.make_plan(cfg, "demo", tmp_path / "results", True, env_cache, cores=1)
    # one core: one job at a time, the sum of the parts (a calibration under load is measured again)
    assert one["total_seconds"] == pytest.approx(one["optimisation_seconds"] + one["targets"]["seconds"] + one["other_seconds"])


def test_the_wall_time_spreads_the_jobs_cpu_time_over_the_cores():
    """Jobs side by side: two one-thread jobs of 10 s and a two-thread one of 5 s take 15 s on two
    cores and 25 s on one (the two-thread job on one thread); one job never splits."""
    jobs = [(10.0, 1, 2), (5.0, 2, 1)]
    assert plan_mod.wall_seconds(jobs, 2) == pytest.approx(15.0)
    assert plan_mod.wall_seconds(jobs, 1) == pytest.approx(25.0)
    assert plan_mod.wall_seconds(jobs, 8) == pytest.approx(10.0)
    assert plan_mod.wall_seconds([(100.0, 1, 1), (1.0, 1, 4)], 2) == pytest.approx(100.0)


@pytest.mark.slow(minutes=0.5)
def test_a_calibration_under_load_is_said_and_not_kept(tmp_path, monkeypatch):
    """Two processes spinning on the CPU while the plan calibrates a step: the figure's source says
    what share of the CPU others used, and nothing is cached (the next plan measures again)."""
    monkeypatch.delenv("TANGO_PLAN_BUSY_SHARE", raising=False)
    spinners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]
    try:
        time.sleep(0.5)
        settings = OptimizeSettings(
            clip_tiny_test=True, image_size=64, width=16, crops=0, light_lobes=4, material_frequencies=2, eval_width=16
        )
        seconds, source = plan_mod.step_seconds(
            settings, RaycacheSettings(views=4, resolution=32), "cpu", tmp_path / "results", tmp_path / "cache", True, 2
        )
    finally:
        for proc in spinners:
            proc.kill()
    assert seconds > 0
    assert "taken while other processes used" in source and "so not kept" in source, source
    assert not list((tmp_path / "cache").glob("*.json"))


def test_the_load_meter_counts_other_processes():
    """A child spinning for a second while this process waits is at least 0.3 CPUs of others' load
    (Linux; other processes on the machine can only add to it)."""
    with plan_mod.LoadMeter() as other:
        child = subprocess.Popen([sys.executable, "-c", "import time; t=time.time()\nwhile time.time()-t<1.0: pass"])
        child.wait()
    if other.others_share is None:
        pytest.skip("no /proc/stat here")
    assert other.others_share * (os.cpu_count() or 1) > 0.3, other.others_share


def test_the_plan_says_how_many_suns_each_optimisation_gets(tmp_path):
    """``optimize.suns: auto`` on the first demo (image targets under ``builtin:sun_sky``): the plan
    decides as the run will, on the targets' environment, and says the sun's share and size; under
    ``target.environment: builtin:sunset`` it finds none; a count is said as it is. No calibration
    (the step's time is not what this checks)."""
    import yaml

    base = yaml.safe_load(DEMO.read_text())
    for environment, needle in (
        ("builtin:sun_sky", "suns: auto -> 1 on builtin:sun_sky (63% of its energy within 1.56 degrees)"),
        ("builtin:sunset", "suns: auto -> 0 on builtin:sunset (no region held enough)"),
        (None, "suns: 2"),
    ):
        cfg_dict = dict(base, optimize={**base["optimize"], "suns": "auto" if environment else 2})
        if environment:
            cfg_dict["target"] = {**base["target"], "environment": environment}
        path = tmp_path / "suns.yaml"
        path.write_text(yaml.safe_dump(cfg_dict))
        p = plan_mod.make_plan(load_config_files([path]), "suns", tmp_path / "results", False, tmp_path / "cache")
        assert needle in plan_mod.plan_text(p), plan_mod.plan_text(p)


def test_the_plan_says_what_bounce_each_optimisation_models(tmp_path):
    """``optimize.bounces``: a 1 is said with its refresh and hits; ``auto`` says that the
    optimisation decides it; 0 says nothing."""
    import yaml

    base = yaml.safe_load(DEMO.read_text())
    for setting, needle in (
        (1, "bounces: 1 (one bounce of the mesh's own light, refreshed every 25 steps, 16 hits per point)"),
        ("auto", "bounces: auto (at the optimisation:"),
        (0, None),
    ):
        path = tmp_path / "bounces.yaml"
        path.write_text(yaml.safe_dump(dict(base, optimize={**base["optimize"], "bounces": setting})))
        text = plan_mod.plan_text(plan_mod.make_plan(load_config_files([path]), "b", tmp_path / "results", False, tmp_path / "c"))
        assert (needle in text) if needle else ("bounces:" not in text), text


@pytest.mark.slow(minutes=0.5)
def test_on_a_gpu_the_torch_jobs_take_their_turns(tmp_path, monkeypatch):
    """On a GPU run the torch jobs share the GPU one at a time (the workflow profile's gpu=1): the
    total is never less than their seconds one after another, however many cores."""
    cfg = load_config_files([DEMO])
    monkeypatch.setattr(type(cfg), "gpu_jobs", lambda self: 1)
    p = plan_mod.make_plan(cfg, "demo", tmp_path / "results", False, tmp_path / "cache", cores=64)
    p["optimisation"] = [dict(row, seconds=100.0) for row in p["optimisation"]]
    p["targets"]["seconds"] = 10.0
    torch_jobs = 2 * 100.0 + sum(p["other_stage_seconds"][r] * n for r, n in p["other_jobs"].items() if r in plan_mod.TORCH_RULES)
    assert [row["threads"] for row in p["optimisation"]] == [2, 2]  # a GPU job's threads
    assert plan_mod._total(cfg, p) == pytest.approx(torch_jobs)


def test_the_cores_must_be_positive(capsys):
    assert plan_mod.main(["--cores", "0", "--no-calibrate"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--cores" in err[0] and "at least 1" in err[0], err


def test_a_calibration_and_a_probe_run_on_their_jobs_threads(tmp_path, monkeypatch):
    """The plan times a step and probes Mitsuba on the threads their job will have (torch's and
    the tracer's, which Mitsuba's follow), keyed by them, and leaves the process as it was."""
    import torch

    from stages.core.threads import cpu_threads

    seen = []

    def spy(*args):
        seen.append((torch.get_num_threads(), cpu_threads(), plan_mod._machine()))
        return 0.25

    monkeypatch.setattr(plan_mod, "seconds_per_step", spy)
    monkeypatch.setenv("TANGO_PLAN_BUSY_SHARE", "1")  # kept however busy the test machine is
    before = torch.get_num_threads(), cpu_threads()
    settings, raycache = OptimizeSettings(clip_tiny_test=True), RaycacheSettings(views=4, resolution=32)
    for threads in (1, 3):
        seconds, _ = plan_mod.step_seconds(settings, raycache, "cpu", tmp_path / "r", tmp_path / "c", True, threads)
        assert seconds == 0.25
    assert [s[:2] for s in seen] == [(1, 1), (3, 3)] and seen[0][2] != seen[1][2]  # each its own cache key
    assert (torch.get_num_threads(), cpu_threads()) == before
    assert len(list((tmp_path / "c").glob("*.json"))) == 2
