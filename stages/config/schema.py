"""The workflow config's JSON schema, generated from the settings classes.

    python -m stages.config.schema           # print it (YAML)
    python -m stages.config.schema --write   # (re)write workflow/schemas/config.schema.yaml
    python -m stages.config.schema --check   # exit status 1 when that file differs

Each stage section (``$defs/<section>``) comes from its settings class
(:mod:`stages.config.sections`): every field's type, default, limits and description, from its
annotation and its :class:`~stages.core.settings.Spec`. The config's own structure (meshes,
prompts, grid, variants, experiment, device) is written here, its one home. The workflow validates
every config against :func:`schema` (the file is the same schema, for editors and readers; CI
checks that it is up to date). No torch, no numpy.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import sys
from functools import cache
from pathlib import Path
from typing import Any

import yaml

from ..core.safefiles import atomic_path, read_text
from ..core.settings import Kind, Settings, Spec
from .presets import PRESETS
from .sections import PATH_MAX, PATH_PATTERN, SECTIONS

REPO_ROOT = Path(__file__).resolve().parents[2]
SCHEMA_PATH = REPO_ROOT / "workflow" / "schemas" / "config.schema.yaml"
#: the command that rewrites the file (the drift check names it)
WRITE_COMMAND = "python -m stages.config.schema --write"

#: a mesh, prompt or variant id: a folder name. ``(?!\n)``: Python's ``$`` (jsonschema's regex
#: engine) also matches before a trailing newline
ID_PATTERN = "^[A-Za-z0-9][A-Za-z0-9_.-]*(?!\\n)$"
ID_MAX = 64
#: an experiment's name: a folder under ``results/``
EXPERIMENT_PATTERN = "^[A-Za-z0-9][A-Za-z0-9_.+-]*(?!\\n)$"
EXPERIMENT_MAX = 128
#: one line of text: no control characters, no line or paragraph separators, no bidirectional
#: overrides or isolates (which show the text in another order than it is stored)
ONE_LINE = "^[^\\x00-\\x1f\\x7f-\\x9f\\u2028\\u2029\\u202a-\\u202e\\u2066-\\u2069]*(?!\\n)$"
#: a prompt's text: one line that is not blank (a text of invisible characters only is refused by
#: the workflow's own check, :func:`stages.config.workflow.blank`, which no pattern can state)
PROMPT_PATTERN = "^(?=.*\\S)[^\\x00-\\x1f\\x7f-\\x9f\\u2028\\u2029\\u202a-\\u202e\\u2066-\\u2069]*(?!\\n)$"
#: the longest prompt text a config may give ({object} replaced)
PROMPT_CHARS = 1000
#: stages whose settings a mesh entry may override, and those a prompt or variant may
MESH_OVERRIDES = ("normalize", "decimate", "raycache", "target")
CELL_OVERRIDES = ("optimize", "bake", "relight", "lod")
#: the built-in meshes (:mod:`stages.geometry.shapes`)
BUILTIN_MESHES = ("vase", "candle", "knot")

_TYPES = {int: "integer", float: "number", bool: "boolean", str: "string"}


# ------------------------------------------------------------------------------- settings
def _limits(spec: Spec) -> dict[str, Any]:
    """A spec's limits of one value (a scalar, or each item of a list) as schema keywords."""
    words = {
        "ge": "minimum",
        "gt": "exclusiveMinimum",
        "le": "maximum",
        "lt": "exclusiveMaximum",
        "multiple_of": "multipleOf",
        "min_length": "minLength",
        "max_length": "maxLength",
        "pattern": "pattern",
    }
    out = {}
    for name, keyword in words.items():
        value = getattr(spec, name)
        if value is not None:
            out[keyword] = value if name == "pattern" else _plain(value)
    return out


def _plain(value: Any) -> Any:
    """A number as the schema writes it: an integer where it is one (YAML reads 1000.0 as a float)."""
    if isinstance(value, float) and value.is_integer() and abs(value) < 1e15:
        return int(value)
    return value


def _scalar(kind: Kind, spec: Spec) -> dict[str, Any]:
    if kind.choices is not None:
        return {"enum": [*kind.choices, *((True, False) if kind.switch else ())]}
    if kind.words:  # a number or a word (a count, or auto)
        return {"anyOf": [{"enum": list(kind.words)}, {"type": _TYPES[kind.base], **_limits(spec)}]}
    return {"type": _TYPES[kind.base], **_limits(spec)}


def setting_node(kind: Kind, spec: Spec, default: Any) -> dict[str, Any]:
    """The schema of one setting: description, type (or choices), default, limits."""
    node: dict[str, Any] = {"description": spec.doc}
    if kind.item is None:
        body = _scalar(kind, spec)
    else:
        body = {"type": "array", "items": _scalar(kind.item, spec)}
        lo = kind.length if kind.length is not None else spec.min_items
        hi = kind.length if kind.length is not None else spec.max_items
        body.update({k: v for k, v in (("minItems", lo), ("maxItems", hi)) if v is not None})
    if kind.nullable and "anyOf" in body:
        body["anyOf"].append({"type": "null"})
    elif kind.nullable:
        body["type"] = [body["type"], "null"]
    node.update(body)
    node["default"] = list(default) if isinstance(default, tuple) else default
    return node


def section_schema(cls: type[Settings]) -> dict[str, Any]:
    """The schema of one config section: an object of its class's settings, nothing else."""
    kinds = cls.kinds()
    props = {f.name: setting_node(kinds[f.name], cls.specs()[f.name], f.default) for f in dataclasses.fields(cls)}
    doc = " ".join((cls.__doc__ or "").split())
    return {"description": doc, "type": "object", "additionalProperties": False, "properties": props}


# ------------------------------------------------------------------------------ structure
def _refs(names: tuple[str, ...]) -> dict[str, Any]:
    return {name: {"$ref": f"#/$defs/{name}"} for name in names}


def _prompt_text() -> dict[str, Any]:
    return {"type": "string", "minLength": 1, "maxLength": PROMPT_CHARS, "pattern": PROMPT_PATTERN}


def _structure() -> dict[str, Any]:
    """The config's top level and its entries (everything but the stage sections)."""
    id_ref = {"$ref": "#/$defs/id"}
    overrides = {"preset": {"$ref": "#/$defs/preset"}, **_refs(CELL_OVERRIDES)}
    return {
        "meshes": {
            "description": (
                "mesh id -> source. Ids name the results folders (results/<experiment>/<mesh>/... and results/meshes/<mesh>/...)."
            ),
            "type": "object",
            "minProperties": 1,
            "propertyNames": id_ref,
            "additionalProperties": {"$ref": "#/$defs/mesh"},
        },
        "prompts": {
            "description": (
                f"prompt id -> text (one line, at most {PROMPT_CHARS} characters: CLIP reads 77 tokens, about 300 "
                'characters, and a longer prompt is cut with a warning). "{object}" in the text is replaced by the '
                'mesh\'s `object` noun (default: the mesh id), so "a {object} made of wood" works across a grid.'
            ),
            "type": "object",
            "minProperties": 1,
            "propertyNames": id_ref,
            "additionalProperties": {
                "oneOf": [
                    _prompt_text(),
                    {
                        "type": "object",
                        "additionalProperties": False,
                        "required": ["text"],
                        "properties": {"text": _prompt_text(), **overrides},
                    },
                ]
            },
        },
        "grid": {
            "description": (
                'which mesh x prompt cells to run: "all" (the full product) or a list of {mesh, prompt} pairs naming ids above.'
            ),
            "default": "all",
            "oneOf": [
                {"const": "all"},
                {
                    "type": "array",
                    "minItems": 1,
                    "items": {
                        "type": "object",
                        "additionalProperties": False,
                        "required": ["mesh", "prompt"],
                        "properties": {"mesh": id_ref, "prompt": id_ref},
                    },
                },
            ],
        },
        "variants": {
            "description": (
                "variant id -> a preset and/or overrides of the per-cell stages' settings (ablations are named "
                "variants). Mesh-level stages (normalize, decimate, raycache) are per mesh, never per variant: "
                "override those per mesh instead. Settings resolve from the least to the most specific level, later "
                "winning: schema defaults < the config's `optimize` section < the prompt's preset < the prompt's "
                "`optimize` overrides < the variant's preset < the variant's `optimize` overrides (a variant over a "
                "prompt over the base section; within a level, explicit keys over the level's preset). Other "
                "per-cell stages: section < prompt < variant. `python -m stages.config --configfile C --cell "
                "mesh/prompt/variant` prints where each resolved value came from."
            ),
            "default": {"base": {}},
            "type": "object",
            "minProperties": 1,
            "propertyNames": id_ref,
            "additionalProperties": {"type": "object", "additionalProperties": False, "properties": overrides},
        },
        "experiment": {
            "description": (
                "the experiment's name: its cells and report live in results/<experiment>/ (default: the config "
                'file\'s stem, e.g. results/tiny/ for config/tiny.yaml; stems joined by "+" when several config files '
                "are given). Mesh-level work (normalize, decimate, raycache, target) lives in "
                "results/meshes/<mesh>/<key>/, keyed by a digest of its settings, and is shared by every experiment "
                'whose settings for it are equal. Not "meshes"'
            ),
            "type": "string",
            "pattern": EXPERIMENT_PATTERN,
            "maxLength": EXPERIMENT_MAX,
        },
        "device": {
            "description": (
                "where the torch stages run (optimize, bake, lod, relight, metrics, roundtrip): auto (CUDA when torch "
                "sees a GPU, else the CPU), cpu or cuda. Jobs that will use a GPU (cuda, or auto on a machine with an "
                "NVIDIA driver) ask for the resource gpu=1, and the workflow profile (profiles/default) allows one at a "
                'time: pass --resources gpu=N to share a GPU among N jobs. "auto" looks for the driver on the machine '
                "that builds the DAG: on a cluster whose GPUs are on other nodes, say cuda"
            ),
            "default": "auto",
            "enum": ["auto", "cpu", "cuda"],
        },
        **_refs(tuple(SECTIONS)),
    }


def _entry_defs() -> dict[str, Any]:
    """``$defs`` of the entries: a preset name, an id, a mesh entry."""
    return {
        "preset": {
            "description": (
                "a named optimisation preset (stages/config/presets.py): metal and rough after TANGO's demo scripts, "
                "paper = the paper's settings written out, fast and balanced = points measured by the speed/accuracy "
                "sweep under image guidance (they leave out the image size, the guidance and the ray cache; their "
                "learning rate was tuned on image targets). A preset sits at the level (prompt or variant) that names "
                "it: it beats less specific levels and loses to its own level's explicit keys."
            ),
            "enum": list(PRESETS),
        },
        "id": {"type": "string", "pattern": ID_PATTERN, "maxLength": ID_MAX},
        "mesh": {
            "type": "object",
            "additionalProperties": False,
            "properties": {
                "path": {
                    "description": (
                        "mesh file (OBJ, PLY, STL, OFF, GLB, GLTF), relative to the working directory; like every "
                        "path in a config, no braces (Snakemake reads {...} as a wildcard), control characters, line "
                        "separators or bidirectional controls"
                    ),
                    "type": "string",
                    "minLength": 1,
                    "maxLength": PATH_MAX,
                    "pattern": PATH_PATTERN,
                },
                "builtin": {"description": "a mesh generated in code", "enum": list(BUILTIN_MESHES)},
                "object": {
                    "description": "noun substituted for {object} in prompt texts (default the mesh id); one line",
                    "type": "string",
                    "minLength": 1,
                    "maxLength": 200,
                    "pattern": ONE_LINE,
                },
                **_refs(MESH_OVERRIDES),
            },
            "oneOf": [
                {"required": ["path"], "not": {"required": ["builtin"]}},
                {"required": ["builtin"], "not": {"required": ["path"]}},
            ],
        },
    }


@cache
def _schema() -> dict[str, Any]:
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": "tango-stylize workflow configuration",
        "description": (
            "Validated when the DAG is built (workflow/rules/common.smk -> stages.config). Unknown keys fail with "
            "their name and location; omitted keys take their defaults. Generated from the settings classes "
            f"(stages/config/sections.py) by `{WRITE_COMMAND}`."
        ),
        "type": "object",
        "additionalProperties": False,
        "required": ["meshes", "prompts"],
        "properties": _structure(),
        "$defs": {**_entry_defs(), **{name: section_schema(cls) for name, cls in SECTIONS.items()}},
    }


def schema() -> dict[str, Any]:
    """The workflow config's JSON schema (a fresh copy: callers may not change the cached one)."""
    return copy.deepcopy(_schema())


def yaml_text() -> str:
    """The schema as the YAML file holds it."""
    header = (
        f"# Generated by `{WRITE_COMMAND}` from stages/config/sections.py (the settings)\n"
        "# and stages/config/schema.py (the config's structure): edit those, not this file.\n"
    )
    body = yaml.safe_dump(_schema(), sort_keys=False, allow_unicode=True, width=110, default_flow_style=False)
    return header + body


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m stages.config.schema", description=__doc__.split("\n\n")[0])
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--write", action="store_true", help=f"(re)write {SCHEMA_PATH.relative_to(REPO_ROOT)}")
    group.add_argument("--check", action="store_true", help="exit 1 when the file differs from the generated schema")
    args = parser.parse_args(argv)
    text, where = yaml_text(), SCHEMA_PATH.relative_to(REPO_ROOT).as_posix()
    if args.write:
        with atomic_path(SCHEMA_PATH) as tmp:
            tmp.write_text(text)
        sys.stderr.write(f"wrote {where}\n")
        return 0
    if args.check:
        current = read_text(SCHEMA_PATH) if SCHEMA_PATH.is_file() else ""
        if current != text:
            sys.stderr.write(f"{where} is out of date with the settings classes: run {WRITE_COMMAND}\n")
            return 1
        sys.stderr.write(f"{where} is up to date\n")
        return 0
    sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
