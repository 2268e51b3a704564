"""Real kills: SIGKILL to a running Snakemake and its job (as a crashed node or the OOM killer
would), then a rerun with --rerun-incomplete. The optimisation resumes from its checkpoint and
ends with parameters bit-identical to an uninterrupted run; a bake killed while writing leaves no
output that looks finished and reruns to the same files."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pytest
import torch
import yaml
from conftest import REPO, run_snakemake, snakemake_command, snakemake_env

CELL = Path("results/kill/vase/wood/base")
CONFIG = {
    "experiment": "kill",
    "meshes": {"vase": {"builtin": "vase"}},
    "prompts": {"wood": "a {object} made of wood"},
    "raycache": {
        "views": 4,
        "resolution": 48,
        "eval_azimuths": 4,
        "eval_elevations_deg": [0.0, 30.0],
        "eval_resolution": 32,
        # (the metric views' cache is made with the others: at its default 24 views of 224 pixels its
        # shadows' visibility took 28 s of each run; this test runs no metrics)
        "metrics_azimuths": 2,
        "metrics_elevations_deg": [0.0],
        "metrics_resolution": 32,
    },
    "optimize": {
        "iterations": 80,
        "milestones": [40],
        "clip_tiny_test": True,
        "image_size": 64,
        "width": 16,
        "crops": 1,
        "light_lobes": 4,
        "checkpoint_every": 10,
        "eval_width": 32,
    },
    "bake": {"texture_size": 256, "eval_width": 64, "light_width": 64, "occlusion_samples": 8192},
    "metrics": {"clip": False},
}


def declared_outputs(stage: str) -> list[Path]:
    """The files a rule declares, relative to the working directory (from the rule helpers'
    own definitions, so the test follows the Snakefile)."""
    from stages.config.layout import OPTIMIZE_FILES, TEXTURES

    if stage == "optimize":
        return [CELL / "optimize" / name for name in OPTIMIZE_FILES.values()] + [CELL / "optimize" / "meta.json"]
    names = [f"textures/{k}.png" for k in TEXTURES] + ["light.exr", "light.hdr", "atlas.npz", "preview.png", "meta.json"]
    return [CELL / "bake" / n for n in names]


def kill_when(workdir: Path, config: Path, target: Path, ready) -> None:
    """Start Snakemake for ``target`` in its own session; SIGKILL the whole session (Snakemake,
    the job's shell and the stage) as soon as ``ready()`` is true."""
    proc = subprocess.Popen(
        # the target before --configfile, which takes a list
        snakemake_command(workdir, str(target), "--cores", "1", "--configfile", str(config)),
        cwd=REPO,
        env=snakemake_env(workdir),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    deadline = time.monotonic() + 600
    try:
        while not ready():
            if proc.poll() is not None:
                pytest.fail(f"the workflow ended (exit {proc.returncode}) before the moment to kill it")
            if time.monotonic() > deadline:
                pytest.fail("timed out waiting for the moment to kill the workflow")
            time.sleep(0.002)
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=60)


def rerun(workdir: Path, config: Path, target: Path) -> subprocess.CompletedProcess:
    unlock = run_snakemake(workdir, "--cores", "1", "--configfile", str(config), "--unlock")
    assert unlock.returncode == 0, unlock.stderr[-2000:]
    proc = run_snakemake(workdir, str(target), "--cores", "1", "--rerun-incomplete", "--configfile", str(config))
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    """The reference: the same cell run to its bake without interruption."""
    work = tmp_path_factory.mktemp("reference")
    config = work / "config.yaml"
    config.write_text(yaml.safe_dump(CONFIG))
    proc = run_snakemake(work, str(CELL / "bake" / "meta.json"), "--cores", "1", "--configfile", str(config))
    assert proc.returncode == 0, proc.stderr[-3000:]
    return work


@pytest.mark.slow(minutes=2.5)  # with the uninterrupted run it compares against
def test_sigkill_during_optimize_resumes_bit_identical(uninterrupted, tmp_path):
    config = tmp_path / "config.yaml"
    config.write_text(yaml.safe_dump(CONFIG))
    target = CELL / "optimize" / "meta.json"
    ckpt = tmp_path / CELL / "optimize" / "checkpoint.pt"
    kill_when(tmp_path, config, target, ckpt.is_file)
    # after the kill: a checkpoint to resume from, and nothing of the job that looks finished
    assert ckpt.is_file()
    left = [p for p in declared_outputs("optimize") if (tmp_path / p).exists()]
    assert left == [], f"a killed optimize left finished-looking outputs: {left}"
    rerun(tmp_path, config, target)
    meta = json.loads((tmp_path / target).read_text())
    assert meta["resumed_from_iteration"] is not None and 10 <= meta["resumed_from_iteration"] < 80
    assert "resumed from" in (tmp_path / CELL / "logs" / "optimize.log").read_text()
    assert not ckpt.exists()
    a = torch.load(uninterrupted / CELL / "optimize" / "field.pt", weights_only=True)["state_dict"]
    b = torch.load(tmp_path / CELL / "optimize" / "field.pt", weights_only=True)["state_dict"]
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), f"{key} differs after the resumed run"
    assert not list((tmp_path / "results").rglob(".staging-*"))


@pytest.mark.slow(minutes=2)
def test_sigkill_during_bake_write_leaves_nothing_finished(uninterrupted, tmp_path):
    # the uninterrupted run's work up to its optimisation (and Snakemake's records of it), copied
    # with its times: nothing but the bake is out of date here
    shutil.copytree(uninterrupted, tmp_path, symlinks=True, dirs_exist_ok=True)
    bake_dir = tmp_path / CELL / "bake"
    shutil.rmtree(bake_dir)
    config = tmp_path / "config.yaml"
    plan = run_snakemake(tmp_path, str(CELL / "bake" / "meta.json"), "--cores", "1", "--configfile", str(config), "-n")
    assert plan.returncode == 0 and "bake" in plan.stdout and "rule optimize" not in plan.stdout, plan.stdout[-3000:]

    def first_file_written() -> bool:
        # the moment the bake has written its first output file, wherever it puts it
        return bake_dir.is_dir() and any(p.suffix == ".png" and not p.name.startswith(".") for p in bake_dir.rglob("*"))

    target = CELL / "bake" / "meta.json"
    kill_when(tmp_path, config, target, first_file_written)
    left = [p for p in declared_outputs("bake") if (tmp_path / p).exists()]
    assert left == [], f"a bake killed mid-write left finished-looking outputs: {left}"
    rerun(tmp_path, config, target)
    for p in declared_outputs("bake"):
        if p.name == "meta.json":
            continue
        assert (tmp_path / p).read_bytes() == (uninterrupted / p).read_bytes(), f"{p} differs from the uninterrupted run"
    assert not list(bake_dir.rglob(".staging-*"))
