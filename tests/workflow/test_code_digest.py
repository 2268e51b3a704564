"""Reruns when the code changes: every job has a params entry ``code``, the digest of the source of
the stage module it runs and of every module of the package that one imports
(``stages.config.code``); Snakemake's params trigger then reruns exactly the jobs whose code
changed. Tested on the digests and on a real Snakemake run in a copy of the repository."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import yaml
from conftest import REPO

from stages.config.code import code_digest, module_closure
from stages.config.workflow import WorkflowConfig


def copy_repo(dst: Path) -> Path:
    for name in ("Snakefile", "workflow", "stages", "profiles", "config", "pyproject.toml"):
        src = REPO / name
        (shutil.copytree if src.is_dir() else shutil.copy2)(src, dst / name)
    return dst


def test_closure_follows_the_package_imports_only():
    closure = module_closure("stages.raycache")
    assert {"stages.raycache", "stages.geometry.raycache", "stages.config.sections", "stages", "stages.geometry"} <= set(closure)
    assert not any(m.startswith(("torch", "numpy")) for m in closure)
    # the report reads JSON: no geometry, no model code
    assert not any(m.startswith(("stages.geometry", "stages.model")) for m in module_closure("stages.report"))


def test_digest_changes_with_code_not_with_comments(tmp_path):
    root = copy_repo(tmp_path)
    stages = root / "stages"
    before = {m: code_digest(m, stages) for m in ("stages.normalize", "stages.raycache", "stages.report")}
    target = stages / "geometry" / "normalization.py"
    text = target.read_text()
    target.write_text(text + "\n# a comment\n\n")
    assert {m: code_digest(m, stages) for m in before} == before  # comments and blank lines: no rerun
    target.write_text(text + "\nEDITED = 1\n")
    after = {m: code_digest(m, stages) for m in before}
    assert after["stages.normalize"] != before["stages.normalize"]  # it imports the edited module
    assert after["stages.report"] == before["stages.report"]  # it does not


def test_digest_covers_package_data(tmp_path):
    """The report's style sheet and scripts, and the renderer's tables, are code too."""
    root = copy_repo(tmp_path)
    stages = root / "stages"
    names = ("stages.html_report", "stages.report", "stages.normalize", "stages.optimize")
    before = {m: code_digest(m, stages) for m in names}
    css = stages / "results" / "web" / "report.css"
    css.write_text(css.read_text() + "body{color:red}\n")
    after = {m: code_digest(m, stages) for m in names}
    assert after["stages.html_report"] != before["stages.html_report"]
    assert after["stages.report"] != before["stages.report"]  # the same package (stages.results)
    assert after["stages.normalize"] == before["stages.normalize"] and after["stages.optimize"] == before["stages.optimize"]
    table = stages / "render" / "data" / "specular_albedo.npz"
    table.write_bytes(table.read_bytes() + b"\0")
    assert code_digest("stages.optimize", stages) != before["stages.optimize"]
    assert code_digest("stages.normalize", stages) == before["stages.normalize"]


TINY = {
    "meshes": {"vase": {"builtin": "vase"}},
    "prompts": {"wood": "a {object} made of wood"},
    "optimize": {"clip_tiny_test": True},
    "metrics": {"clip_tiny_test": True},
    "raycache": {
        "views": 2,
        "resolution": 16,
        "eval_azimuths": 2,
        "eval_elevations_deg": [0.0],
        "eval_resolution": 16,
        "metrics_azimuths": 2,
        "metrics_elevations_deg": [0.0],
        "metrics_resolution": 16,
    },
}


def snakemake(root: Path, *args: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    cmd = [sys.executable, "-m", "snakemake", *args, "--cores", "1", "--configfile", "cfg.yaml"]  # targets before nargs options
    return subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True, timeout=600)


def test_snakemake_reruns_exactly_the_jobs_whose_code_changed(tmp_path):
    """In a copy of the repository: normalise and ray-cache a mesh, then edit the ray-cache
    module (a comment: nothing reruns; code: the raycache job reruns because its params changed,
    the normalize job does not)."""
    root = copy_repo(tmp_path)
    (root / "cfg.yaml").write_text(yaml.safe_dump(TINY))
    key = WorkflowConfig(TINY).mesh_work_keys("vase")["raycache"]
    target = f"results/meshes/vase/{key}/raycache/meta.json"
    first = snakemake(root, target)
    assert first.returncode == 0, first.stderr
    module = root / "stages" / "geometry" / "raycache.py"
    text = module.read_text()
    module.write_text(text + "\n# only a comment\n")
    quiet = snakemake(root, "-n", target)
    assert quiet.returncode == 0 and "Nothing to be done" in quiet.stdout + quiet.stderr, quiet.stdout
    module.write_text(text + "\nEDITED = 1\n")
    dry = snakemake(root, "-n", target)
    assert dry.returncode == 0, dry.stderr
    out = dry.stdout
    assert "rule raycache:" in out and "rule normalize:" not in out, out
    assert "params" in out.split("rule raycache:", 1)[1].lower(), out
