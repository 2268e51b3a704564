"""First contact: the doctor (what a run needs, and how to fix each missing piece), the plan (cells,
jobs, device and an estimate of the wall time, printed when the workflow starts), and the main
job's message without CLIP weights, followed to the letter."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import yaml
from conftest import REPO, job_counts, run_snakemake, snakemake_command, snakemake_env

SMOKE = REPO / "tests" / "smoke" / "config.yaml"
DEFAULT = REPO / "config" / "config.yaml"
IN_CI = bool(os.environ.get("CI"))


def offline_env(tmp_path: Path) -> dict[str, str]:
    """No hub and an empty Hugging Face cache: a fresh clone without internet."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env.update(HF_HUB_OFFLINE="1", HF_HOME=str(tmp_path / "hf"), HF_HUB_CACHE=str(tmp_path / "hf" / "hub"))
    return env


def module(name: str, *args: str, env=None, cwd=REPO) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", name, *args], capture_output=True, text=True, env=env, cwd=cwd, timeout=600)


def test_doctor_flags_both_missing_models_within_seconds(tmp_path):
    t0 = time.perf_counter()
    proc = module("stages.doctor", "--configfile", str(DEFAULT), "--json", env=offline_env(tmp_path))
    seconds = time.perf_counter() - t0
    assert proc.returncode == 1, proc.stderr[-2000:]
    assert seconds < 30, seconds
    checks = {c["name"]: c for c in json.loads(proc.stdout)}
    for name in ("torch and device", "Embree", "pymeshlab", "xatlas", "usd-core", "pygltflib"):
        assert checks[name]["ok"], checks[name]
    guidance, evaluation = checks["CLIP weights (guidance)"], checks["CLIP weights (evaluation)"]
    assert guidance["status"] == evaluation["status"] == "MISSING"
    assert "ViT-B-32 with the weights 'openai'" in guidance["detail"] and "optimize:" in guidance["fix"]
    assert "ViT-B-16 with the weights 'openai'" in evaluation["detail"] and "metrics: {clip: false}" in evaluation["fix"]
    assert "torch stages run on cpu" in checks["torch and device"]["detail"]
    # the optional pieces: said what they add; CI installs every one of them
    for name in ("Node.js and the report's viewer", "Mitsuba 3", "Blender", "Chromium", "Slurm"):
        assert not checks[name]["needed"], name
        if IN_CI and name != "Slurm":
            assert checks[name]["ok"], checks[name]
    text = module("stages.doctor", "--configfile", str(DEFAULT), env=offline_env(tmp_path)).stdout
    assert "2 needed piece(s) missing (CLIP weights (guidance), CLIP weights (evaluation))" in text


def test_doctor_passes_a_config_that_needs_no_weights(tmp_path):
    proc = module("stages.doctor", "--configfile", str(SMOKE), env=offline_env(tmp_path))
    assert proc.returncode == 0, proc.stdout + proc.stderr[-2000:]
    assert "Everything this config's run needs is here." in proc.stdout
    assert "CLIP weights" in proc.stdout and "needs no real CLIP weights" in proc.stdout


def test_plan_counts_jobs_like_snakemake_and_calibrates_once(tmp_path):
    # (the suite's other workers keep the CPU busy: a calibration taken under load is not kept,
    # which tests/workflow/test_plan_estimate.py tests; here it is kept whatever the load)
    env = {**offline_env(tmp_path), "TANGO_PLAN_BUSY_SHARE": "1"}
    args = ("--configfile", str(SMOKE), "--results", str(tmp_path / "results"), "--cache", str(tmp_path / "cache"), "--json")
    proc = module("stages.plan", *args, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    plan = json.loads(proc.stdout)
    dry = run_snakemake(tmp_path, "-n", "--cores", "2", "--configfile", str(SMOKE))
    counts = {r: n for r, n in job_counts(dry.stdout).items() if r != "total"}
    assert plan["jobs"] == counts
    cells = counts["optimize"]  # the smoke grid's
    assert plan["cells"] == cells == 8 and plan["optimisations_done"] == 0 and plan["device"] == "cpu"
    assert sum(e["cells"] for e in plan["optimisation"]) == cells
    for e in plan["optimisation"]:
        assert e["seconds_per_step"] > 0 and e["source"].startswith("a calibration")
        assert e["seconds"] == e["seconds_per_step"] * e["iterations"] * e["cells"]
    assert "paper_on_cpu" not in plan  # 3 iterations are not the paper's settings
    again = json.loads(module("stages.plan", *args, env=env).stdout)
    assert all(e["source"] == "a calibration of these settings (cached)" for e in again["optimisation"])


def test_plan_names_faster_presets_for_the_paper_on_a_cpu(tmp_path):
    args = ("--configfile", str(DEFAULT), "--no-calibrate", "--cache", str(tmp_path))
    proc = module("stages.plan", *args, env=offline_env(tmp_path))
    assert proc.returncode == 0, proc.stderr[-3000:]
    text = proc.stdout
    assert "3 meshes x 2 prompts x 1 variant = 6 cells" in text and "run on cpu" in text
    assert "6 of these optimisations run the paper's settings" in text and "balanced:" in text and "fast:" in text
    costs = json.loads((REPO / "benchmarks" / "figures" / "preset_costs.json").read_text())
    for preset in ("balanced", "fast"):
        for mesh, db in zip(costs["meshes"], costs["presets"][preset]["psnr_db"], strict=True):
            assert f"{mesh} {db:.1f} dB (paper " in text
    assert costs["conditions"] in text  # the conditions of the measurement travel with it


def test_main_job_offline_names_both_checkpoints_and_following_it_starts(tmp_path):
    """A fresh clone without internet: the main job stops before any job with one message per
    model; with both keys set as the messages say, it goes on (plan printed, jobs run)."""
    (tmp_path / "config").mkdir()
    (tmp_path / "config" / "config.yaml").write_text(DEFAULT.read_text())
    env = {**snakemake_env(tmp_path), **offline_env(tmp_path)}
    env["PATH"] = snakemake_env(tmp_path)["PATH"]
    t0 = time.perf_counter()
    proc = subprocess.run(
        snakemake_command(tmp_path, "--cores", "1"), cwd=REPO, env=env, capture_output=True, text=True, timeout=600
    )
    assert proc.returncode != 0 and time.perf_counter() - t0 < 60
    out = proc.stdout + proc.stderr
    assert "2 of the CLIP models this run needs cannot be loaded; nothing was run." in out
    assert out.index("The guidance CLIP") < out.index("The evaluation CLIP")
    assert "  optimize:\n    clip_checkpoint: /path/to/open_clip_pytorch_model.bin\n    clip_model: ViT-B-32-quickgelu" in out
    assert "  metrics:\n    clip_checkpoint: /path/to/open_clip_pytorch_model.bin\n    clip_model: ViT-B-16-quickgelu" in out
    assert not (tmp_path / "results").exists()
    # follow the messages: both checkpoints set (files standing in for the weights); the check passes
    for name in ("b32.bin", "b16.bin"):
        (tmp_path / name).write_bytes(b"weights")
    overlay = {
        "optimize": {"clip_checkpoint": str(tmp_path / "b32.bin"), "clip_model": "ViT-B-32-quickgelu"},
        "metrics": {"clip_checkpoint": str(tmp_path / "b16.bin"), "clip_model": "ViT-B-16-quickgelu"},
    }
    (tmp_path / "weights.yaml").write_text(yaml.safe_dump(overlay))
    env["TANGO_PLAN_CALIBRATE"] = "0"
    args = (
        "--cores",
        "1",
        "--until",
        "normalize",
        "--configfile",
        str(tmp_path / "config" / "config.yaml"),
        str(tmp_path / "weights.yaml"),
    )
    proc = subprocess.run(snakemake_command(tmp_path, *args), cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "cannot be loaded" not in proc.stderr
    assert "Plan of experiment main" in proc.stderr and "3 of them to run now (normalize 3)" in proc.stderr


def test_calibration_times_real_steps_of_a_random_architecture():
    """The calibration's path for real weights: the architecture with random weights (no download,
    marked test-only), a few real steps of these settings, a positive finite time."""
    import math

    from stages.config.sections import OptimizeSettings, RaycacheSettings
    from stages.guidance.clip import TINY_MODEL
    from stages.training.calibrate import random_guide, seconds_per_step

    settings = OptimizeSettings(clip_model=TINY_MODEL, image_size=64, width=16, crops=0, light_lobes=4, iterations=10)
    seconds = seconds_per_step(settings, RaycacheSettings(views=4, resolution=64), "cpu", steps=2)
    assert 0 < seconds < math.inf
    guide = random_guide(TINY_MODEL, False, settings.clip_tower, "cpu")
    assert guide.test_only and guide.weights_id == "calibration: random weights"


def test_calibration_times_the_eager_renderer_without_warnings_of_levers_it_leaves_off(caplog):
    """The calibration times the eager renderer (a compilation would be spent inside the plan):
    settings that ask for the compiled forms (the one graph, static shapes) are timed eager, without
    the warnings those levers give when asked for without a compiled renderer."""
    import logging
    import math

    from stages.config.sections import OptimizeSettings, RaycacheSettings
    from stages.guidance.clip import TINY_MODEL
    from stages.training.calibrate import seconds_per_step

    on = {"compile_shading": "on", "compile_networks": "on", "compile_static": "on"}
    settings = OptimizeSettings(clip_model=TINY_MODEL, image_size=64, width=16, crops=0, light_lobes=4, iterations=10, **on)
    with caplog.at_level(logging.WARNING, logger="stages"):
        assert 0 < seconds_per_step(settings, RaycacheSettings(views=4, resolution=64), "cpu", steps=1) < math.inf
    assert not [r.getMessage() for r in caplog.records if "compile_" in r.getMessage()]


def test_calibration_leaves_the_plans_process_allocator_as_it_is(monkeypatch):
    """The plan runs inside Snakemake's own process: its calibration must not make that process
    keep its memory for the whole workflow (keep_freed_memory), whatever the settings ask."""
    from stages.config.sections import OptimizeSettings, RaycacheSettings
    from stages.core import allocator
    from stages.guidance.clip import TINY_MODEL
    from stages.training.calibrate import seconds_per_step

    asked = []
    monkeypatch.setattr(allocator, "keep_freed_memory", lambda setting: asked.append(setting) or (False, "recorded"))
    monkeypatch.setattr("stages.training.optimizer.keep_freed_memory", allocator.keep_freed_memory)
    settings = OptimizeSettings(clip_model=TINY_MODEL, image_size=64, width=16, crops=0, light_lobes=4, iterations=10)
    assert settings.keep_freed_memory == "auto"
    seconds_per_step(settings, RaycacheSettings(views=4, resolution=64), "cpu", steps=1)
    assert asked == ["off"]


def test_calibration_times_a_bouncing_run_with_the_visibility_it_needs(monkeypatch):
    """A run of ``optimize.bounces: 1`` needs the ray cache's visibility: the calibration traces it
    on its vase and times the bouncing step (its table refreshed at the first step), where a cache
    without it would refuse the setting; so too with ``raycache.visibility: on`` (shadows for
    certain), while ``auto`` (each mesh decides) is timed without. With shadows off nothing can
    bounce, and the setting's own error says so."""
    import math

    import pytest

    from stages.config.sections import OptimizeSettings, RaycacheSettings
    from stages.guidance.clip import TINY_MODEL
    from stages.training import calibrate, optimizer
    from stages.training.calibrate import seconds_per_step

    refreshed, traced = [], []
    table, trace = optimizer.bounce_table, calibrate.trace_cache_visibility
    monkeypatch.setattr(optimizer, "bounce_table", lambda *a, **k: refreshed.append(1) or table(*a, **k))
    monkeypatch.setattr(calibrate, "trace_cache_visibility", lambda *a: traced.append(a[2]) or trace(*a))
    tiny = {"clip_model": TINY_MODEL, "image_size": 64, "width": 16, "crops": 0, "light_lobes": 4, "iterations": 10}
    raycache = RaycacheSettings(views=4, resolution=64, visibility_directions=64)
    assert 0 < seconds_per_step(OptimizeSettings(bounces=1, bounce_samples=4, **tiny), raycache, "cpu", steps=1) < math.inf
    assert refreshed and traced == [64]  # the bounce was modelled, on the visibility traced for it
    on = RaycacheSettings(views=4, resolution=64, visibility="on", visibility_directions=72)
    seconds_per_step(OptimizeSettings(**tiny), on, "cpu", steps=1)
    seconds_per_step(OptimizeSettings(**tiny), RaycacheSettings(views=4, resolution=64, visibility_directions=80), "cpu", steps=1)
    assert traced == [64, 72]  # on: traced; auto: not
    with pytest.raises(ValueError, match="bounces: 1 needs shadows"):
        seconds_per_step(OptimizeSettings(bounces=1, shadows=False, **tiny), raycache, "cpu", steps=1)
