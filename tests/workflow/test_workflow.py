"""The Snakemake workflow: DAG of the default config, a smoke run, --keep-going on bad input."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from conftest import REPO, SMOKE, assert_not_blank, browser_check, job_counts, mesh_work_dir, run_snakemake, smoke_run

from stages.config.workflow import WorkflowConfig, load_config_file
from stages.core.device import bf16_choice
from stages.geometry.raycache import RayCache

#: the smoke grid's meshes (the knot decimated), prompts (wood with levels of detail) and variants
MESHES, PROMPTS, VARIANTS = ("vase", "knot"), ("wood", "gold"), ("full", "second")
CELLS = [(m, p, v) for m in MESHES for p in PROMPTS for v in VARIANTS]


def test_dry_run_default_config(tmp_path):
    # no --configfile: the Snakefile's default experiment (config/config.yaml, relative to the
    # working directory), so run from a copy of the config folder
    (tmp_path / "config").mkdir()
    (tmp_path / "config" / "config.yaml").write_text((REPO / "config" / "config.yaml").read_text())
    proc = run_snakemake(tmp_path, "-n", "--cores", "2")
    assert proc.returncode == 0, proc.stderr
    counts = job_counts(proc.stdout)
    assert counts == {
        "normalize": 3,
        "raycache": 3,
        "optimize": 6,
        "bake": 6,
        "export": 6,
        "relight": 6,
        "metrics": 6,
        "report": 1,
        "pack": 1,
        "html_report": 1,
        "all": 1,
        "total": 40,
    }


def test_configfile_replaces_default_and_dag_is_per_mesh(tmp_path):
    """2 meshes x 2 prompts x 2 variants: mesh stages still run once per mesh."""
    (tmp_path / "config").mkdir()
    (tmp_path / "config" / "config.yaml").write_text((REPO / "config" / "config.yaml").read_text())
    proc = run_snakemake(tmp_path, "-n", "--cores", "2", "--configfile", str(SMOKE))
    assert proc.returncode == 0, proc.stderr
    counts = job_counts(proc.stdout)
    assert counts["normalize"] == len(MESHES) and counts["raycache"] == len(MESHES) and counts["decimate"] == 1
    for rule in ("optimize", "bake", "export", "relight", "metrics"):
        assert counts[rule] == len(CELLS), rule
    assert counts["report"] == counts["pack"] == counts["html_report"] == 1
    assert counts["lod"] == len(MESHES) * len(VARIANTS)  # levels of detail: the wood prompt's cells only
    assert "silver" not in proc.stdout  # the default config's prompts are not merged in


@pytest.mark.parametrize("single_file", [False, True])
def test_html_report_outputs_follow_its_form(tmp_path, single_file):
    """As a folder the HTML report declares its cell pages and viewer folders; as one file, only
    index.html; the report settings reach both report jobs."""
    extra = tmp_path / "form.yaml"
    extra.write_text(yaml.safe_dump({"report": {"single_file": single_file, "reference": "second"}}))
    proc = run_snakemake(tmp_path, "-n", "-p", "--cores", "2", "--configfile", str(SMOKE), str(extra))
    assert proc.returncode == 0, proc.stderr
    block = proc.stdout[proc.stdout.index("rule html_report:") :]
    outputs = block[block.index("output:") : block.index("\n", block.index("output:"))]
    assert "results/smoke/report/index.html" in outputs
    assert ("results/smoke/report/cells" in outputs) != single_file
    assert ("results/smoke/report/viewer" in outputs) != single_file
    assert proc.stdout.count('"reference": "second"') == 2  # report and html_report
    assert proc.stdout.count(f'"single_file": {str(single_file).lower()}') == 2


TORCH_RULES = ("optimize", "bake", "relight", "metrics", "lod", "roundtrip")


@pytest.mark.parametrize("device", ["cuda", "cpu"])
def test_device_reaches_every_torch_job_and_gpu_jobs_ask_for_the_gpu(tmp_path, device):
    """``device`` goes to every torch stage's ``--device``; on a GPU each of their jobs asks for
    gpu=1, and the workflow profile (loaded by default) holds the limit of one at a time."""
    proc = run_snakemake(tmp_path, "-n", "-p", "--cores", "2", "--configfile", str(SMOKE), "--config", f"device={device}")
    assert proc.returncode == 0, proc.stderr
    assert "Using workflow specific profile profiles/default" in proc.stdout + proc.stderr
    jobs = re.findall(r"^(?:local)?rule (\w+):\n(.*?)(?:\n\n|\Z)", proc.stdout, re.S | re.M)
    torch_jobs = [body for rule, body in jobs if rule in TORCH_RULES]
    # optimize, bake, relight, metrics per cell; lod for the wood cells
    assert len(torch_jobs) == len(CELLS) * 4 + len(MESHES) * len(VARIANTS)
    for body in torch_jobs:
        assert f"gpu={int(device == 'cuda')}" in body, body
        assert f"--device {device}" in body, body
    assert all("gpu=" not in body for rule, body in jobs if rule not in TORCH_RULES)
    profile = yaml.safe_load((REPO / "profiles" / "default" / "config.yaml").read_text())
    assert profile["resources"] == ["gpu=1"]


def test_gpu_jobs_without_torch(tmp_path):
    """``auto`` asks for the GPU only where the NVIDIA driver lists one (decided without torch)."""
    cfg = load_config_file(SMOKE)
    driver = tmp_path / "gpus"
    assert cfg.device == "auto" and cfg.gpu_jobs(driver) == 0
    driver.mkdir()
    assert cfg.gpu_jobs(driver) == 0
    (driver / "0000:01:00.0").mkdir()
    assert cfg.gpu_jobs(driver) == 1


def test_optimize_jobs_take_their_guidance_modes_threads(tmp_path, monkeypatch):
    """On a CPU run a CLIP-guided cell's optimize job takes two threads and an image-guided one
    one (two of them then run side by side on two cores); on a GPU run every one takes two."""
    cfg = yaml.safe_load(SMOKE.read_text())
    cfg["variants"]["second"]["optimize"].update(guidance="image", target_renderer="sg")
    path = tmp_path / "threads.yaml"
    path.write_text(yaml.safe_dump(cfg))
    proc = run_snakemake(tmp_path, "-n", "-p", "--cores", "2", "--configfile", str(path), "--config", "device=cpu")
    assert proc.returncode == 0, proc.stderr
    jobs = re.findall(r"^(?:local)?rule (\w+):\n(.*?)(?:\n\n|\Z)", proc.stdout, re.S | re.M)
    threads = {
        re.search(r"variant=(\w+)", body)[1]: re.search(r"--threads (\d+)", body)[1] for rule, body in jobs if rule == "optimize"
    }
    assert threads == {"full": "2", "second": "1"}, threads
    loaded = load_config_file(path)
    assert (loaded.optimize_threads("wood", "full"), loaded.optimize_threads("wood", "second")) == (2, 1)
    monkeypatch.setattr(WorkflowConfig, "gpu_jobs", lambda self: 1)
    assert loaded.optimize_threads("wood", "second") == 2


def test_face_budget_mode_reads_the_mesh_cache_settings(tmp_path):
    """``decimate.mode: budget`` inserts the decimate stage, hands it the mesh's own ray-cache
    settings (which set the budget: a cache edit reruns it) and traces its output; a mesh
    decimated to a face count gets no cache settings (a cache edit does not rerun it)."""
    cfg = yaml.safe_load(SMOKE.read_text())
    cfg["meshes"]["vase"] = {"builtin": "vase", "decimate": {"enabled": True, "mode": "budget"}, "raycache": {"resolution": 40}}
    path = tmp_path / "budget.yaml"
    path.write_text(yaml.safe_dump(cfg))
    proc = run_snakemake(tmp_path, "-n", "-p", "--cores", "2", "--configfile", str(path))
    assert proc.returncode == 0, proc.stderr
    assert job_counts(proc.stdout)["decimate"] == 2
    jobs = re.findall(r"^(?:local)?rule (\w+):\n(.*?)(?:\n\n|\Z)", proc.stdout, re.S | re.M)
    decimations = {("vase/" in body): body for rule, body in jobs if rule == "decimate"}
    assert "--raycache-settings" in decimations[True] and '"resolution": 40' in decimations[True]
    assert '"views"' not in decimations[True]  # only what the budget reads: other cache edits do not rerun it
    assert "--raycache-settings" not in decimations[False]
    traced = [body for rule, body in jobs if rule == "raycache" and "vase/" in body]
    assert len(traced) == 1 and re.search(r"meshes/vase/[0-9a-f]{12}/decimate/mesh.ply", traced[0])


def test_invalid_config_fails_at_dag_build(tmp_path):
    bad = yaml.safe_load(SMOKE.read_text())
    bad["raycache"]["resoluton"] = 64
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(bad))
    proc = run_snakemake(tmp_path, "-n", "--cores", "1", "--configfile", str(path))
    assert proc.returncode != 0
    out = proc.stdout + proc.stderr
    assert "invalid configuration" in out and "'resoluton'" in out and str(path) in out


def check_test_only_marks(res) -> None:
    """Every file of every cell made from the test-only CLIP says so: each stage's metadata, the
    GLB's asset.extras, both USD files' layer metadata, the asset index, the pack's README, the
    summary (CSV and JSON) and the HTML report."""
    import zipfile

    import pandas as pd
    import pygltflib
    from pxr import Usd

    cells = CELLS
    for mesh, prompt, variant in cells:
        cell = res / mesh / prompt / variant
        origins = [
            json.loads((cell / rel).read_text())["origin"]
            for rel in (
                "optimize/meta.json",
                "bake/meta.json",
                "export/meta.json",
                "relight/meta.json",
                "metrics/meta.json",
                "metrics/metrics.json",
            )
        ]
        for origin in origins:
            assert origin == origins[0], cell
            assert origin["test_only"] is True and origin["label"].startswith("TEST ONLY") and "TEST ONLY" in origin["weights"]
        glb = pygltflib.GLTF2().load(str(cell / "export" / "model.glb"))
        assert glb.asset.extras["tango_stylize"] == origins[0]
        for name in ("model.usda", "model.usdz"):
            stage = Usd.Stage.Open(str(cell / "export" / name))  # keep the stage: it owns the layer
            layer = stage.GetRootLayer()
            assert layer.customLayerData["tango_stylize"]["test_only"] is True, (cell, name)
            assert "TEST ONLY" in layer.documentation
    index = pd.read_csv(res / "report" / "asset_index.csv")
    assert len(index) == len(cells) and index["test_only"].all() and index["origin"].str.startswith("TEST ONLY").all()
    with zipfile.ZipFile(res / "report" / "asset_pack.zip") as z:
        readme = z.read("README.txt").decode()
        inner = pd.read_csv(z.open("index.csv"))
    assert inner["test_only"].all()
    assert readme.startswith("tango-stylize asset pack") and f"WARNING: TEST ONLY. {len(cells)} of {len(cells)}" in readme
    for mesh, prompt, variant in cells:
        assert f"- {mesh}/{prompt}/{variant}: TEST ONLY" in readme
    summary = pd.read_csv(res / "report" / "summary.csv")
    assert summary["test_only_weights"].all() and summary["origin"].str.startswith("TEST ONLY").all()
    # each mesh's self-occlusion, from its raycache stage: shares of a hemisphere
    assert summary["self_occlusion_median"].between(0.0, 1.0).all() and summary["self_occlusion_p95"].between(0.0, 1.0).all()
    assert all(
        r["test_only_weights"] and r["origin"].startswith("TEST ONLY")
        for r in json.loads((res / "report" / "summary.json").read_text())
    )
    page = (res / "report" / "index.html").read_text()
    assert f"TEST ONLY: {len(cells)} of {len(cells)} cells" in page
    for mesh, prompt, variant in cells:
        cell_page = (res / "report" / "cells" / mesh / prompt / variant / "index.html").read_text()
        assert "TEST ONLY: 1 of 1 cells" in cell_page and "<p class='banner note'>TEST ONLY: made with random" in cell_page


@pytest.mark.slow(minutes=6)
def test_smoke_run(tmp_path_factory, tmp_path):
    """The smoke grid's run (:func:`conftest.smoke_run`, shared with the Slurm grid test), its
    outputs, the report in a browser, and a second run with nothing to do."""
    proc = smoke_run(tmp_path_factory)
    assert proc.returncode == 0, proc.stderr[-3000:]
    work = proc.workdir  # the run's folder (shared: read it only); screenshots go to tmp_path
    # the experiment's cells and report in results/smoke (the config's `experiment`), mesh-level
    # work in results/meshes/<mesh>/<key>/<stage>
    res = work / "results" / "smoke"
    # the plan, printed before the first job: the cells, the jobs to run, the device, an estimate
    plan = proc.stderr[proc.stderr.index("Plan of experiment smoke") :]
    assert "2 meshes x 2 prompts x 2 variants = 8 cells" in plan and "(device: auto)" in plan
    assert "to run now" in plan and "optimize 8" in plan and "Estimated wall time on this machine" in plan
    assert "on 2 cores (jobs side by side as their threads allow)" in plan  # Snakemake's --cores
    # progress: each optimisation's short line reaches Snakemake's terminal; the logs have theirs
    for cell in ("vase/wood/full", "knot/gold/second"):
        assert f"[optimize {cell}] 3/3 it, " in proc.stdout, proc.stdout[-2000:]
    assert "optimize vase/wood/full: 3/3 it (100%)" in (res / "vase/wood/full/logs/optimize.log").read_text()
    assert "bake vase/wood/full: unwrapping and baking" in (res / "vase/wood/full/logs/bake.log").read_text()
    for mesh in MESHES:
        raycache = mesh_work_dir(work, mesh, "raycache")
        meta = json.loads((raycache / "meta.json").read_text())
        assert meta["stats"]["train"]["views"] == 4 and meta["stats"]["eval"]["views"] == 8
        assert meta["stats"]["train"]["width"] == 48
        cache = RayCache(raycache / "train.npz")
        assert len(cache) == 4 and cache.arrays["offsets"][-1] > 0
        assert np.abs(np.linalg.norm(cache.view(0).point, axis=1)).max() <= 1.0 + 1e-3
        for stage in ("normalize", "raycache"):
            mesh_dir = mesh_work_dir(work, mesh, stage).parent
            assert " INFO " in (mesh_dir / "logs" / f"{stage}.log").read_text()
            assert (mesh_dir / "benchmarks" / f"{stage}.tsv").is_file()
        tf = json.loads((mesh_work_dir(work, mesh, "normalize") / "transform.json").read_text())
        assert len(tf["inverse_matrix"]) == 4
    # the knot is decimated and traced at the decimated level; the vase is not decimated
    decimate = mesh_work_dir(work, "knot", "decimate")
    dec = json.loads((decimate / "meta.json").read_text())
    assert abs(dec["stats"]["faces_after"] - 3000) <= 30
    knot_cache = mesh_work_dir(work, "knot", "raycache")
    traced = json.loads((knot_cache / "meta.json").read_text())
    assert traced["inputs"]["mesh"]["path"].endswith(str(decimate.relative_to(work) / "mesh.ply"))
    assert len(RayCache(knot_cache / "train.npz").arrays["faces"]) == dec["stats"]["faces_after"]
    assert not list((work / "results" / "meshes" / "vase").glob("*/decimate"))
    # every grid cell optimised, with outputs marked as made by the test-only CLIP
    for mesh, prompt, variant in CELLS:
        cell = res / mesh / prompt / variant / "optimize"
        meta = json.loads((cell / "meta.json").read_text())
        assert meta["test_only_weights"] is True and "TEST ONLY" in meta["weights"]
        # bf16: auto, decided where the job ran (this machine): bfloat16 where it is native
        assert meta["clip_precision"] == bf16_choice("auto", torch.device("cpu"), "bf16")[1]
        # compile_shading: auto, and 3 iterations do not repay a compilation
        assert meta["shading_path"].startswith("eager (auto: 3 iterations")
        assert meta["prompt"] == f"a {mesh} made of {prompt}"
        assert (cell / "renders" / "rgb.png").is_file() and (cell / "field.pt").is_file()
        assert not (cell / "checkpoint.pt").exists()
    # the report closes the main job: one summary row per cell, the overview, the asset pack
    import pandas as pd

    summary = pd.read_csv(res / "report" / "summary.csv")
    assert len(summary) == len(CELLS) and set(summary["weights"]) == {"test-only random"}
    assert summary["eval_test_only"].all() and (summary["r_precision_candidates"] == len(PROMPTS)).all()
    assert summary["clip_score"].notna().all()
    assert (summary["usd_validation_errors"] == 0).all() and (summary["bake_psnr_db"] >= 35).all()
    assert (
        summary.loc[summary["mesh"] == "knot", "faces_after"].iloc[0]
        < summary.loc[summary["mesh"] == "knot", "faces_before"].iloc[0]
    )
    for name in ("overview.png", "asset_pack.zip", "index.html", "viewer/cell.js", "cells/knot/gold/second/model.glb"):
        assert (res / "report" / name).is_file(), name
    assert "TEST ONLY" in (res / "report" / "index.html").read_text()
    # the figures compare like with like: per mesh x prompt, "second" (normal network off) is an
    # ablation of "full"; no mesh has a decimated twin, so there is no robustness figure, and why
    figures = json.loads((res / "report" / "figures.json").read_text())
    drawn = {e["file"] for e in figures["figures"] if "file" in e}
    assert {"figures/speed_accuracy.png", "figures/ablations.png", "figures/loss_curves.png", "figures/grid_vase.png"} <= drawn
    assert all((res / "report" / f).is_file() for f in drawn)
    skipped = {e["title"]: e["skipped"] for e in figures["figures"] if "skipped" in e}
    skipped_robustness = skipped["Robustness: each mesh beside its decimated versions"]
    assert "decimated version" in skipped_robustness
    assert len(figures["groups"]) == len(MESHES) * len(PROMPTS) and all(g["ablations"] == ["second"] for g in figures["groups"])
    # the real report's pages in a browser: the index and a cell page with its viewer
    r = browser_check("index", res / "report" / "index.html", tmp_path / "index.png", "--filter", "knot gold")
    assert r["errors"] == [] and r["rows"] == len(CELLS) and r["filtered_rows"] == len(VARIANTS)
    assert r["skipped"] == [f"Not drawn: {skipped_robustness}."]
    r = browser_check("cell", res / "report" / "cells" / "knot" / "gold" / "second" / "index.html", tmp_path / "cell.png")
    assert r["errors"] == [] and r["loaded"] == 1 and r["environment"].endswith("#light.hdr")
    assert_not_blank(tmp_path / "cell.png")
    check_downloads(res, ("knot", "gold", "second"), tmp_path / "downloads")
    for rel in ("export/model.usdz", "export/model.glb", "relight/material_edit.png"):
        assert (res / "vase" / "wood" / "full" / rel).is_file()
    check_test_only_marks(res)
    # levels of detail for the wood cells only (a prompt-level override), packed with their assets
    import zipfile

    for mesh in MESHES:
        for prompt in PROMPTS:
            lod = res / mesh / prompt / "full" / "lod"
            assert (lod / "meta.json").is_file() == (prompt == "wood"), lod
        meta = json.loads((res / mesh / "wood" / "second" / "lod" / "meta.json").read_text())
        faces = [r["faces"] for r in meta["stats"]["levels"]]
        assert len(faces) == 3 and faces[0] > faces[1] > faces[2]
        assert meta["origin"]["test_only"] is True
    with zipfile.ZipFile(res / "report" / "asset_pack.zip") as z:
        names = set(z.namelist())
    assert "knot/wood/full/lod/model_lods.usdz" in names and "knot/wood/full/lod/lod2/model.glb" in names
    assert not any("/gold/" in n and "/lod/" in n for n in names)
    index = pd.read_csv(res / "report" / "asset_index.csv")
    assert index.loc[index["prompt"] == "wood", "lod_levels"].str.startswith("lod0:").all()
    assert index.loc[index["prompt"] != "wood", "lod_levels"].isna().all()
    # nothing half-written anywhere
    assert not list(res.parent.rglob(".*.tmp-*")) and not list(res.parent.rglob(".staging-*"))
    # a second run has nothing to do
    again = run_snakemake(work, "--cores", "2", "--configfile", str(SMOKE))
    assert again.returncode == 0 and "Nothing to be done" in again.stdout + again.stderr


@pytest.mark.slow(minutes=1)
def test_keep_going_finishes_other_meshes(tmp_path):
    cfg = yaml.safe_load(SMOKE.read_text())
    cfg["meshes"] = {"vase": {"builtin": "vase"}, "broken": {"path": str(tmp_path / "missing.obj")}}
    # one cell per mesh is enough to show the good mesh's work going on (the smoke run covers the grid)
    cfg["prompts"] = {"wood": "a {object} made of wood"}
    cfg["variants"] = {"full": {}}
    path = tmp_path / "cfg.yaml"
    path.write_text(yaml.safe_dump(cfg))
    proc = run_snakemake(tmp_path, "--cores", "2", "--keep-going", "--configfile", str(path))
    assert proc.returncode != 0
    assert "not found" in proc.stdout + proc.stderr  # the DAG-time warning
    res = tmp_path / "results"
    assert (mesh_work_dir(tmp_path, "vase", "raycache") / "meta.json").is_file()
    assert (res / cfg["experiment"] / "vase" / "wood" / "full" / "export" / "meta.json").is_file()
    broken = tmp_path / "results" / "meshes" / "broken" / WorkflowConfig(cfg).mesh_work_keys("broken")["normalize"]
    assert not (broken / "normalize" / "mesh.ply").exists()
    log = (broken / "logs" / "normalize.log").read_text()
    assert "missing.obj: file not found" in log


def check_downloads(res: Path, cell: tuple[str, str, str], into: Path) -> None:
    """A cell page's download links, clicked in Chromium over HTTP: the GLB passes the Khronos
    validator, the USDZ usd-core's validators, the texture zip holds the export's PNGs, and the asset
    pack holds the cell's files; the run summary on the index links the same pack."""
    import functools
    import http.server
    import threading
    import zipfile

    from PIL import Image

    from stages.assets.formats.gltf import validate_glb
    from stages.assets.formats.usd import validate_usd

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args):
            pass

    into.mkdir(parents=True)
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Quiet, directory=str(res / "report")))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        url = f"http://127.0.0.1:{server.server_address[1]}/cells/{'/'.join(cell)}/index.html"
        r = browser_check("downloads", url, into / "page.png", "--into", str(into))
    finally:
        server.shutdown()
    assert r["errors"] == [], r["errors"]
    got = {d["suggested"]: Path(d["saved"]) for d in r["downloads"] if d["failure"] is None}
    assert sorted(got) == ["asset_pack.zip", "model.glb", "model.usdz", "textures.zip"], r["downloads"]
    glb = validate_glb(got["model.glb"])
    assert glb["ran"] and glb["errors"] == 0, glb
    usd = validate_usd(got["model.usdz"])
    assert usd["validators"] > 0 and usd["errors"] == 0, usd["messages"]
    export = res.joinpath(*cell, "export")
    with zipfile.ZipFile(got["textures.zip"]) as z:
        assert sorted(z.namelist()) == sorted(f"textures/{p.name}" for p in (export / "textures").glob("*.png"))
        for name in z.namelist():
            assert Image.open(z.open(name)).size[0] > 0
    with zipfile.ZipFile(got["asset_pack.zip"]) as z:
        assert f"{'/'.join(cell)}/model.glb" in z.namelist() and "index.csv" in z.namelist()
    assert got["model.glb"].read_bytes() == (export / "model.glb").read_bytes()
    index = (res / "report" / "index.html").read_text()
    assert "<h2>This run</h2>" in index and "href='asset_pack.zip' download" in index
