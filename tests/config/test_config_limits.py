"""Every number of the config at its extremes: 0, -1, its maximum + 1, NaN, infinity and a string
either pass (where the schema allows them) or are refused when the DAG is built with one line
naming the key and what to do. Every size, count and resolution has a maximum."""

from __future__ import annotations

import math

import pytest

from stages.config.schema import schema as load_schema
from stages.config.workflow import ConfigError, WorkflowConfig

BASE = {"meshes": {"vase": {"builtin": "vase"}}, "prompts": {"wood": "a {object} made of wood"}}
#: numbers that are not sizes, counts or resolutions (angles in radians): bounded by nothing a machine runs out of
UNBOUNDED = {("raycache", "anchor_azimuth"), ("raycache", "anchor_elevation")}


def numeric_keys() -> list[tuple[str, str, dict]]:
    schema = load_schema()
    keys = []
    for section, node in schema["properties"].items():
        ref = node.get("$ref", "")
        props = schema["$defs"][ref.split("/")[-1]].get("properties", {}) if ref else {}
        for key, spec in props.items():
            types = spec.get("type") if isinstance(spec.get("type"), list) else [spec.get("type")]
            if {"integer", "number"} & set(types) and "enum" not in spec:
                keys.append((section, key, spec))
    return keys


KEYS = numeric_keys()


def build(section: str, key: str, value) -> None:
    config = {**BASE, section: {key: value}}
    if section == "target":  # the target stage runs where a cell asks for image targets
        config["optimize"] = {"guidance": "image"}
    WorkflowConfig(config)


def test_the_corpus_covers_every_section():
    assert {s for s, _, _ in KEYS} >= {"decimate", "raycache", "optimize", "target", "bake", "relight", "roundtrip", "lod"}
    assert len(KEYS) > 80


@pytest.mark.parametrize(("section", "key"), [(s, k) for s, k, _ in KEYS])
def test_every_number_has_a_maximum(section, key):
    spec = next(sp for s, k, sp in KEYS if (s, k) == (section, key))
    if (section, key) in UNBOUNDED:
        return
    assert "maximum" in spec or "exclusiveMaximum" in spec, f"{section}.{key} has no maximum"
    assert "minimum" in spec or "exclusiveMinimum" in spec, f"{section}.{key} has no minimum"


@pytest.mark.parametrize(("section", "key"), [(s, k) for s, k, _ in KEYS])
def test_a_number_at_its_extremes_passes_or_is_one_line_naming_it(section, key):
    spec = next(sp for s, k, sp in KEYS if (s, k) == (section, key))
    top = spec.get("maximum", spec.get("exclusiveMaximum"))
    values = [0, -1, math.nan, math.inf, -math.inf, "a string", "1e9"]
    must_fail = {repr(math.nan), repr(math.inf), repr(-math.inf), "'a string'", "'1e9'"}
    if top is not None:
        over = top + 1 if "integer" in str(spec.get("type")) else top * 2 + 1
        values.append(over)
        must_fail.add(repr(over))
    for value in values:
        try:
            build(section, key, value)
        except ConfigError as err:
            text = str(err)
            assert "\n" not in text and key in text, text
            assert len(text) < 400, text
            continue
        assert repr(value) not in must_fail, f"{section}.{key} = {value!r} was accepted"
