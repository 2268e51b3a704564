"""A fresh machine, as a newcomer has it: a clone of the repository (no node_modules, no
.venv-blender, no results) on a PATH without Node.js, npm, Chromium, Blender or Slurm, and no
system libLLVM 16+ for Mitsuba (``TANGO_LIBLLVM_DIRS`` empty: no system folder is searched, so the
set-up's ``karellen-llvm-core`` wheel is what is left), offline. CI installs all of these, so
without this test CI would never take the paths a newcomer takes.

On such a machine the doctor tells the truth (Mitsuba runs ``llvm_ad_rgb`` on the wheel's
libLLVM; where no libLLVM loads at all, ``scalar_rgb``, and it says how long this config's targets
take there; Blender is missing and needed by the offline demo's round trip), the offline demo stops
before any job with a message that names what to install, and one's own mesh runs end to end
through ``python -m stages.quick`` with image guidance: targets in ``llvm_ad_rgb`` on the wheel's
libLLVM, an export that records why the glTF validator did not run, a report of static previews."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from conftest import REPO, TINY, TINY_OPTIMIZE, shared_mesh

from stages.config.workflow import load_config_files
from stages.doctor import target_samples
from stages.geometry.meshio import load_mesh

#: the programs a fresh machine lacks (CI installs them)
HIDDEN = {"node", "nodejs", "npm", "npx", "chromium", "chromium-browser", "blender", "sbatch", "squeue", "sinfo", "sacct"}


def fresh_clone(dest: Path) -> Path:
    """The repository's files as git sees them (tracked or new, not ignored), copied to ``dest``."""
    listed = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=REPO, capture_output=True, check=True
    ).stdout.decode()
    for rel in filter(None, listed.split("\0")):
        src = REPO / rel
        if src.is_file():
            (dest / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / rel)
    return dest


def bare_path(links: Path) -> str:
    """A PATH of this interpreter's folder, then one folder of links to every program on today's
    PATH except :data:`HIDDEN`."""
    links.mkdir()
    for folder in os.environ.get("PATH", "").split(os.pathsep):
        if not os.path.isdir(folder):
            continue
        for entry in os.scandir(folder):
            if entry.name in HIDDEN or (links / entry.name).exists() or not os.access(entry.path, os.X_OK):
                continue
            (links / entry.name).symlink_to(entry.path)
    return f"{Path(sys.executable).parent}{os.pathsep}{links}"


@pytest.fixture(scope="module")
def machine(tmp_path_factory):
    """``(clone, env)``: a fresh clone and the environment of a machine without the tools above."""
    root = tmp_path_factory.mktemp("fresh")
    clone = fresh_clone(root / "clone")
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "TANGO_BLENDER", "DRJIT_LIBLLVM_PATH")}
    env.update(
        PATH=bare_path(root / "bin"),
        TANGO_LIBLLVM_DIRS="",
        HF_HUB_OFFLINE="1",
        HF_HOME=str(root / "hf"),
        HF_HUB_CACHE=str(root / "hf" / "hub"),
        XDG_CACHE_HOME=str(root / "cache"),
        TANGO_PLAN_CALIBRATE="0",
    )
    for tool in HIDDEN:
        assert shutil.which(tool, path=env["PATH"]) is None, tool
    return clone, env


def run(cmd: list[str], clone: Path, env: dict, timeout: float = 900) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, cwd=clone, env=env, capture_output=True, text=True, timeout=timeout)


def test_doctor_tells_the_truth_on_a_bare_machine(machine):
    clone, env = machine
    demo = load_config_files([REPO / "config" / "demo-offline.yaml"])
    jobs = demo.target_jobs()
    samples = sum(target_samples(demo, mesh) for mesh, _ in jobs)
    proc = run([sys.executable, "-m", "stages.doctor", "--configfile", "config/demo-offline.yaml", "--json"], clone, env)
    checks = {c["name"]: c for c in json.loads(proc.stdout)}
    assert proc.returncode == 1, proc.stderr[-2000:]
    mitsuba = checks["Mitsuba 3"]
    assert mitsuba["ok"] and mitsuba["needed"], mitsuba
    # no system libLLVM: the set-up's wheel gives Mitsuba its vectorised variant
    assert "variant llvm_ad_rgb with libLLVM 23" in mitsuba["detail"] and "from the karellen-llvm-core wheel" in mitsuba["detail"]
    # the real use: a render in the run's variant, and what this config's targets cost there
    assert "rendered a 128 x 128 target probe at 64 spp in llvm_ad_rgb" in mitsuba["tried"]
    assert f"this config's targets ({len(jobs)} job(s), {samples / 1e6:.0f} M samples) take about" in mitsuba["tried"]
    assert "scalar_rgb" not in mitsuba["tried"]
    blender = checks["Blender"]
    assert blender["status"] == "MISSING" and "Blender was not found" in blender["detail"]
    assert "bash scripts/setup.sh" in blender["fix"] and "roundtrip: {enabled: false}" in blender["fix"]
    node = checks["Node.js and the report's viewer"]
    assert (
        node["status"] == "optional" and node["detail"].startswith("node not found") and "apt-get install nodejs" in node["fix"]
    )
    assert checks["Chromium"]["status"] == "optional"
    for name in ("torch and device", "Embree", "pymeshlab", "xatlas", "usd-core", "pygltflib"):
        assert checks[name]["ok"] and checks[name]["tried"], checks[name]
    text = run([sys.executable, "-m", "stages.doctor", "--configfile", "config/demo-offline.yaml"], clone, env).stdout
    assert "1 needed piece(s) missing (Blender): the run would stop; fix them first." in text
    # with the overlay the message names, Blender is no longer needed
    cmd = [sys.executable, "-m", "stages.doctor", "--configfile", "config/demo-offline.yaml", "config/overlays/no-blender.yaml"]
    proc = run(cmd, clone, env)
    assert proc.returncode == 0 and "Everything this config's run needs is here." in proc.stdout, proc.stdout[-2000:]


def test_doctor_without_any_libllvm_says_scalar_and_what_it_costs(machine):
    """Where no libLLVM loads (here: ``DRJIT_LIBLLVM_PATH``, which always wins, names no file),
    Mitsuba falls back to ``scalar_rgb`` and the doctor says so, how long this config's targets take
    in it, and what to install."""
    clone, env = machine
    demo = load_config_files([REPO / "config" / "demo-offline.yaml"])
    samples = sum(target_samples(demo, mesh) for mesh, _ in demo.target_jobs())
    env = {**env, "DRJIT_LIBLLVM_PATH": str(clone.parent / "no-libLLVM.so")}
    proc = run([sys.executable, "-m", "stages.doctor", "--configfile", "config/demo-offline.yaml", "--json"], clone, env)
    mitsuba = {c["name"]: c for c in json.loads(proc.stdout)}["Mitsuba 3"]
    assert mitsuba["ok"] and "variant scalar_rgb (no libLLVM 16+ found)" in mitsuba["detail"], mitsuba
    assert "rendered a 128 x 128 target probe at 64 spp in scalar_rgb" in mitsuba["tried"]
    assert f"({len(demo.target_jobs())} job(s), {samples / 1e6:.0f} M samples) take about" in mitsuba["tried"]
    assert "slow scalar_rgb variant (pip install karellen-llvm-core, or Debian: apt-get install libllvm19" in mitsuba["tried"]


def test_offline_demo_stops_at_once_naming_what_to_install(machine):
    clone, env = machine
    t0 = time.perf_counter()
    proc = run([sys.executable, "-m", "snakemake", "--cores", "2", "--configfile", "config/demo-offline.yaml"], clone, env)
    out = proc.stdout + proc.stderr
    assert proc.returncode != 0 and time.perf_counter() - t0 < 120, out[-3000:]
    assert "1 of the tools this run needs are missing; nothing was run." in out
    assert "roundtrip: enabled in 3 cell(s)" in out and "Blender was not found" in out
    assert "bash scripts/setup.sh test,reference,blender" in out and "roundtrip: {enabled: false}" in out
    assert "config/overlays/no-blender.yaml" in out
    assert not (clone / "results").exists()
    # only the jobs still to run count: the same config up to its meshes' normalisation needs no judge
    proc = run(
        [sys.executable, "-m", "snakemake", "--cores", "2", "--until", "normalize", "--configfile", "config/demo-offline.yaml"],
        clone,
        env,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "tools this run needs are missing" not in proc.stderr and "3 of them to run now (normalize 3)" in proc.stderr


@pytest.mark.slow(minutes=1)
def test_own_mesh_image_guided_runs_end_to_end_on_a_bare_machine(machine, tmp_path):
    """``python -m stages.quick`` on a shared mesh with image guidance, sized down by an overlay:
    it writes an ordinary experiment config, and the run goes through on the fallbacks."""
    clone, env = machine
    mesh = shared_mesh("bunny.obj")
    overlay = tmp_path / "tiny.yaml"
    overlay.write_text(yaml.safe_dump({**TINY, "prompts": {"a-bunny-made-of-wood": {"optimize": TINY_OPTIMIZE}}}))
    cmd = [sys.executable, "-m", "stages.quick", str(mesh), "a bunny made of wood", "--image-guided", "wood"]
    proc = run([*cmd, "--overlay", str(overlay)], clone, env)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-4000:]
    name = "bunny-a-bunny-made-of-wood"
    config = yaml.safe_load((clone / "config" / "quick" / f"{name}.yaml").read_text())
    assert config["meshes"]["bunny"]["path"] == str(mesh.resolve())
    assert config["prompts"]["a-bunny-made-of-wood"]["optimize"] == {"guidance": "image", "target_material": "wood"}
    loaded = load_mesh(mesh)
    assert f"mesh {mesh}: {len(loaded.vertices):,} vertices, {len(loaded.faces):,} faces" in proc.stdout
    assert f"Plan of experiment {name}" in proc.stderr
    cell = clone / "results" / name / "bunny" / "a-bunny-made-of-wood" / "base"
    # the targets were path-traced in Mitsuba's vectorised variant on the set-up's libLLVM wheel
    (target_meta,) = (clone / "results" / "meshes" / "bunny").glob("*/target/wood/meta.json")
    renderer = json.loads(target_meta.read_text())["renderer"]
    assert renderer["variant"] == "llvm_ad_rgb" and "from the karellen-llvm-core wheel" in renderer["libllvm"], renderer
    optimize = json.loads((cell / "optimize" / "meta.json").read_text())
    assert optimize["settings"]["guidance"] == "image" and optimize["settings"]["iterations"] == 3
    export = json.loads((cell / "export" / "meta.json").read_text())
    assert export["stats"]["validation"]["model.glb"] == {"ran": False, "reason": "Node.js (node) is not on PATH"}
    lod = json.loads((cell / "lod" / "meta.json").read_text())
    assert lod["stats"]["validation"]["model_lods.glb"] == {"ran": False, "reason": "Node.js (node) is not on PATH"}
    # the relighting was graded against Mitsuba's relit truth (target.relight_environments)
    relit = json.loads((cell / "relight" / "meta.json").read_text())["stats"]["ground_truth"]
    assert [g["environment"] for g in relit] == ["builtin:sunset"] and all(g["pixels"] > 0 for g in relit)
    # shown beside the truth: one environment, three rows (ours, Mitsuba's, the difference) on the cell's page
    from PIL import Image

    tile = json.loads((cell / "relight" / "meta.json").read_text())["settings"]["width"]
    width, height = Image.open(cell / "relight" / "ground_truth.png").size
    # three rows of tiles (ours, Mitsuba's, the difference), labelled around them with a grey scale
    assert 3 * tile < height < 3 * tile + 100 and tile < width
    summary = (clone / "results" / name / "report" / "summary.csv").read_text()
    assert "relit_psnr_db" in summary.splitlines()[0] and "relit_scale" in summary.splitlines()[0]
    index = (clone / "results" / name / "report" / "index.html").read_text()
    assert "<model-viewer" not in index and "id='no-viewer'" in index and "image-guided" in index
    # the same command again: the same config, nothing to redo
    again = run([*cmd, "--overlay", str(overlay)], clone, env)
    assert again.returncode == 0 and "Nothing to be done" in again.stdout + again.stderr, again.stderr[-2000:]
