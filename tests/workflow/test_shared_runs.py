"""The smoke run shared by the test workers (:func:`conftest.smoke_run`): made once, read by every
later caller in any worker, and a run that timed out recorded so that the next caller fails at
once instead of running it again."""

from __future__ import annotations

import subprocess
from types import SimpleNamespace

import conftest


def _worker(monkeypatch, tmp_path, name: str):
    """A test worker's ``tmp_path_factory``: its folder inside the session's, as xdist makes them."""
    monkeypatch.setenv("PYTEST_XDIST_WORKER", name)
    folder = tmp_path / f"popen-{name}"
    folder.mkdir(exist_ok=True)
    return SimpleNamespace(getbasetemp=lambda: folder)


def test_made_once_and_read_by_every_worker(monkeypatch, tmp_path):
    calls = []

    def fake(work, *args, **kwargs):
        calls.append(work)
        (work / "made").write_text("yes")
        return subprocess.CompletedProcess(args, 0, "the output", "the log")

    monkeypatch.setattr(conftest, "run_snakemake", fake)
    first = conftest.smoke_run(_worker(monkeypatch, tmp_path, "gw0"))
    second = conftest.smoke_run(_worker(monkeypatch, tmp_path, "gw1"))
    assert calls == [tmp_path / "smoke-run"]
    assert first == second == conftest.SmokeRun(tmp_path / "smoke-run", 0, "the output", "the log")
    assert (first.workdir / "made").read_text() == "yes"


def test_a_run_that_timed_out_is_not_run_again(monkeypatch, tmp_path):
    calls = []

    def slow(work, *args, timeout, **kwargs):
        calls.append(work)
        raise subprocess.TimeoutExpired(["snakemake"], timeout)

    monkeypatch.setattr(conftest, "run_snakemake", slow)
    first = conftest.smoke_run(_worker(monkeypatch, tmp_path, "gw0"))
    second = conftest.smoke_run(_worker(monkeypatch, tmp_path, "gw1"))
    assert len(calls) == 1 and first == second
    assert first.returncode != 0 and "did not finish in 1500 s" in first.stderr


def test_a_run_whose_worker_died_is_made_again(monkeypatch, tmp_path):
    """A folder without the finished record (its worker killed mid-run) is cleared and run anew."""
    (tmp_path / "smoke-run").mkdir()
    (tmp_path / "smoke-run" / "half").write_text("left by a killed run")
    monkeypatch.setattr(conftest, "run_snakemake", lambda work, *a, **k: subprocess.CompletedProcess(a, 0, "", ""))
    run = conftest.smoke_run(_worker(monkeypatch, tmp_path, "gw2"))
    assert run.returncode == 0 and not (run.workdir / "half").exists()


def test_the_slurm_grid_compares_with_the_smoke_run_only_where_it_ran_on_the_cpu(monkeypatch, tmp_path):
    """The Slurm grid runs on the CPU: where the smoke run took a GPU (``device: auto`` on a GPU
    host) its files are no reference, and the Slurm test makes its own local run of the grid."""
    import test_slurm

    smoke = tmp_path / "smoke-run"
    meta = smoke / "results" / "smoke" / "vase" / "wood" / "full" / "optimize" / "meta.json"
    meta.parent.mkdir(parents=True)
    monkeypatch.setattr(test_slurm, "smoke_run", lambda factory: conftest.SmokeRun(smoke, 0, "", ""))
    runs = []
    monkeypatch.setattr(
        test_slurm, "run_snakemake", lambda work, *a, **k: runs.append(work) or subprocess.CompletedProcess(a, 0, "", "")
    )
    config = tmp_path / "grid.yaml"
    meta.write_text('{"device": "cpu"}')
    assert test_slurm.local_reference(None, tmp_path, config) == (smoke, "smoke") and runs == []
    meta.write_text('{"device": "cuda"}')
    assert test_slurm.local_reference(None, tmp_path, config) == (tmp_path / "local", "grid")
    assert runs == [tmp_path / "local"]
