"""Experiments live apart: each experiment's cells and report under results/<experiment>/, its
mesh-level work (normalize, decimate, raycache, target) under results/meshes/<mesh>/<key>/,
keyed by a digest of the settings that shape it and so shared by experiments that agree."""

from __future__ import annotations

import copy
import re

import pytest
import yaml
from conftest import run_snakemake

from stages.config.workflow import WorkflowConfig, experiment_name, main, settings_digest
from stages.core.errors import ConfigError

CACHE = {
    "views": 2,
    "resolution": 16,
    "eval_azimuths": 2,
    "eval_elevations_deg": [0.0],
    "eval_resolution": 16,
    "metrics_azimuths": 2,
    "metrics_elevations_deg": [0.0],
    "metrics_resolution": 16,
}
MAIN = {
    "meshes": {"vase": {"builtin": "vase"}, "candle": {"builtin": "candle"}},
    "prompts": {"wood": "a {object} made of wood"},
    "raycache": CACHE,
    "optimize": {"clip_tiny_test": True},
    "metrics": {"clip_tiny_test": True},
}


def ablation_config() -> dict:
    """Another experiment on the same meshes: the vase's mesh-level settings equal the main
    experiment's, the candle's ray cache is finer, and the prompts and variants differ."""
    cfg = copy.deepcopy(MAIN)
    cfg["meshes"]["candle"]["raycache"] = {"resolution": 24}
    cfg["prompts"] = {"gold": "a {object} made of gold"}
    cfg["variants"] = {"no_normal": {"optimize": {"normal_network": False}}}
    return cfg


def planned(proc) -> list[tuple[str, str]]:
    """(rule, first output) of every job of a dry run."""
    return re.findall(r"^(?:local)?rule (\w+):\n(?:    input: .*\n)?    output: ([^,\n]+)", proc.stdout, re.M)


def test_experiment_name_from_key_or_config_stem():
    assert experiment_name({"experiment": "paper-grid"}, ["config/x.yaml"]) == "paper-grid"
    assert experiment_name({}, ["config/ablations.yaml"]) == "ablations"
    assert experiment_name({}, ["config/ablations.yaml", "config/overlays/offline.yaml"]) == "ablations+offline"
    for bad in ("meshes", "../up", "a b", "_x"):
        with pytest.raises(ConfigError, match="experiment name"):
            experiment_name({"experiment": bad}, ["c.yaml"])


def test_mesh_work_keys_follow_exactly_the_settings_that_shape_the_work():
    base = WorkflowConfig(copy.deepcopy(MAIN)).mesh_work_keys("vase")
    assert set(base) == {"normalize", "raycache", "target"}
    assert all(re.fullmatch(r"[0-9a-f]{12}", k) for k in base.values())
    # another experiment (other prompts, variants, optimize settings) with equal mesh settings
    assert WorkflowConfig(ablation_config()).mesh_work_keys("vase") == base

    def keys(**mesh_entry):
        cfg = copy.deepcopy(MAIN)
        cfg["meshes"]["vase"].update(mesh_entry)
        return WorkflowConfig(cfg).mesh_work_keys("vase")

    # a ray-cache setting: the cache and the targets traced from it, not the normalised mesh
    finer = keys(raycache={"resolution": 20})
    assert finer["normalize"] == base["normalize"]
    assert finer["raycache"] != base["raycache"] and finer["target"] != base["target"]
    # a target setting: the targets alone
    target = keys(target={"spp": 8})
    assert (target["normalize"], target["raycache"]) == (base["normalize"], base["raycache"])
    assert target["target"] != base["target"]
    # a normalisation setting: everything downstream
    norm = keys(normalize={"up_axis": "+z"})
    assert all(norm[s] != base[s] for s in base)
    # another source under the same id never shares
    other = copy.deepcopy(MAIN)
    other["meshes"]["vase"] = {"builtin": "knot"}
    assert WorkflowConfig(other).mesh_work_keys("vase")["normalize"] != base["normalize"]
    # decimation: keyed by its own settings, and by the cache only where the budget reads it
    dec = keys(decimate={"enabled": True, "target_faces": 500})
    assert dec["normalize"] == base["normalize"] and dec["raycache"] != base["raycache"]
    dec_views = keys(decimate={"enabled": True, "target_faces": 500}, raycache={"views": 3})
    assert dec_views["decimate"] == dec["decimate"] and dec_views["raycache"] != dec["raycache"]
    budget = keys(decimate={"enabled": True, "mode": "budget"})
    budget_res = keys(decimate={"enabled": True, "mode": "budget"}, raycache={"resolution": 20})
    budget_views = keys(decimate={"enabled": True, "mode": "budget"}, raycache={"views": 3})
    assert budget_res["decimate"] != budget["decimate"]  # the budget reads the resolution
    assert budget_views["decimate"] == budget["decimate"]  # but not the number of views
    # the key is the digest of canonical JSON: key order does not matter
    assert settings_digest({"a": 1, "b": [1, 2]}) == settings_digest({"b": [1, 2], "a": 1})


def test_two_experiments_run_one_after_the_other_without_rerunning_each_others_work(tmp_path):
    """The main experiment's mesh-level work runs; the ablations then plan only what they add
    (the candle's finer cache, their own cells under results/ablations/), and after the
    ablations ran theirs, the main experiment still has nothing of its own to redo."""
    (tmp_path / "main.yaml").write_text(yaml.safe_dump(MAIN))
    (tmp_path / "ablations.yaml").write_text(yaml.safe_dump(ablation_config()))
    keys = {
        name: {m: WorkflowConfig(cfg).mesh_work_keys(m) for m in ("vase", "candle")}
        for name, cfg in (("main", MAIN), ("ablations", ablation_config()))
    }
    assert keys["main"]["vase"] == keys["ablations"]["vase"]
    assert keys["main"]["candle"]["raycache"] != keys["ablations"]["candle"]["raycache"]

    def mesh_targets(name):
        return [f"results/meshes/{m}/{k['raycache']}/raycache/meta.json" for m, k in keys[name].items()]

    # a mesh-level job is built only under the experiment's own key
    wrong = run_snakemake(
        tmp_path, "-n", mesh_targets("ablations")[1], "--cores", "1", "--configfile", str(tmp_path / "main.yaml")
    )
    assert wrong.returncode != 0 and "keyed by other raycache settings" in wrong.stdout + wrong.stderr

    # the main experiment's mesh-level work, for real
    first = run_snakemake(tmp_path, *mesh_targets("main"), "--cores", "2", "--configfile", str(tmp_path / "main.yaml"))
    assert first.returncode == 0, first.stderr[-3000:]

    # the ablations plan: their cells and the candle's finer cache only
    dry = run_snakemake(tmp_path, "-n", "--cores", "2", "--configfile", str(tmp_path / "ablations.yaml"))
    assert dry.returncode == 0, dry.stderr[-3000:]
    jobs = planned(dry)
    mesh_jobs = [(rule, out) for rule, out in jobs if rule in ("normalize", "decimate", "raycache", "target")]
    candle_cache = f"results/meshes/candle/{keys['ablations']['candle']['raycache']}/raycache/train.npz"
    assert mesh_jobs == [("raycache", candle_cache)], mesh_jobs
    cell_jobs = [out for rule, out in jobs if rule == "optimize"]
    assert sorted(cell_jobs) == [f"results/ablations/{m}/gold/no_normal/optimize/field.pt" for m in ("candle", "vase")]
    assert all(not out.startswith("results/main/") for _, out in jobs)
    assert "results/ablations/report/summary.csv" in dry.stdout

    # the ablations' own mesh-level work, for real; the main experiment's still stands
    second = run_snakemake(tmp_path, *mesh_targets("ablations"), "--cores", "2", "--configfile", str(tmp_path / "ablations.yaml"))
    assert second.returncode == 0, second.stderr[-3000:]
    assert "rule normalize" not in second.stdout + second.stderr  # both normalised meshes were shared
    for name in ("main", "ablations"):
        again = run_snakemake(tmp_path, "-n", *mesh_targets(name), "--cores", "1", "--configfile", str(tmp_path / f"{name}.yaml"))
        assert again.returncode == 0 and "Nothing to be done" in again.stdout + again.stderr, (name, again.stdout)
    main_dry = run_snakemake(tmp_path, "-n", "--cores", "2", "--configfile", str(tmp_path / "main.yaml"))
    assert not [j for j in planned(main_dry) if j[0] in ("normalize", "decimate", "raycache", "target")]
    assert all(out.startswith("results/main/") for rule, out in planned(main_dry) if rule not in ("all",))


def test_mesh_work_lists_the_experiments_folders(tmp_path, capsys):
    """``python -m stages.config --mesh-work``: the folders to keep when cleaning up."""
    path = tmp_path / "ablations.yaml"
    path.write_text(yaml.safe_dump(ablation_config()))
    assert main(["--configfile", str(path), "--mesh-work"]) == 0
    listed = capsys.readouterr().out.splitlines()
    cfg = WorkflowConfig(ablation_config())
    want = sorted({f"results/meshes/{m}/{k}" for m in ("vase", "candle") for k in cfg.mesh_work_keys(m).values()})
    assert listed == want and len(want) == 6
