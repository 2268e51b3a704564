"""Each setting written once: the settings classes' limits, the schema generated from them, and the
checks derived from them agree, and they say what a user needs in one line."""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import re
from pathlib import Path
from typing import Literal

import jsonschema
import pytest
import yaml

from stages.config import schema as schema_module
from stages.config.sections import SECTIONS, FieldSettings, OptimizeSettings
from stages.core.errors import ConfigError
from stages.core.settings import Settings, kind_of, setting

REPO = Path(__file__).resolve().parents[2]
SETTINGS_CLASSES = [*SECTIONS.values(), FieldSettings]


def _validator(section: str):
    full = schema_module.schema()
    return jsonschema.Draft202012Validator({"$defs": full["$defs"], "$ref": f"#/$defs/{section}"})


def _class_error(cls: type[Settings], **values) -> str | None:
    try:
        cls(**values)
    except ConfigError as err:
        return str(err)
    return None


# ------------------------------------------------------------------------------ the file
def test_the_schema_file_is_the_generated_schema(tmp_path, monkeypatch, capsys):
    assert schema_module.main(["--check"]) == 0, capsys.readouterr().err
    assert yaml.safe_load(schema_module.SCHEMA_PATH.read_text()) == schema_module.schema()
    # a hand edit of the file (a default changed) is caught, naming the command that rewrites it
    edited = schema_module.SCHEMA_PATH.read_text().replace("default: 1500", "default: 1600", 1)
    assert edited != schema_module.SCHEMA_PATH.read_text()
    monkeypatch.setattr(schema_module, "SCHEMA_PATH", tmp_path / "workflow" / "schemas" / "config.schema.yaml")
    schema_module.SCHEMA_PATH.parent.mkdir(parents=True)
    schema_module.SCHEMA_PATH.write_text(edited)
    monkeypatch.setattr(schema_module, "REPO_ROOT", tmp_path)
    assert schema_module.main(["--check"]) == 1
    assert schema_module.WRITE_COMMAND in capsys.readouterr().err


def test_every_setting_has_a_spec_with_a_one_line_description():
    for cls in SETTINGS_CLASSES:
        for name, spec in cls.specs().items():
            assert spec.doc and "\n" not in spec.doc, f"{cls.__name__}.{name}"
            assert not re.search(r"\b20\d\d-\d\d-\d\d\b", spec.doc), f"{cls.__name__}.{name}: a dated result belongs in the docs"
    # and no dated result hides in the module's comments either
    source = (REPO / "stages" / "config" / "sections.py").read_text()
    assert not re.findall(r"\b20\d\d-\d\d-\d\d\b", source)


def test_a_field_without_a_spec_or_with_an_unsupported_type_is_refused():
    @dataclasses.dataclass(frozen=True, kw_only=True)
    class Bare(Settings):
        n: int = 3

    with pytest.raises(TypeError, match="not declared with setting"):
        Bare()
    with pytest.raises(TypeError, match="unsupported settings type"):
        kind_of(dict)
    with pytest.raises(TypeError, match="one type"):
        kind_of(tuple[int, str])

    @dataclasses.dataclass(frozen=True, kw_only=True)
    class Fine(Settings):
        section = "fine"
        n: int = setting(3, "a count", ge=1)

    assert Fine(n=2).n == 2
    with pytest.raises(ConfigError, match=r"^fine settings: fine\.n must be >= 1, got 0$"):
        Fine(n=0)


# --------------------------------------------------------------------- limits, both sides
def _bounded_fields():
    for cls in SECTIONS.values():
        kinds = cls.kinds()
        for name, spec in cls.specs().items():
            kind = kinds[name]
            base = (kind.item or kind).base
            if base in (int, float) and any(v is not None for v in (spec.ge, spec.gt, spec.le, spec.lt)):
                yield pytest.param(cls, name, id=f"{cls.section}.{name}")


def _edges(base: type, spec) -> tuple[list, list]:
    """Values just inside and just outside each bound, written from the bound itself."""
    inside, outside = [], []
    step = 1 if base is int else None
    for bound, closed, sign in ((spec.ge, True, -1), (spec.gt, False, -1), (spec.le, True, 1), (spec.lt, False, 1)):
        if bound is None:
            continue
        if base is int:
            inside.append(int(bound) if closed else int(bound) - sign * step)
            outside.append(int(bound) + sign * step if closed else int(bound))
        else:
            beyond = math.nextafter(float(bound), sign * math.inf)
            inside.append(float(bound) if closed else math.nextafter(float(bound), -sign * math.inf))
            outside.append(beyond if closed else float(bound))
    if spec.multiple_of:
        inside = [v - v % spec.multiple_of for v in inside]
    return inside, outside


@pytest.mark.parametrize(("cls", "name"), list(_bounded_fields()))
def test_every_limit_holds_in_the_class_and_the_schema_alike(cls, name):
    kind, spec = cls.kinds()[name], cls.specs()[name]
    base = (kind.item or kind).base
    inside, outside = _edges(base, spec)
    validator = _validator(cls.section)
    # inside a field's limits, a value may still break a relation with another field's default
    # (a 16384-texel min_size above the default max_size): those are tested on their own
    unrelated = type(cls.__name__, (cls,), {"relations": lambda self: []})

    def as_value(x):
        if kind.item is None:
            return x
        return [x, 0.0] if name == "anchor_deg" else [x] * (kind.length or 1)

    for x in inside:
        value = as_value(x)
        assert _class_error(unrelated, **{name: value}) is None, x
        assert not [e for e in validator.iter_errors({name: value}) if list(e.absolute_path)[:1] == [name]], x
    for x in outside:
        value = as_value(x)
        error = _class_error(cls, **{name: value})
        assert error is not None and f"{cls.section}.{name}" in error and "\n" not in error, (x, error)
        assert re.search(r"[\[(]-?[\d.e+-]+, -?[\d.e+-]+[\])]|[<>]=? -?[\d.e+-]+", error), error  # the limit, stated
        assert any(True for _ in validator.iter_errors({name: value})), x


# ----------------------------------------------------------------- hand-written expectations
#: (section, key, value, what the one-line message says): written from the limits a user reads
#: in the configuration reference, not from the specs
REFUSED = [
    ("optimize", "lr", 0.0, "optimize.lr must be in (0, 1], got 0.0"),
    ("optimize", "lr", 1.5, "optimize.lr must be in (0, 1], got 1.5"),
    ("optimize", "lr", float("nan"), "optimize.lr must be a finite number"),
    ("optimize", "iterations", 0, "optimize.iterations must be in [1, 1000000], got 0"),
    ("optimize", "iterations", 2.5, "optimize.iterations must be an integer, got 2.5"),
    ("optimize", "iterations", True, "optimize.iterations must be an integer, got true"),
    ("optimize", "background", "grey", "optimize.background must be one of black, white, noise"),
    ("optimize", "crop_scale", (0.1,), "optimize.crop_scale must hold 2 items"),
    ("optimize", "crop_scale", (0.3, 0.1), "smallest <= largest"),
    ("optimize", "milestones", (-1, 5), "optimize.milestones items: each must be in [0, 1000000]"),
    ("optimize", "init_metallic", 0.5, None),  # accepted: the default BRDF is glTF's
    ("optimize", "clip_checkpoint", "", "optimize.clip_checkpoint must not be empty"),
    ("optimize", "light_map", "builtin:sunset", "with light: learn it would be ignored"),
    ("raycache", "visibility_directions", 12, "raycache.visibility_directions must be a multiple of 8"),
    ("raycache", "anchor_deg", (10.0, 95.0), "elevation in (-90, 90)"),
    ("raycache", "eval_elevations_deg", (), "raycache.eval_elevations_deg must hold at least 1 item"),
    ("target", "spp", 33, "target.spp must be an even number"),
    ("target", "max_depth", 1, "target.max_depth must be >= 2 (or -1: unlimited)"),
    ("target", "environment", "builtin:moon", "no procedural environment 'builtin:moon'"),
    ("roundtrip", "formats", ("obj",), "roundtrip.formats items: each must be one of glb, usdz"),
    ("lod", "levels", (0.1, 0.5), "lod.levels must be strictly decreasing"),
    ("bake", "min_size", 4096, "bake.min_size must not exceed bake.max_size"),
    ("relight", "envmap", "sky.png", "'sky.png' is neither builtin:<name> nor an .hdr/.exr file"),
    ("report", "ablations", ("a", ""), "report.ablations items: each must not be empty"),
]


@pytest.mark.parametrize(("section", "key", "value", "message"), REFUSED, ids=[f"{s}.{k}={v!r}" for s, k, v, _ in REFUSED])
def test_a_bad_value_fails_in_one_line_naming_the_key_and_the_limit(section, key, value, message):
    error = _class_error(SECTIONS[section], **{key: value})
    if message is None:
        assert error is None
        return
    assert error is not None and message in error, error
    assert "\n" not in error


def test_yaml_on_off_and_lists_take_the_forms_the_settings_hold():
    s = OptimizeSettings(bf16=True, bf16_networks=False, milestones=[10, 20], crop_scale=[0.1, 0.2])
    assert (s.bf16, s.bf16_networks, s.milestones, s.crop_scale) == ("on", "off", (10, 20), (0.1, 0.2))
    assert SECTIONS["raycache"](visibility=False).visibility == "off"
    with pytest.raises(ConfigError, match="must be one of"):
        OptimizeSettings(bf16="yes")
    # the schema takes the same forms
    validator = _validator("optimize")
    assert not list(validator.iter_errors({"bf16": True, "milestones": [10, 20]}))
    assert list(validator.iter_errors({"bf16": "yes"}))


# ------------------------------------------------------------------- what already exists
def test_the_settings_stored_in_trained_fields_still_load():
    from stages.model.checkpoint import SETTINGS_BEFORE_THEY_EXISTED

    stored = json.loads((Path(__file__).parent / "data" / "stored_field_settings.json").read_text())["fields"]
    assert len(stored) >= 4
    for origin, settings in stored.items():
        loaded = OptimizeSettings.from_dict({**SETTINGS_BEFORE_THEY_EXISTED, **copy.deepcopy(settings)})
        as_stored = json.loads(json.dumps(loaded.to_dict()))
        assert {k: as_stored[k] for k in settings} == settings, origin
        field = loaded.field_settings()
        assert all(getattr(field, k) == getattr(loaded, k) for k in (f.name for f in dataclasses.fields(FieldSettings)))


def test_the_field_settings_are_the_optimize_sections_own():
    assert issubclass(OptimizeSettings, FieldSettings)
    assert {f.name for f in dataclasses.fields(FieldSettings)} < {f.name for f in dataclasses.fields(OptimizeSettings)}
    s = OptimizeSettings(width=64, light_lobes=7, seed=3).field_settings()
    assert type(s) is FieldSettings and (s.width, s.light_lobes, s.seed) == (64, 7, 3)
    # the field's relations hold on their own (a stored field built without the optimize section)
    with pytest.raises(ConfigError, match="no isotropic specular model"):
        FieldSettings(specular_lobe="isotropic")


def test_a_count_or_a_word_takes_either_and_says_so():
    """``int | Literal["auto"]`` (``optimize.suns``): a count in its range or the word; the
    schema takes the same values (jsonschema against the generated node), and the reference
    says both."""
    from stages.config.schema import setting_node
    from stages.core.settings import kind_words

    kind = kind_of(int | Literal["auto"])
    assert kind.base is int and kind.words == ("auto",) and not kind.nullable
    assert kind_words(kind) == "integer or auto"
    assert kind_words(kind_of(int | Literal["auto"] | None)) == "integer or auto or null"

    @dataclasses.dataclass(frozen=True, kw_only=True)
    class Counted(Settings):
        section = "counted"
        n: int | Literal["auto"] = setting(0, "a count or auto", ge=0, le=8)

    node = setting_node(Counted.kinds()["n"], Counted.specs()["n"], 0)
    for good in ("auto", 0, 8):
        assert Counted(n=good).n == good
        jsonschema.validate(good, node)
    wrong = "must be auto or an integer"
    for bad, why in (("many", wrong), (9, r"must be in \[0, 8\]"), (1.5, wrong), (True, wrong)):
        with pytest.raises(ConfigError, match=rf"counted\.n {why}"):
            Counted(n=bad)
        with pytest.raises(jsonschema.ValidationError):
            jsonschema.validate(bad, node)
    with pytest.raises(TypeError, match="one type"):
        kind_of(int | str | None)
