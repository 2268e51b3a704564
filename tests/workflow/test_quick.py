"""One's own mesh without YAML: ``python -m stages.quick MESH "PROMPT"`` checks the mesh, writes an
ordinary experiment config, says what will run and runs it; bad input stops before anything is
written or run. (Its image-guided run on a fresh machine: tests/workflow/test_fresh_machine.py.)"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from conftest import REPO, TINY, TINY_OPTIMIZE, shared_mesh, snakemake_env
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st


def quick(cwd: Path, *args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    env = env or {**snakemake_env(cwd), "TANGO_PLAN_CALIBRATE": "0"}
    env.pop("PYTHONPATH", None)
    return subprocess.run(
        [sys.executable, "-m", "stages.quick", *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=900
    )


@pytest.mark.slow(minutes=1)
def test_test_clip_run_on_an_open_shared_mesh(tmp_path):
    """spot (open seams, a missing .mtl) with the tiny test CLIP: every output says TEST ONLY, and
    the experiment's report lists the cell like any other."""
    mesh = shared_mesh("spot.obj")
    overlay = tmp_path / "tiny.yaml"
    overlay.write_text(yaml.safe_dump({**TINY, "prompts": {"a-cow-made-of-gold": {"optimize": TINY_OPTIMIZE}}}))
    proc = quick(tmp_path, str(mesh), "a cow made of gold", "--test-clip", "--name", "spot-gold", "--overlay", str(overlay))
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert "the tiny random test CLIP (results marked TEST ONLY)" in proc.stdout
    config = yaml.safe_load((tmp_path / "config" / "quick" / "spot-gold.yaml").read_text())
    assert config["optimize"] == {"clip_tiny_test": True} and config["metrics"] == {"clip_tiny_test": True}
    assert config["prompts"]["a-cow-made-of-gold"] == {"text": "a cow made of gold", "preset": "fast"}
    cell = tmp_path / "results" / "spot-gold" / "spot" / "a-cow-made-of-gold" / "base"
    meta = json.loads((cell / "optimize" / "meta.json").read_text())
    assert meta["settings"]["clip_tiny_test"] and meta["settings"]["iterations"] == 3
    assert "TEST ONLY" in json.dumps(meta["origin"])
    index = (tmp_path / "results" / "spot-gold" / "report" / "index.html").read_text()
    assert "TEST ONLY: 1 of 1 cells" in index and "a-cow-made-of-gold" in index
    # spot's own UV layout is usable: the workflow hands the input to the bake and the export
    assert "UV layout: the input's own (usable: 13 islands" in proc.stdout
    bake = json.loads((cell / "bake" / "meta.json").read_text())["stats"]
    assert bake["uv"]["layout"] == "kept" and bake["uv_layout"] == "kept"
    assert (cell / "export" / "model.obj").is_file() and (cell / "export" / "model.mtl").is_file()
    assert "UV layout" in index and ">kept<" in index


def test_without_weights_it_stops_at_once_with_one_message_per_model(tmp_path):
    hf = {"HF_HUB_OFFLINE": "1", "HF_HOME": str(tmp_path / "hf"), "HF_HUB_CACHE": str(tmp_path / "hf" / "hub")}
    env = {**snakemake_env(tmp_path), "TANGO_PLAN_CALIBRATE": "0", **hf}
    t0 = time.perf_counter()
    proc = quick(tmp_path, str(REPO / "tests" / "data" / "absent.obj"), "a vase made of gold", env=env)
    assert proc.returncode == 2 and "file not found" in proc.stderr  # the mesh is checked first
    # named on the command line, before there is any config: the advice says so
    assert "Check the mesh path in the command" in proc.stderr and "in the config" not in proc.stderr
    mesh = tmp_path / "pot.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n")
    proc = quick(tmp_path, str(mesh), "a pot made of gold", env=env)
    out = proc.stdout + proc.stderr
    assert proc.returncode != 0 and time.perf_counter() - t0 < 120, out[-3000:]
    assert "CLIP ViT-B-32 (needs its weights)" in proc.stdout
    assert "2 of the CLIP models this run needs cannot be loaded; nothing was run." in out
    assert "The guidance CLIP" in out and "The evaluation CLIP" in out
    assert not (tmp_path / "results").exists()
    # --dry-run: the config and the plan, nothing run
    proc = quick(tmp_path, str(mesh), "a pot made of gold", "--dry-run", env=env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "Plan of experiment pot-a-pot-made-of-gold" in proc.stdout and "1 optimisation(s) of 300 steps" in proc.stdout
    assert "on 2 cores (jobs side by side" in proc.stdout  # quick's --cores reach the plan
    assert not (tmp_path / "results").exists()


def test_bad_input_is_refused_before_anything_is_written(tmp_path):
    empty = tmp_path / "empty.obj"
    empty.write_text("")
    proc = quick(tmp_path, str(empty), "a vase made of wood")
    assert proc.returncode == 2 and str(empty) in proc.stderr and "file is empty" in proc.stderr
    mesh = tmp_path / "pot.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n")
    proc = quick(tmp_path, str(mesh), "a pot", "--preset", "fastest")
    assert proc.returncode == 2 and "unknown preset 'fastest': use one of balanced, fast, metal, paper, rough" in proc.stderr
    proc = quick(tmp_path, str(mesh), "a pot", "--image-guided", "gold")
    assert proc.returncode == 2 and "use one of wood, metal, chrome, plaster" in proc.stderr
    proc = quick(tmp_path, str(mesh), "a pot", "--name", "my pot")
    assert proc.returncode == 2 and "'my-pot'" in proc.stderr
    proc = quick(tmp_path, str(mesh), "   ")
    assert proc.returncode == 2 and "the prompt is empty" in proc.stderr
    assert not (tmp_path / "config").exists() and not (tmp_path / "results").exists()
    # an existing config of the same name with other settings is kept
    (tmp_path / "config" / "quick").mkdir(parents=True)
    mine = tmp_path / "config" / "quick" / "pot.yaml"
    mine.write_text("# my edits\nexperiment: pot\n")
    proc = quick(tmp_path, str(mesh), "a pot made of wood", "--image-guided", "wood", "--name", "pot", "--dry-run")
    assert proc.returncode == 2 and "exists with other settings" in proc.stderr and "--force" in proc.stderr
    assert mine.read_text() == "# my edits\nexperiment: pot\n"
    # names another experiment owns: a config of the repository's, results another config made
    (tmp_path / "config" / "tiny.yaml").write_text("experiment: tiny\n")
    proc = quick(tmp_path, str(mesh), "a pot", "--name", "tiny", "--dry-run")
    assert proc.returncode == 2 and "is config/tiny.yaml's: pick another --name" in proc.stderr
    (tmp_path / "results" / "other").mkdir(parents=True)
    proc = quick(tmp_path, str(mesh), "a pot", "--name", "other", "--dry-run")
    assert proc.returncode == 2 and "results/other/ holds another config's experiment" in proc.stderr
    assert sorted(p.name for p in (tmp_path / "config" / "quick").iterdir()) == ["pot.yaml"]


def test_ids_built_ins_overlays_and_a_second_run(tmp_path):
    """Ids from any file name or prompt, a built-in mesh, an overlay with its own variants, and the
    same command twice (the config, comments and all, left as it is)."""
    from stages.quick import slug

    assert slug("a vase made of wood", 40) == "a-vase-made-of-wood" and slug("Stühle aus Holz", 40) == "Stuhle-aus-Holz"
    assert slug("木の花瓶", 40) != slug("金の花瓶", 40) and slug("木の花瓶", 40).startswith("x-")
    assert slug("-glossy", 40) == "glossy" and len(slug("a" * 500, 40)) == 40
    report_mesh = tmp_path / "report.obj"
    report_mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n")
    overlay = tmp_path / "variants.yaml"
    overlay.write_text(yaml.safe_dump({"variants": {"hi": {"preset": "balanced"}}}))
    args = (str(report_mesh), "一个木花瓶", "--test-clip", "--overlay", str(overlay), "--dry-run")
    proc = quick(tmp_path, *args)
    assert proc.returncode == 0, proc.stderr[-2000:]
    (written,) = (tmp_path / "config" / "quick").iterdir()
    config = yaml.safe_load(written.read_text())
    assert list(config["meshes"]) == ["report-mesh"]  # not the report's own folder
    (prompt_id,) = config["prompts"]
    assert prompt_id == slug("一个木花瓶", 40) and written.stem == f"report-mesh-{prompt_id}"
    assert "1 mesh x 1 prompt x 1 variant = 1 cell" in proc.stdout  # the overlay's variant, no 'base' assumed
    # the same command again: nothing rewritten (a comment added by hand survives)
    written.write_text(written.read_text() + "# my note\n")
    assert quick(tmp_path, *args).returncode == 0 and written.read_text().endswith("# my note\n")
    proc = quick(tmp_path, "builtin:knot", "a knot made of wood", "--image-guided", "wood", "--dry-run")
    assert proc.returncode == 0, proc.stderr[-2000:]
    config = yaml.safe_load((tmp_path / "config" / "quick" / "knot-a-knot-made-of-wood.yaml").read_text())
    assert config["meshes"] == {"knot": {"builtin": "knot"}}


def test_a_mesh_past_the_face_limit_a_reserved_name_and_a_folder_with_spaces(tmp_path, monkeypatch, capsys):
    """In process: the quick command refuses a mesh the normalize stage would refuse (its face
    limit, here lowered by an overlay) before writing anything; ``Report.obj`` gets an id the
    config accepts (ids are reserved in any case); the commands it prints quote a config folder
    with spaces."""
    from stages import quick as q

    monkeypatch.chdir(tmp_path)
    mesh = tmp_path / "pot.obj"  # an octahedron: 8 faces
    corners = "v 1 0 0\nv -1 0 0\nv 0 1 0\nv 0 -1 0\nv 0 0 1\nv 0 0 -1\n"
    faces = "f 1 3 5\nf 3 2 5\nf 2 4 5\nf 4 1 5\nf 3 1 6\nf 2 3 6\nf 4 2 6\nf 1 4 6\n"
    mesh.write_text(corners + faces)
    overlay = tmp_path / "small.yaml"
    overlay.write_text("normalize: {max_faces: 4}\n")
    configs = tmp_path / "my configs"
    assert q.main([str(mesh), "a pot", "--overlay", str(overlay), "--config-dir", str(configs), "--dry-run"]) == 2
    assert "has 8 faces, more than normalize.max_faces (4)" in capsys.readouterr().err and not configs.exists()
    assert q.mesh_entry(str(tmp_path / "Report.obj"))[0] == "Report-mesh"
    assert q.mesh_entry(str(tmp_path / "REPORT.obj"))[0] == "REPORT-mesh"
    monkeypatch.setenv("TANGO_PLAN_CALIBRATE", "0")
    assert q.main([str(mesh), "a pot", "--image-guided", "wood", "--config-dir", str(configs), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert f"--configfile '{configs}/pot-a-pot.yaml'" in out, out
    assert (configs / "pot-a-pot.yaml").read_text().startswith(q.HEADER)


#: what YAML reads as a line break or what makes a name look other than it is: C0 and C1 controls
#: (U+0085 among them), line and paragraph separators, bidirectional overrides and isolates
HOSTILE = [chr(c) for c in (*range(0, 32), 127, *range(128, 160), 0x2028, 0x2029, *range(0x202A, 0x202F), *range(0x2066, 0x206A))]


def test_a_folder_name_cannot_write_config_keys(tmp_path, monkeypatch, capsys):
    """A parent folder named with a character YAML reads as a line break, then a template key and
    an expression: refused in one line naming the character, and no config is written (it used
    to leave the header's comment and become top-level YAML that Snakemake evaluated)."""
    from stages import quick as q

    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("TANGO_PLAN_CALIBRATE", "0")
    for sep in ("\u2028", "\u2029", "\x85"):
        folder = tmp_path / f"x{sep}__use_yte__: true{sep}? __import__('os').getcwd() : 1{sep}"
        folder.mkdir()
        (folder / "pot.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 3 4\nf 1 4 2\nf 2 4 3\n")
        code = q.main([str(folder / "pot.obj"), "a pot", "--image-guided", "wood", "--dry-run"])
        err = capsys.readouterr().err
        assert code == 2 and f"U+{ord(sep):04X}" in err, err
        assert len(err.strip().splitlines()) == 1 and not Path("config").exists()


@settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))
@given(st.sampled_from(HOSTILE), st.integers(0, 3), st.sampled_from(["folder", "stem", "prompt"]))
def test_the_written_config_loads_to_exactly_its_keys(char, at, where):
    """Property: whatever a path or a prompt holds, in whichever position, the written file loads
    (by YAML and by the project's reader) to exactly the config written, and its comments hold no
    text from the command line; the config check refuses such a path in one line naming it."""
    import tempfile

    from stages import quick as q
    from stages.config.workflow import WorkflowConfig, read_yaml
    from stages.core.errors import ConfigError

    def put(text: str) -> str:
        i = min(at, len(text))
        return text[:i] + char + text[i:]

    folder = put("meshes") if where == "folder" else "meshes"
    stem = put("pot") if where == "stem" else "pot"
    prompt = put("a pot of wood") if where == "prompt" else "a pot of wood"
    mesh = f"/data/{folder}/{stem}.obj"
    config = {
        "experiment": "e",
        "meshes": {"pot": {"path": mesh, "object": stem}},
        "prompts": {"p": {"text": prompt, "preset": "fast"}},
        "optimize": {"clip_tiny_test": True},
    }
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "e.yaml"
        q.write_config(config, path)
        text = path.read_text(encoding="utf-8")
        assert yaml.safe_load(text) == config and read_yaml(path) == config
        comments = [ln for ln in text.splitlines() if ln.startswith("#")]
        assert "\n".join(comments) + "\n" == q.HEADER
    if where == "prompt":
        return  # a prompt goes into the config as an escaped value; the config check has its own rules
    for refuse in (lambda: q.check_path_argument("the mesh", mesh, mesh=True), lambda: WorkflowConfig(config)):
        with pytest.raises(ConfigError) as err:
            refuse()
        assert "\n" not in str(err.value) and f"U+{ord(char):04X}" in str(err.value), str(err.value)


def test_the_uv_layout_is_decided_and_said_before_anything_runs(tmp_path):
    """``--uv``: the layout the bake will use, measured on the mesh as the normalize stage reads it,
    is printed with why; ``--uv keep`` on a mesh without a usable layout stops before anything is
    written."""
    import uvmeshes

    vase = tmp_path / "vase.obj"
    uvmeshes.write_obj(vase)
    proc = quick(tmp_path, str(vase), "a vase made of wood", "--test-clip", "--uv", "keep", "--dry-run")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "UV layout: the input's own (usable: " in proc.stdout
    (written,) = (tmp_path / "config" / "quick").iterdir()
    assert yaml.safe_load(written.read_text())["bake"] == {"uv": "keep"}
    bare = tmp_path / "pot.obj"
    bare.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n")
    proc = quick(tmp_path, str(bare), "a pot", "--test-clip", "--dry-run")
    said = "UV layout: a new atlas (auto: the input has no texture coordinates; and an OBJ holds one UV set"
    assert proc.returncode == 0 and said in proc.stdout
    # a glTF input without UVs takes a second set (its own document kept); an OBJ cannot hold one
    import trimesh

    trimesh.Trimesh(*uvmeshes.unwrapped()[::2], process=False).export(tmp_path / "bare.glb")
    proc = quick(tmp_path, str(tmp_path / "bare.glb"), "a pot", "--test-clip", "--dry-run")
    assert proc.returncode == 0 and "UV layout: a second UV set beside the input's own (auto: the input has no" in proc.stdout
    proc = quick(tmp_path, str(bare), "a pot", "--test-clip", "--uv", "second", "--name", "ps", "--dry-run")
    assert proc.returncode == 2 and "bake.uv: second, but an OBJ holds one UV set" in proc.stderr
    proc = quick(tmp_path, "builtin:vase", "a vase", "--test-clip", "--uv", "keep", "--name", "vk", "--dry-run")
    assert proc.returncode == 2 and "bake.uv: keep, but builtin:vase has no UV layout" in proc.stderr
    assert not (tmp_path / "config" / "quick" / "vk.yaml").exists()


def test_the_overlap_threshold_and_the_up_axis_from_the_command(tmp_path):
    """A layout folded over itself: ``--uv keep`` stops naming the threshold and the flag that
    raises it; with ``--uv-max-overlap 1`` it is kept, and the value and ``--up-axis`` land in the
    written config (the mesh's own ``normalize`` entry); a value out of range is one line."""
    import uvmeshes

    folded = tmp_path / "folded.glb"
    uvmeshes.skinned_glb(folded, fold=True)
    proc = quick(tmp_path, str(folded), "a vase", "--test-clip", "--uv", "keep", "--name", "f1", "--dry-run")
    assert proc.returncode == 2 and "(bake.uv_max_overlap: 0.01;" in proc.stderr, proc.stderr[-2000:]
    assert "or raise bake.uv_max_overlap (stages.quick: --uv-max-overlap) to bake over the overlap" in proc.stderr
    args = ("--test-clip", "--uv", "keep", "--uv-max-overlap", "1", "--up-axis", "+z", "--name", "f2", "--dry-run")
    proc = quick(tmp_path, str(folded), "a vase", *args)
    assert proc.returncode == 0 and "UV layout: the input's own (usable: " in proc.stdout, proc.stderr[-2000:]
    config = yaml.safe_load((tmp_path / "config" / "quick" / "f2.yaml").read_text())
    assert config["bake"] == {"uv": "keep", "uv_max_overlap": 1.0}
    assert config["meshes"]["folded"]["normalize"] == {"up_axis": "+z"}
    proc = quick(tmp_path, str(folded), "a vase", "--test-clip", "--uv-max-overlap", "2", "--name", "f3", "--dry-run")
    assert proc.returncode == 2 and "uv_max_overlap" in proc.stderr and "Traceback" not in proc.stderr
    assert (
        sum("ERROR" in line for line in proc.stderr.splitlines()) == 1
        and not (tmp_path / "config" / "quick" / "f3.yaml").exists()
    )


@pytest.mark.slow(minutes=1)
def test_a_rigged_animated_glb_through_the_workflow(tmp_path):
    """A skinned, animated, two-material GLB with its own UV layout through the whole workflow:
    its asset is its own document with new textures (skeleton, weights, animation, vertex order
    and UVs as they were), valid for the Khronos validator."""
    import pygltflib
    import uvmeshes

    mesh = tmp_path / "rigged.glb"
    uvmeshes.skinned_glb(mesh)
    overlay = tmp_path / "tiny.yaml"
    overlay.write_text(yaml.safe_dump({**TINY, "prompts": {"a-wooden-vase": {"optimize": TINY_OPTIMIZE}}}))
    proc = quick(tmp_path, str(mesh), "a wooden vase", "--test-clip", "--uv", "keep", "--name", "rig", "--overlay", str(overlay))
    assert proc.returncode == 0, proc.stderr[-4000:]
    cell = tmp_path / "results" / "rig" / "rigged" / "a-wooden-vase" / "base"
    a, b = pygltflib.GLTF2().load(str(mesh)), pygltflib.GLTF2().load(str(cell / "export" / "model.glb"))
    ja, jb = json.loads(a.to_json()), json.loads(b.to_json())
    for key in ("nodes", "skins", "animations", "meshes", "accessors"):
        keep = ("bufferView",) if key == "accessors" else ()
        strip = [{k: v for k, v in x.items() if k not in keep} for x in ja[key]]
        assert strip == [{k: v for k, v in x.items() if k not in keep} for x in jb[key]], key
    assert [m["name"] for m in jb["materials"]] == ["Body", "Rim"]
    export = json.loads((cell / "export" / "meta.json").read_text())["stats"]
    assert export["topology"].startswith("the input's own") and export["gltf_validation_errors"] == 0


def test_the_flags_list_their_choices_and_refuse_two_guidances(tmp_path):
    """``--help`` lists every preset with its steps; ``--image-guided`` and ``--test-clip`` together
    stop before anything is written (an unknown preset: test_bad_input_is_refused_before_anything_is_written)."""
    from stages.config.choices import preset_steps

    proc = quick(tmp_path, "--help")
    assert proc.returncode == 0
    text = " ".join(proc.stdout.split())
    for name, steps in preset_steps().items():
        assert f"{name} ({steps:,} steps" in text
    # with the optimisation's measured time: rough and metal cost what paper does (COST_KEYS)
    assert re.search(r"rough \(1,500 steps, [0-9.]+-[0-9.]+ (s|min) as paper\)", text), text
    assert "--uv-max-overlap" in text and "--up-axis" in text
    proc = quick(tmp_path, "builtin:vase", "a vase", "--image-guided", "wood", "--test-clip", "--dry-run")
    assert proc.returncode == 2 and "not allowed with argument" in proc.stderr
    assert not (tmp_path / "config").exists()
