"""The Slurm profile's resources on the DAG (no cluster needed) and the helper that derives
resources from benchmark files."""

from __future__ import annotations

import re
import subprocess
import sys

import yaml
from conftest import REPO, run_snakemake

SMOKE = REPO / "tests" / "smoke" / "config.yaml"
PROFILE = REPO / "profiles" / "slurm"


def job_resources(stdout: str) -> dict[str, set[str]]:
    """Rule -> the distinct resource lines of its jobs in a dry run."""
    out: dict[str, set[str]] = {}
    rule = None
    for line in stdout.splitlines():
        if m := re.match(r"(?:local)?rule (\w+):$", line):
            rule = m.group(1)
        elif rule and (m := re.match(r"\s+resources: (.*)", line)):
            out.setdefault(rule, set()).add(m.group(1))
            rule = None
    return out


def test_profile_resources_per_rule_and_the_gpu_switch(tmp_path):
    profile = yaml.safe_load((PROFILE / "config.yaml").read_text())
    assert profile["executor"] == "slurm" and profile["retries"] == 1
    # device=cuda would make every torch job ask for the GPU locally (profiles/default); under the
    # Slurm profile no job asks for one unless the profile says so, whatever the host has
    proc = run_snakemake(
        tmp_path, "-n", "--workflow-profile", str(PROFILE), "--configfile", str(SMOKE), "--config", "device=cuda"
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = job_resources(proc.stdout)
    assert len(res["optimize"]) == 1
    (opt,) = res["optimize"]
    assert "mem_mb=8192" in opt and "runtime=120" in opt and "gpu=0" in opt
    assert all("mem_mb=8192" in r and "runtime=60" in r for r in res["bake"] | res["lod"])
    for rule in ("normalize", "raycache", "export", "relight", "metrics", "report"):
        assert all("mem_mb=4096" in r and "runtime=30" in r for r in res[rule]), rule
    assert all("gpu=0" in r for rule in ("bake", "lod", "relight", "metrics") for r in res[rule])
    # the GPU for the optimisation alone, switched on in (a copy of) the profile: the other
    # resources stay as they were
    profile["set-resources"]["optimize"]["gpu"] = 1
    (tmp_path / "gpu").mkdir()
    (tmp_path / "gpu" / "config.yaml").write_text(yaml.safe_dump(profile))
    gpu = run_snakemake(tmp_path, "-n", "--workflow-profile", str(tmp_path / "gpu"), "--configfile", str(SMOKE))
    assert gpu.returncode == 0, gpu.stderr[-3000:]
    res = job_resources(gpu.stdout)
    assert all("gpu=1" in r and "runtime=120" in r and "mem_mb=8192" in r for r in res["optimize"])
    assert all("gpu=0" in r for r in res["bake"] | res["metrics"])


def test_resources_from_benchmark_files(tmp_path):
    header = "s\th:m:s\tmax_rss\tmax_vms\tmax_uss\tmax_pss\tio_in\tio_out\tmean_load\tcpu_time\n"
    runs = {
        "a/x/wood/full/benchmarks/optimize.tsv": (400.0, 3000.0),
        "a/x/wood/second/benchmarks/optimize.tsv": (1300.0, 2100.0),
        "meshes/x/0123456789ab/benchmarks/target-wood.tsv": (90.0, 700.0),
        "meshes/x/0123456789ab/benchmarks/normalize.tsv": (1.0, 40.0),
    }
    for rel, (s, rss) in runs.items():
        path = tmp_path / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(header + f"{s}\t0:00:00\t{rss}\t1\t1\t1\t0\t0\t100\t1\n")
    proc = subprocess.run(
        [sys.executable, str(REPO / "scripts" / "slurm_resources.py"), str(tmp_path)], capture_output=True, text=True
    )
    assert proc.returncode == 0, proc.stderr
    block = yaml.safe_load(proc.stdout[proc.stdout.index("set-resources:") :])["set-resources"]
    # runtime: 3 x the largest wall time, in whole minutes, at least 10; memory: 2 x the largest
    # peak, rounded up to 256 MB, at least 2048
    assert block["optimize"] == {"runtime": 65, "mem_mb": 6144}
    assert block["target"] == {"runtime": 10, "mem_mb": 2048}
    assert block["normalize"] == {"runtime": 10, "mem_mb": 2048}
    assert re.search(r"^optimize\s+2\s+1300\.0\s+3000$", proc.stdout, re.M)
    empty = subprocess.run(
        [sys.executable, str(REPO / "scripts" / "slurm_resources.py"), str(tmp_path / "none")], capture_output=True, text=True
    )
    assert empty.returncode == 1 and "no benchmarks/*.tsv" in empty.stderr
