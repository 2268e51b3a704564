"""Config schema and resolution: defaults agree with the stages, bad configs fail usefully."""

from __future__ import annotations

import copy
import dataclasses

import pytest
import yaml
from conftest import REPO

from stages.bake import BakeSettings
from stages.config import MESH_STAGES, WorkflowConfig, load_config_file, load_schema
from stages.decimate import DecimateSettings
from stages.errors import ConfigError
from stages.export import ExportSettings
from stages.normalize import NormalizeSettings
from stages.optimize import OptimizeSettings
from stages.raycache import RaycacheSettings
from stages.relight import RelightSettings

SETTINGS = {
    "normalize": NormalizeSettings,
    "decimate": DecimateSettings,
    "raycache": RaycacheSettings,
    "optimize": OptimizeSettings,
    "bake": BakeSettings,
    "export": ExportSettings,
    "relight": RelightSettings,
}


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


@pytest.mark.parametrize("stage", [*MESH_STAGES, "optimize", "bake", "export", "relight"])
def test_schema_defaults_equal_dataclass_defaults(stage):
    props = load_schema()["$defs"][stage]["properties"]
    fields = {f.name: f.default for f in dataclasses.fields(SETTINGS[stage])}
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
    base["prompts"]["gold"] = {"text": "a gold {object}", "preset": "metal"}
    base["optimize"] = {"iterations": 10, "light_lobes": 16}
    base["variants"] = {"full": {}, "flat": {"preset": "rough", "optimize": {"normal_network": False}}}
    cfg = WorkflowConfig(base)
    full_gold = cfg.optimize_settings("gold", "full")
    assert full_gold.material_encoding == "fourier" and full_gold.init_roughness == 0.3
    assert full_gold.light_lobes == 16  # the config's explicit section beats the preset
    assert full_gold.iterations == 10
    flat_gold = cfg.optimize_settings("gold", "flat")
    assert flat_gold.material_encoding == "nerf" and flat_gold.crops == 4  # the variant's preset
    assert flat_gold.normal_network is False  # the variant's own override wins
    assert cfg.prompt_text("vase", "gold") == "a gold vase"


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
