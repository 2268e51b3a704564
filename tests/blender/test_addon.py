"""The Blender add-on (blender/tango_stylize): installed with Blender's own extension installer into
a headless Blender, it stylises the selected objects of a rigged, animated, UV-mapped scene with the
tiny test CLIP and leaves every object's vertices, UV maps, weights, rig and animation as they were,
its material slots reading the baked textures through a bake UV map by name; with modifiers applied
it makes a stylised copy instead. Its job module (no Blender) builds the command, reads progress and
errors, and stops every process a run started."""

from __future__ import annotations

import importlib.util
import json
import math
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from conftest import REPO, TINY, TINY_OPTIMIZE, require_blender

ADDON = REPO / "blender" / "tango_stylize"


def addon_job():
    """The add-on's job module, loaded from its file (the package's __init__ needs bpy)."""
    spec = importlib.util.spec_from_file_location("tango_stylize_job", ADDON / "job.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def test_the_command_is_the_quick_command_with_the_panels_choices(tmp_path):
    job = addon_job()
    r = job.Request("/p/python", tmp_path, tmp_path / "in.glb", "a ball", "balanced", "n", "wood", True, "keep", ("o.yaml",))
    assert r.command(dry_run=True) == [
        "/p/python", "-m", "stages.quick", "--preset", "balanced", "--name", "n", "--uv", "keep", "--force",
        "--image-guided", "wood", "--test-clip", "--overlay", "o.yaml", "--dry-run", "--", str(tmp_path / "in.glb"), "a ball",
    ]  # fmt: skip
    plain = job.Request("p", tmp_path, tmp_path / "m", "-a prompt with a hyphen", "fast", "n").command()
    assert "--image-guided" not in plain and plain[-3:] == ["--", str(tmp_path / "m"), "-a prompt with a hyphen"]
    assert job.run_name("My Scene.blend", "Body", "Ünïcode box") == "my-scene-blend-body-n-code-box"
    assert job.run_name("", "") == "blender"
    # another prompt is another experiment, the same one the same
    a, b = job.run_name("f", "o", settings=("wood", "fast")), job.run_name("f", "o", settings=("gold", "fast"))
    assert a != b and a == job.run_name("f", "o", settings=("wood", "fast")) and a.startswith("f-o-")


def test_progress_and_the_one_line_error_come_from_the_runs_output(tmp_path):
    job = addon_job()
    log = tmp_path / "run.log"
    log.write_text("Building DAG\n3 of 11 steps (27%) done\nrule bake:\n7 of 11 steps (64%) done\n")
    j = job.Job(["true"], tmp_path, log)
    assert j.progress() == (0.64, "7 of 11 steps (64%) done")
    failed = "2026-11-29 02:56:53,612 ERROR stages.bake: bake failed: mesh.ply: file not found. Run the earlier stages first.\n"
    assert job.last_line("noise\n" + failed + "Shutting down\n") == "mesh.ply: file not found. Run the earlier stages first."
    assert job.last_line("one\ntwo\n\n") == "two" and job.last_line("") == "no output"
    with pytest.raises(RuntimeError, match="0 exported cells"):
        job.result_of(job.Request("p", tmp_path, tmp_path / "m", "x", "fast", "none"))


def test_cancel_stops_the_run_and_every_process_it_started(tmp_path):
    job = addon_job()
    pids = tmp_path / "pids"
    script = f"sleep 300 & echo $! > {pids}; sleep 300"
    j = job.Job(["bash", "-c", script], tmp_path, tmp_path / "log").start()
    for _ in range(100):
        if pids.is_file() and pids.read_text().strip():
            break
        time.sleep(0.05)
    child = int(pids.read_text())
    assert j.poll() is None
    j.cancel(grace=5)
    assert j.poll() is not None
    time.sleep(0.2)
    alive = subprocess.run(["ps", "-o", "stat=", "-p", str(child)], capture_output=True, text=True).stdout.strip()
    assert alive in ("", "Z"), f"the run's child {child} is still running ({alive})"


def test_the_manifest_is_the_projects_version_and_the_world_turns_as_the_judges():
    import tomllib

    from stages.reference.blender import WORLD_ROTATION_Z

    manifest = tomllib.loads((ADDON / "blender_manifest.toml").read_text())
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    assert manifest["version"] == project["version"] and manifest["id"] == "tango_stylize"
    text = (ADDON / "exchange.py").read_text()
    value = re.search(r"^WORLD_ROTATION_Z = (.+)$", text, re.M).group(1)
    assert eval(value, {"math": math}) == WORLD_ROTATION_Z  # noqa: S307 - a constant of our own file


def test_choices_come_from_the_project(tmp_path):
    job = addon_job()
    found = job.choices(sys.executable)
    assert found["default_preset"] in found["presets"] and "wood" in found["materials"]
    with pytest.raises(RuntimeError, match="could not be run"):
        job.choices(str(tmp_path / "absent-python"))
    absent = job.Request(str(tmp_path / "absent-python"), tmp_path, tmp_path / "m.glb", "x", "fast", "n")
    with pytest.raises(RuntimeError, match="the plan could not be made"):
        job.plan(absent)


@pytest.mark.slow(minutes=2)
def test_blender_stylises_the_selected_objects_and_keeps_their_rig(tmp_path):
    require_blender()
    from stages.reference.blender import find_blender

    sys.path.insert(0, str(REPO / "scripts"))
    from build_blender_addon import build

    zip_path = build(tmp_path / "dist")
    overlay = tmp_path / "tiny.yaml"
    tiny = {**TINY, "lod": {"enabled": False}, "prompts": {"a-ball-made-of-wood": {"optimize": TINY_OPTIMIZE}}}
    overlay.write_text(yaml.safe_dump(tiny))
    job = {"zip": str(zip_path), "python": sys.executable, "workdir": str(tmp_path / "work"), "overlay": str(overlay)}
    job["out"] = str(tmp_path / "out.json")
    (tmp_path / "job.json").write_text(json.dumps(job))
    env = {**os.environ, "BLENDER_USER_RESOURCES": str(tmp_path / "blender-user")}
    cmd = [*find_blender(), str(REPO / "tests" / "blender" / "addon_driver.py"), str(tmp_path / "job.json")]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=1200, env=env, cwd=tmp_path)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-4000:]
    out = json.loads((tmp_path / "out.json").read_text())
    assert out["result"] == out["applied"] == ["FINISHED"]
    before, after, copy = out["before"], out["after"], out["copy"]
    for name in ("Body", "Box"):
        b, a = before["objects"][name], after["objects"][name]
        for key in ("vertices", "polygons", "weights", "parent", "modifiers"):
            assert a[key] == b[key], (name, key)
        for uv_map, coords in b["uv_maps"].items():  # every UV map the object had, as it was
            assert a["uv_maps"][uv_map] == coords, (name, uv_map)
        assert a["provenance"]["test_only"] and a["provenance"]["prompt"] == "a ball made of wood"
        for slot in a["slots"]:  # each slot reads baked textures (packed) through the bake UV map by name
            assert "TEST ONLY" in slot["material"] and slot["packed"] and slot["sizes"] == [[64, 64]]
            assert {"Base Color", "Metallic", "Roughness", "Normal"} <= set(slot["wired"])
            assert slot["uv_maps"] == [a["provenance"]["uv_map"]]
    assert after["objects"]["Body"]["provenance"]["uv_map"] == "UVMap"  # its own render map, kept
    # the material the two objects shared: each now has its own, reading its own UV map
    assert after["objects"]["Box"]["slots"][0]["material"] != after["objects"]["Body"]["slots"][0]["material"]
    assert list(after["objects"]["Box"]["uv_maps"]) == ["TANGO"]  # it had none: one was made
    assert after["bones"] == before["bones"] and after["keys"] == before["keys"] and len(after["keys"]) == 6
    assert after["world"].startswith("TANGO light")
    # modifiers applied: a stylised copy holds the subdivided mesh, its rig kept; textures in files
    stylised = copy["objects"]["Body stylised"]
    assert stylised["polygons"] > before["objects"]["Body"]["polygons"] and stylised["parent"] == "Rig"
    assert stylised["modifiers"] == ["ARMATURE"] and "TANGO" in stylised["uv_maps"]
    assert all(not s["packed"] and all(Path(f).is_file() for f in s["files"]) for s in stylised["slots"])
    assert copy["objects"]["Body"]["vertices"] == before["objects"]["Body"]["vertices"]
