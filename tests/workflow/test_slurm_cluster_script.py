"""scripts/slurm-cluster.sh refuses a machine that has a Slurm of its own, before it installs,
writes or starts anything, and `purge` deletes only a state folder it made. Every case here stops
at the refusal, so nothing on the machine changes (the script needs root: CI runs as root)."""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from pathlib import Path

import pytest
from conftest import REPO, slurm_lock

SCRIPT = REPO / "scripts" / "slurm-cluster.sh"

pytestmark = pytest.mark.skipif(os.geteuid() != 0 and not os.environ.get("CI"), reason="the script runs as root")


@pytest.fixture(autouse=True)
def _no_cluster_meanwhile():
    """The script refuses while a cluster runs: never beside the Slurm tests' (parallel workers)."""
    with slurm_lock():
        yield


def script(tmp_path: Path, command: str, **env: str) -> subprocess.CompletedProcess:
    environ = {k: v for k, v in os.environ.items() if k != "SLURM_CONF"}
    environ.update(TANGO_SLURM_STATE=str(tmp_path / "state"), TANGO_SLURM_INSTALL="0", **env)
    return subprocess.run(["bash", str(SCRIPT), command], capture_output=True, text=True, timeout=60, env=environ)


def test_slurm_conf_of_another_slurm_is_refused(tmp_path):
    conf = tmp_path / "slurm.conf"
    conf.write_text("ClusterName=real\n")
    proc = script(tmp_path, "start", SLURM_CONF=str(conf))
    assert proc.returncode == 1
    assert f"SLURM_CONF is set ({conf}) and names a configuration this script did not write" in proc.stderr
    assert not (tmp_path / "state").exists() and conf.read_text() == "ClusterName=real\n"


def test_a_foreign_slurm_conf_holding_the_marker_in_a_comment_is_refused(tmp_path):
    """The marker counts only as the first line of a file the script wrote: a real cluster's
    configuration that quotes it in a comment further down is still refused."""
    marker = next(line for line in SCRIPT.read_text().splitlines() if line.startswith("marker=")).split('"')[1]
    conf = tmp_path / "slurm.conf"
    conf.write_text(f"ClusterName=real\n{marker}\n")
    proc = script(tmp_path, "start", SLURM_CONF=str(conf))
    assert proc.returncode == 1 and "names a configuration this script did not write" in proc.stderr
    assert not (tmp_path / "state").exists()


def test_a_source_built_slurms_configuration_is_refused(tmp_path):
    """A Slurm built from source reads /usr/local/etc/slurm.conf by default: its presence stops the
    script as /etc/slurm's does (the file is made for the test and removed after)."""
    conf = Path("/usr/local/etc/slurm.conf")
    if conf.exists():
        pytest.skip(f"{conf} exists on this machine (the test would not remove it)")
    conf.parent.mkdir(parents=True, exist_ok=True)
    conf.write_text("ClusterName=real\n")
    try:
        proc = script(tmp_path, "start")
    finally:
        conf.unlink()
    assert proc.returncode == 1 and f"{conf} exists and was not written by this script" in proc.stderr
    assert not (tmp_path / "state").exists()


def test_a_slurm_daemon_it_did_not_start_is_refused(tmp_path):
    """A process called slurmd (here a copy of sleep) that the script did not start: refused."""
    fake = tmp_path / "slurmd"
    shutil.copy(shutil.which("sleep"), fake)
    daemon = subprocess.Popen([str(fake), "60"])
    try:
        time.sleep(0.2)
        proc = script(tmp_path, "start")
    finally:
        daemon.kill()
        daemon.wait()
    assert proc.returncode == 1
    assert "slurmd is running and was not started by this script" in proc.stderr or "exists" in proc.stderr
    assert not (tmp_path / "state").exists()


def test_purge_deletes_no_folder_it_did_not_make(tmp_path):
    state = tmp_path / "state"
    (state / "data").mkdir(parents=True)
    (state / "data" / "precious.db").write_text("a real cluster's accounting")
    proc = script(tmp_path, "purge")
    assert proc.returncode == 1 and "was not made by this script" in proc.stderr
    assert (state / "data" / "precious.db").read_text() == "a real cluster's accounting"


def test_stop_removes_the_configuration_it_wrote_and_no_other(tmp_path):
    """While a configuration names a controller that is not running, every Slurm command waits
    about 9 s for it (and Snakemake's Slurm plugin runs one each time Snakemake starts): `stop`
    removes the files it wrote (its marker line), which `start` writes again, and keeps any other."""
    marker = next(line for line in SCRIPT.read_text().splitlines() if line.startswith("marker=")).split('"')[1]
    ours, theirs = tmp_path / "ours", tmp_path / "theirs"
    ours.mkdir(), theirs.mkdir()
    for name in ("slurm.conf", "slurmdbd.conf"):
        (ours / name).write_text(f"{marker}\nClusterName=tango\n")
        (theirs / name).write_text("ClusterName=real\n")
    (tmp_path / "state" / "run").mkdir(parents=True)
    (tmp_path / "state" / "run" / "launched").write_text("slurmd /nonexistent/slurmd.pid\n")  # nothing alive
    for conf_dir in (ours, theirs):
        proc = script(tmp_path, "stop", TANGO_SLURM_CONF_DIR=str(conf_dir))
        assert proc.returncode == 0, proc.stderr
    assert not list(ours.iterdir())
    assert sorted(p.name for p in theirs.iterdir()) == ["slurm.conf", "slurmdbd.conf"]
    assert (theirs / "slurm.conf").read_text() == "ClusterName=real\n"
