"""Config schema and resolution: defaults agree with the stages, bad configs fail usefully."""

from __future__ import annotations

import copy
import dataclasses

import pytest
import yaml
from conftest import REPO

from stages.config.schema import schema as load_schema
from stages.config.sections import (
    SECTIONS,
    OptimizeSettings,
)
from stages.config.workflow import WorkflowConfig, load_config_file
from stages.core.errors import ConfigError


@pytest.fixture
def base():
    return {
        "meshes": {
            "vase": {"builtin": "vase"},
            "ring": {"path": "x.obj", "decimate": {"enabled": True}},
        },
        "prompts": {"wood": "a {object} made of wood", "gold": "a gold thing"},
    }


def test_default_config_is_valid():
    cfg = load_config_file(REPO / "config" / "config.yaml")
    assert cfg.grid_meshes == ["vase", "candle", "knot"]
    assert len(cfg.cells) == 3 * 2 * 1
    assert cfg.prompt_text("knot", "wood") == "a knot sculpture made of wood"


def test_every_schema_section_has_a_settings_class():
    schema = load_schema()
    stage_sections = {k for k in schema["properties"] if k in schema["$defs"] and "properties" in schema["$defs"][k]}
    assert stage_sections - {"meshes", "prompts", "grid", "variants", "mesh", "preset", "id"} == set(SECTIONS)


@pytest.mark.parametrize("stage", list(SECTIONS))
def test_schema_defaults_equal_dataclass_defaults(stage):
    props = load_schema()["$defs"][stage]["properties"]
    fields = {f.name: f.default for f in dataclasses.fields(SECTIONS[stage])}
    assert set(props) == set(fields)
    for name, spec in props.items():
        default = fields[name]
        expected = list(default) if isinstance(default, tuple) else default
        assert spec["default"] == expected, name


def test_resolution_and_overrides(base):
    base["raycache"] = {"views": 10, "resolution": 128}
    base["meshes"]["vase"]["raycache"] = {"resolution": 64}
    cfg = WorkflowConfig(base)
    assert cfg.stage_settings("vase", "raycache").resolution == 64
    assert cfg.stage_settings("vase", "raycache").views == 10
    assert cfg.stage_settings("ring", "raycache").resolution == 128
    assert cfg.decimated("ring") and not cfg.decimated("vase")
    assert cfg.mesh_source("vase") == "builtin:vase" and cfg.mesh_source("ring") == "x.obj"
    assert cfg.prompt_text("vase", "wood") == "a vase made of wood"
    assert [c.variant for c in cfg.cells] == ["base"] * 4


def test_explicit_grid(base):
    base["grid"] = [{"mesh": "vase", "prompt": "gold"}]
    cfg = WorkflowConfig(base)
    assert cfg.grid_meshes == ["vase"] and len(cfg.cells) == 1


def expect_error(config, *needles):
    with pytest.raises(ConfigError) as info:
        WorkflowConfig(config, "test.yaml")
    msg = str(info.value)
    assert msg.startswith("test.yaml: ")
    for needle in needles:
        assert needle in msg, msg
    return msg


def test_unknown_top_level_key(base):
    base["raycahce"] = {}
    expect_error(base, "'raycahce'", "the top level", "raycache")


def test_unknown_key_in_mesh(base):
    base["meshes"]["vase"]["pth"] = "a.obj"
    expect_error(base, "'pth'", "meshes -> vase", "allowed keys", "path")


def test_unknown_key_in_stage_override(base):
    base["meshes"]["ring"]["decimate"]["target_face"] = 10
    expect_error(base, "'target_face'", "meshes -> ring -> decimate", "target_faces")


def test_unknown_key_in_section(base):
    base["raycache"] = {"view": 3}
    expect_error(base, "'view'", "raycache", "views")


def test_wrong_type_and_range(base):
    base["raycache"] = {"resolution": "big", "fov_deg": 200}
    msg = expect_error(base, "raycache -> resolution", "raycache -> fov_deg")
    assert "'big'" in msg


def test_mesh_needs_one_source(base):
    base["meshes"]["vase"]["path"] = "v.obj"
    expect_error(base, "meshes -> vase", "exactly one of 'path' or 'builtin'")
    del base["meshes"]["vase"]["path"], base["meshes"]["vase"]["builtin"]
    expect_error(base, "meshes -> vase", "exactly one of")


def test_grid_names_unknown_ids(base):
    base["grid"] = [{"mesh": "vase", "prompt": "silk"}, {"mesh": "teapot", "prompt": "wood"}]
    expect_error(base, "grid -> 0 -> prompt: 'silk'", "grid -> 1 -> mesh: 'teapot'")


def test_ids_must_be_path_safe(base):
    base["prompts"]["a/b"] = "x"
    expect_error(base, "'a/b'", "ids name result folders")


def test_variants_cannot_override_mesh_stages(base):
    base["variants"] = {"full": {}, "lowres": {"raycache": {"resolution": 64}}}
    expect_error(base, "'raycache'", "variants -> lowres", "overridden per mesh")


def test_presets_and_overrides_resolve_in_order(base):
    """The more specific level wins (variant > prompt > base section); within a level, explicit
    keys beat the level's preset."""
    base["prompts"]["gold"] = {"text": "a gold {object}", "preset": "metal", "optimize": {"init_roughness": 0.5}}
    base["optimize"] = {"iterations": 10, "light_lobes": 16, "width": 32}
    base["variants"] = {"full": {}, "flat": {"preset": "rough", "optimize": {"normal_network": False}}}
    cfg = WorkflowConfig(base)
    full_gold = cfg.optimize_settings("gold", "full")
    assert full_gold.material_encoding == "fourier"  # the prompt's preset
    assert full_gold.light_lobes == 64  # the prompt's preset beats the base section
    assert full_gold.init_roughness == 0.5  # the prompt's explicit key beats its own preset
    assert full_gold.iterations == 10 and full_gold.width == 32  # base keys no preset touches
    flat_gold = cfg.optimize_settings("gold", "flat")
    assert flat_gold.material_encoding == "nerf" and flat_gold.crops == 4  # the variant's preset beats the prompt's
    assert flat_gold.light_lobes == 32  # the variant's preset beats the prompt's preset and the base section
    assert flat_gold.init_roughness == 0.5  # a key the variant does not set stays the prompt's
    assert flat_gold.normal_network is False  # the variant's own override wins over its preset
    assert cfg.prompt_text("vase", "gold") == "a gold vase"


def test_variant_preset_beats_the_base_section_of_the_default_config():
    """`variants: {quick: {preset: fast}}` on the default config runs the fast preset's schedule,
    not the default config's 1,500 iterations with the preset's milestones."""
    from stages.config.presets import PRESETS

    raw = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    raw["variants"] = {"quick": {"preset": "fast"}}
    cfg = WorkflowConfig(raw)
    s = cfg.optimize_settings(next(iter(raw["prompts"])), "quick")
    for key, value in PRESETS["fast"].items():
        want = tuple(value) if isinstance(value, list) else value
        assert getattr(s, key) == want, key
    assert s.iterations == 300 and s.milestones == (180, 255) and s.lr == 5e-3


def test_paper_preset_is_the_schema_defaults():
    from stages.config.presets import PRESETS

    defaults = OptimizeSettings()
    for key, value in PRESETS["paper"].items():
        assert getattr(defaults, key) == (tuple(value) if isinstance(value, list) else value), key


def test_speed_presets_are_the_measured_sweep_points():
    """The sweep measures the presets as variants; `fast` is its knee (one view per step), so the
    two resolve to the same settings, and every preset key is a setting the sweep ran."""
    cfg = load_config_file(REPO / "config" / "sweep.yaml")
    prompt = next(iter(cfg.prompts))
    assert cfg.optimize_settings(prompt, "fast") == cfg.optimize_settings(prompt, "views1")
    balanced = cfg.optimize_settings(prompt, "balanced")
    assert (balanced.iterations, balanced.width, balanced.light_lobes) == (600, 128, 32)
    assert balanced.image_size == cfg.optimize_settings(prompt, "base").image_size  # left out on purpose
    # the seed replicates differ from their variant in the seed alone
    for variant in ("base", "fast", "balanced", "it600"):
        for seed in (1, 2):
            replicate = cfg.optimize_settings(prompt, f"{variant}_seed{seed}")
            assert replicate == dataclasses.replace(cfg.optimize_settings(prompt, variant), seed=seed), (variant, seed)


def test_explain_names_the_source_of_every_key(base, tmp_path, capsys):
    from stages.config import workflow as config_mod

    base["prompts"]["gold"] = {"text": "a gold {object}", "preset": "metal"}
    base["optimize"] = {"iterations": 10, "light_lobes": 16}
    base["variants"] = {"full": {}, "flat": {"preset": "rough", "optimize": {"normal_network": False}}}
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(base))
    assert config_mod.main(["--configfile", str(path), "--cell", "vase/gold/flat", "--json"]) == 0
    import json

    rows = {r["key"]: r for r in json.loads(capsys.readouterr().out)}
    assert set(rows) == {f.name for f in dataclasses.fields(OptimizeSettings)}
    assert rows["iterations"]["source"] == "config optimize section" and rows["iterations"]["value"] == 10
    assert rows["light_lobes"]["source"] == "preset 'rough' of variant 'flat'" and rows["light_lobes"]["value"] == 32
    assert rows["init_roughness"]["source"] == "preset 'metal' of prompt 'gold'"
    assert rows["normal_network"]["source"] == "variant 'flat' optimize overrides"
    assert rows["seed"]["source"] == "default"
    assert config_mod.main(["--configfile", str(path), "--cell", "vase/gold/flat", "--stage", "decimate"]) == 0
    assert "enabled" in capsys.readouterr().out
    assert config_mod.main(["--configfile", str(path), "--cell", "vase/nope/flat"]) == 2
    assert "not a cell of the grid" in capsys.readouterr().err


def test_bad_optimize_values_fail_at_dag_time(base):
    base["variants"] = {"x": {"optimize": {"guidance": "vibes"}}}
    expect_error(base, "variants -> x -> optimize -> guidance")
    base["variants"] = {"x": {"optimize": {"crop_scale": [0.5, 0.1]}}}
    expect_error(base, "variant 'x'", "crop_scale")
    base["variants"] = {"x": {"preset": "shiny"}}
    expect_error(base, "variants -> x -> preset")


def test_builtin_name_checked(base):
    base["meshes"]["vase"]["builtin"] = "teapot"
    expect_error(base, "meshes -> vase -> builtin", "'teapot'")


def test_missing_required(base):
    del base["prompts"]
    expect_error(base, "missing required key", "'prompts'")


def test_config_file_errors(tmp_path):
    with pytest.raises(ConfigError, match="config file not found"):
        load_config_file(tmp_path / "none.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("meshes: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config_file(bad)
    bad.write_text("- a\n- b\n")
    with pytest.raises(ConfigError, match="mapping at the top level"):
        load_config_file(bad)


def deep_update(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = deep_update(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def test_every_shipped_config_is_valid():
    overlay = yaml.safe_load((REPO / "config" / "overlays" / "offline.yaml").read_text())
    for path in sorted((REPO / "config").glob("*.yaml")):
        cfg = load_config_file(path)
        # every experiment also validates under the offline overlay (as Snakemake merges them)
        offline = WorkflowConfig(deep_update(cfg.raw, overlay), f"{path} + offline overlay")
        assert all(
            offline.optimize_settings(c.prompt, c.variant).clip_tiny_test
            or offline.optimize_settings(c.prompt, c.variant).guidance == "image"
            for c in offline.cells
        )
    smoke = yaml.safe_load((REPO / "tests" / "smoke" / "config.yaml").read_text())
    WorkflowConfig(copy.deepcopy(smoke))


def test_field_settings_are_a_typed_subset_of_the_optimize_settings():
    from stages.config.sections import FieldSettings

    opt = {f.name: f.type for f in dataclasses.fields(OptimizeSettings)}
    field = {f.name: f.type for f in dataclasses.fields(FieldSettings)}
    assert set(field) < set(opt)
    assert all(field[k] == opt[k] for k in field)
    s = OptimizeSettings(width=64, light_lobes=7, seed=3).field_settings()
    assert (s.width, s.light_lobes, s.seed) == (64, 7, 3)


def test_report_section_names_existing_variants(base):
    base["variants"] = {"full": {}, "no_normal": {"optimize": {"normal_network": False}}}
    base["report"] = {"reference": "full", "ablations": ["no_normal"], "single_file": True}
    settings = WorkflowConfig(base).report_settings()
    assert settings.reference == "full" and settings.ablations == ("no_normal",) and settings.single_file
    for bad, message in (
        ({"reference": "nope"}, "report names variant(s) 'nope' that the config does not define"),
        ({"ablations": ["full", "gone"]}, "'gone'"),
        ({"reference": "full", "ablations": ["full"]}, "cannot be one of the ablations"),
        ({"panels_per_figure": 0}, "report -> panels_per_figure"),
        ({"colour": "red"}, "unknown key.*colour"),
    ):
        base["report"] = bad
        with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
            WorkflowConfig(base)
