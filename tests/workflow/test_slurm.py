"""The Slurm profile on a real Slurm: a one-node cluster started by scripts/slurm-cluster.sh
(slurmctld, slurmd, slurmdbd on MariaDB, munge; as root), the grid run through Snakemake's Slurm
executor with profiles/slurm. Every job must have gone through Slurm (its job id in Slurm's
accounting, completed) and the outputs must equal a local run's. A job killed by Slurm at its
time limit resumes from its checkpoint on the rerun. In CI the cluster must start; elsewhere the
tests skip when it cannot (not root, no packages)."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from conftest import REPO, mesh_work_dir, require_tool, run_snakemake, slurm_lock
from PIL import Image

pytestmark = [pytest.mark.slurm, pytest.mark.slow(minutes=5)]

SCRIPT = REPO / "scripts" / "slurm-cluster.sh"
PROFILE = REPO / "profiles" / "slurm"
CACHE = {
    "views": 4,
    "resolution": 48,
    "eval_azimuths": 4,
    "eval_elevations_deg": [0.0, 30.0],
    "eval_resolution": 32,
    "metrics_azimuths": 4,
    "metrics_elevations_deg": [0.0],
    "metrics_resolution": 64,
}
#: one mesh, one prompt, two variants: every per-mesh and per-cell rule, and the report
GRID = {
    "experiment": "grid",
    "device": "cpu",  # the same work on every host (a lent GPU machine would take CUDA for `auto`)
    "meshes": {"vase": {"builtin": "vase"}},
    "prompts": {"wood": "a {object} made of wood"},
    "variants": {"full": {}, "second": {"optimize": {"normal_network": False}}},
    "raycache": CACHE,
    "optimize": {
        "iterations": 3,
        "milestones": [2],
        "clip_tiny_test": True,
        "image_size": 64,
        "width": 16,
        "crops": 1,
        "light_lobes": 4,
        "checkpoint_every": 2,
        "eval_width": 32,
        # the killed-job test's run is thousands of iterations long, which compile_shading: auto
        # would compile (a minute on an empty cache): Slurm's one-minute limit killed it before its
        # first checkpoint; the calibration's 300 iterations run eager, and so must the run
        "compile_shading": "off",
    },
    "bake": {"texture_size": 64, "eval_width": 32, "light_width": 64},
    "relight": {"lobes": 4, "fit_iterations": 20, "width": 32},
    "metrics": {"clip_tiny_test": True},
}


def slurm_up() -> bool:
    return shutil.which("scontrol") is not None and subprocess.run(["scontrol", "ping"], capture_output=True).returncode == 0


@pytest.fixture(scope="module")
def cluster():
    """A running one-node cluster: started by the script (and stopped after) unless one was up;
    this module holds the machine's Slurm meanwhile (:func:`conftest.slurm_lock`: parallel test
    workers)."""
    with slurm_lock():
        yield from _cluster()


def _cluster():
    was_up = slurm_up()
    if not was_up:
        require_tool(os.geteuid() == 0, "the local Slurm cluster needs root (scripts/slurm-cluster.sh)")
        env = dict(os.environ, TANGO_SLURM_INSTALL="1" if os.environ.get("CI") else "0")
        proc = subprocess.run(["bash", str(SCRIPT), "start"], capture_output=True, text=True, timeout=900, env=env)
        require_tool(proc.returncode == 0, f"a local Slurm cluster could not be started: {proc.stderr[-2000:]}")
    yield
    if not was_up:
        subprocess.run(["bash", str(SCRIPT), "stop"], capture_output=True, timeout=300)


def slurm_run(workdir: Path, config: Path, *args: str, timeout: int = 1200) -> subprocess.CompletedProcess:
    """The workflow through the Slurm profile, polling job states every few seconds (the plugin
    waits 40 s by default before the first check) and keeping every job's Slurm log."""
    return run_snakemake(
        workdir,
        *args,
        "--workflow-profile",
        str(PROFILE),
        "--slurm-init-seconds-before-status-checks",
        "2",
        "--slurm-keep-successful-logs",
        "--slurm-logdir",
        str(workdir / "slurm_logs"),
        "--configfile",
        str(config),
        timeout=timeout,
    )


def slurm_job_ids(proc: subprocess.CompletedProcess) -> list[str]:
    return re.findall(r"submitted with SLURM jobid (\d+)", proc.stdout + proc.stderr)


def sacct_states(ids: list[str]) -> dict[str, str]:
    out = subprocess.run(
        ["sacct", "-X", "-n", "-P", "-j", ",".join(ids), "--format=JobIDRaw,State"], capture_output=True, text=True, check=True
    ).stdout
    return dict(line.split("|")[:2] for line in out.splitlines() if line)


def data_files(root: Path) -> dict[str, Path]:
    """The files whose content the run computes (meshes, caches, parameters, images, textures,
    assets), by path relative to ``results/``; metadata, logs, benchmarks and the report's HTML
    carry times, hosts and paths and are left out."""
    kept = {".ply", ".npz", ".pt", ".png", ".exr", ".hdr", ".glb", ".csv"}
    files = {}
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root)
        if not p.is_file() or p.suffix not in kept or {"logs", "benchmarks", "report"} & set(rel.parts):
            continue
        if p.name == "loss.csv":  # carries wall-clock seconds per iteration
            continue
        files[str(rel)] = p
    return files


def same_content(a: Path, b: Path) -> bool:
    if a.suffix == ".npz":
        x, y = np.load(a), np.load(b)
        return sorted(x.files) == sorted(y.files) and all(np.array_equal(x[k], y[k]) for k in x.files)
    if a.suffix == ".pt":
        x, y = torch.load(a, weights_only=True), torch.load(b, weights_only=True)
        return x["state_dict"].keys() == y["state_dict"].keys() and all(
            torch.equal(x["state_dict"][k], y["state_dict"][k]) for k in x["state_dict"]
        )
    if a.suffix == ".png":
        return np.array_equal(np.asarray(Image.open(a)), np.asarray(Image.open(b)))
    return a.read_bytes() == b.read_bytes()


def test_grid_through_slurm_equals_a_local_run(cluster, tmp_path):
    config = tmp_path / "grid.yaml"
    config.write_text(yaml.safe_dump(GRID))
    slurm_dir, local_dir = tmp_path / "slurm", tmp_path / "local"
    slurm_dir.mkdir()
    local_dir.mkdir()
    proc = slurm_run(slurm_dir, config)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-5000:]
    log = proc.stdout + proc.stderr
    # every job of the DAG but the target rule `all` went through Slurm and completed there
    stats = dict(re.findall(r"^(\w+)\s+(\d+)$", log[log.index("Job stats:") :], re.M))
    expected = int(stats["total"]) - int(stats.get("all", 0))
    ids = slurm_job_ids(proc)
    assert len(ids) == len(set(ids)) == expected, (ids, stats)
    states = sacct_states(ids)
    assert set(states) == set(ids) and set(states.values()) == {"COMPLETED"}, states
    # each job's own Slurm log, named by its job id, shows the stage ran inside it
    for job_id in ids:
        logs = list((slurm_dir / "slurm_logs").rglob(f"{job_id}.log"))
        assert len(logs) == 1, job_id
    # the same grid run locally gives the same files
    local = run_snakemake(local_dir, "--cores", "2", "--configfile", str(config))
    assert local.returncode == 0, local.stderr[-3000:]
    a, b = data_files(slurm_dir / "results"), data_files(local_dir / "results")
    assert a.keys() == b.keys() and len(a) > 40, sorted(set(a) ^ set(b))
    differ = [rel for rel in a if not same_content(a[rel], b[rel])]
    assert not differ, differ
    summary_a = json.loads((slurm_dir / "results" / "grid" / "report" / "summary.json").read_text())
    summary_b = json.loads((local_dir / "results" / "grid" / "report" / "summary.json").read_text())
    for ra, rb in zip(summary_a, summary_b, strict=True):
        for key in ("final_similarity", "eval_psnr_db", "bake_psnr_db", "clip_score", "faces_after"):
            assert ra[key] == rb[key], key


def steps_for(seconds: float, workdir: Path) -> int:
    """How many optimisation steps of the test's settings take about ``seconds`` on this machine,
    measured by a short local run (its own experiment; the mesh-level work it makes is shared)."""
    cfg = json.loads(json.dumps(GRID))
    cfg.update(experiment="calibrate", variants={"full": {}})
    cfg["optimize"].update(iterations=300, milestones=[250], checkpoint_every=20)
    config = workdir / "calibrate.yaml"
    config.write_text(yaml.safe_dump(cfg))
    meta = workdir / "results" / "calibrate" / "vase" / "wood" / "full" / "optimize" / "meta.json"
    proc = run_snakemake(workdir, str(meta.relative_to(workdir)), "--cores", "2", "--configfile", str(config))
    assert proc.returncode == 0, proc.stderr[-3000:]
    per_step = json.loads(meta.read_text())["seconds_per_iteration"]
    return 20 * max(100, round(seconds / per_step / 20))


def test_job_killed_at_its_time_limit_resumes_from_its_checkpoint(cluster, tmp_path):
    """An optimisation with a one-minute limit is killed by Slurm (state TIMEOUT) after writing
    checkpoints; the rerun, with time enough, resumes from the last one and finishes. Slurm
    enforces limits on a periodic sweep (every 30 s), so the kill comes 60-95 s after the start:
    the run is sized to take about 150 s here."""
    steps = steps_for(150.0, tmp_path)
    cfg = json.loads(json.dumps(GRID))
    cfg["variants"] = {"full": {}}
    cfg["optimize"].update(iterations=steps, milestones=[steps - 200], checkpoint_every=20)
    config = tmp_path / "long.yaml"
    config.write_text(yaml.safe_dump(cfg))
    cell = tmp_path / "results" / "grid" / "vase" / "wood" / "full" / "optimize"
    target = str(cell.relative_to(tmp_path) / "meta.json")
    killed = slurm_run(tmp_path, config, target, "--retries", "0", "--set-resources", "optimize:runtime=1")
    assert killed.returncode != 0, killed.stdout[-3000:]
    ids = slurm_job_ids(killed)
    states = sacct_states(ids)
    assert list(states.values()) == ["TIMEOUT"], states  # the mesh-level work came from the calibration
    assert (cell / "checkpoint.pt").is_file() and not (cell / "meta.json").exists()
    saved = torch.load(cell / "checkpoint.pt", weights_only=True)["iteration"]
    assert 20 <= saved < steps
    again = slurm_run(tmp_path, config, target, "--set-resources", "optimize:runtime=30", timeout=1800)
    assert again.returncode == 0, (again.stdout + again.stderr)[-3000:]
    assert sacct_states(slurm_job_ids(again)) and set(sacct_states(slurm_job_ids(again)).values()) == {"COMPLETED"}
    meta = json.loads((cell / "meta.json").read_text())
    assert meta["resumed_from_iteration"] is not None and meta["resumed_from_iteration"] >= saved
    assert not (cell / "checkpoint.pt").exists()
    # the mesh-level work was not redone
    assert "rule raycache" not in again.stdout + again.stderr and "rule normalize" not in again.stdout + again.stderr
    assert (mesh_work_dir(tmp_path, "vase", "raycache") / "meta.json").is_file()
