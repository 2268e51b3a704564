"""The configuration reference, generated from the settings classes (through the schema).

    python -m stages.config.reference           # print the page
    python -m stages.config.reference --write   # (re)write docs/reference/configuration.md
    python -m stages.config.reference --check   # exit status 1 when that file differs from the page

Every config section that holds a stage's settings gets one table: each key of its settings class
(:mod:`stages.config.sections`, in declaration order) with its type, default, allowed values and
description, all from the class (the allowed values in words of the generated schema,
:mod:`stages.config.schema`). The top-level keys, the entries of
``meshes``, ``prompts`` and ``variants``, the presets (:mod:`stages.config.presets`) and the order
in which values resolve come from :mod:`stages.config.schema`. ``tests/docs/test_docs.py`` fails when the
checked-in page and this function's output differ. No torch, no numpy: stdlib and the layer's own
modules only.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
import sys
from pathlib import Path
from typing import Any

from ..core.safefiles import atomic_path, read_text
from ..core.settings import kind_words
from .presets import PRESETS
from .schema import REPO_ROOT, SCHEMA_PATH, schema
from .sections import PATH_PATTERN, SECTIONS

#: the page this module writes, relative to the repository root
PAGE = Path("docs") / "reference" / "configuration.md"
#: the command that rewrites it (the drift test names it)
WRITE_COMMAND = "python -m stages.config.reference --write"

#: the schema, as the page names it
SCHEMA_FILE = SCHEMA_PATH.relative_to(REPO_ROOT).as_posix()
#: the top-level keys that are not a stage's settings, in the order the page lists them
TOP_LEVEL = ("experiment", "meshes", "prompts", "grid", "variants", "device")


# ------------------------------------------------------------------------------------- text
def _one_line(text: str) -> str:
    """A schema description (folded YAML, maybe with newlines) as one line of Markdown."""
    return re.sub(r"\s+", " ", text).strip()


def _escape(text: str) -> str:
    """Text for a Markdown table cell: ``|`` escaped everywhere; ``<``, ``>`` and ``*`` outside code
    spans (``results/<experiment>/`` would otherwise be read as an HTML tag, ``*`` as emphasis)."""
    parts = text.split("`")
    for i in range(0, len(parts), 2):  # the even parts lie outside code spans
        parts[i] = parts[i].replace("<", "&lt;").replace(">", "&gt;").replace("*", "\\*")
    return "`".join(parts).replace("|", "\\|")


def _sentence(text: str) -> str:
    """A description as a sentence: capital first letter, full stop at the end."""
    text = _one_line(text)
    if not text:
        return text
    text = text[0].upper() + text[1:]
    return text if text.endswith(".") else text + "."


def _code(value: str) -> str:
    return f"`{value}`"


def _json(value: Any) -> str:
    """A value as it is written in a YAML config (flow style: JSON is YAML)."""
    if isinstance(value, tuple):
        value = list(value)
    return json.dumps(value)


# ------------------------------------------------------------------------------ settings
def _default(field: dataclasses.Field) -> Any:
    if field.default is not dataclasses.MISSING:
        return field.default
    if field.default_factory is not dataclasses.MISSING:
        return field.default_factory()
    return dataclasses.MISSING


# -------------------------------------------------------------------------------- schema
def _resolve(node: dict, schema: dict) -> dict:
    """A schema node with a local ``$ref`` (``#/$defs/name``) followed."""
    ref = node.get("$ref")
    if ref and ref.startswith("#/$defs/"):
        return schema["$defs"][ref.split("/")[-1]]
    return node


def _bound(low: Any, low_open: bool, high: Any, high_open: bool) -> str:
    if low is not None and high is not None:
        return f"{'(' if low_open else '['}{_json(low)}, {_json(high)}{')' if high_open else ']'}"
    if low is not None:
        return f"{'>' if low_open else '>='} {_json(low)}"
    if high is not None:
        return f"{'<' if high_open else '<='} {_json(high)}"
    return ""


def _allowed(node: dict) -> str:
    """The values a schema node allows, in words: its enum, constant, range, or an array's length
    and its items' constraints."""
    if "enum" in node:
        return ", ".join(_code(_json(v) if not isinstance(v, str) else v) for v in node["enum"])
    if "const" in node:
        return _code(str(node["const"]))
    if "anyOf" in node:  # a number or words (a count, or auto)
        return " or ".join(part for alt in node["anyOf"] if alt.get("type") != "null" and (part := _allowed(alt)))
    parts = []
    low = node.get("exclusiveMinimum", node.get("minimum"))
    high = node.get("exclusiveMaximum", node.get("maximum"))
    rng = _bound(low, "exclusiveMinimum" in node, high, "exclusiveMaximum" in node)
    if rng:
        parts.append(rng)
    if node.get("minLength") == 1:
        parts.append("not empty")
    elif "minLength" in node:
        parts.append(f"at least {node['minLength']} characters")
    if node.get("pattern") == PATH_PATTERN:
        parts.append("a path: no braces, control characters, line separators or bidirectional controls")
    elif "pattern" in node:
        parts.append(f"pattern {_code(node['pattern'])}")
    lo_n, hi_n = node.get("minItems"), node.get("maxItems")
    if lo_n is not None and lo_n == hi_n:
        parts.append(f"{lo_n} items")
    elif lo_n is not None and hi_n is not None:
        parts.append(f"{lo_n} to {hi_n} items")
    elif lo_n is not None:
        parts.append(f"at least {lo_n} item{'s' if lo_n != 1 else ''}")
    items = node.get("items")
    if isinstance(items, dict):
        inner = _allowed(items)
        if inner:
            parts.append(f"each {inner}")
    if "minProperties" in node:
        parts.append(f"at least {node['minProperties']} entr{'ies' if node['minProperties'] != 1 else 'y'}")
    return "; ".join(parts)


def _schema_type(node: dict, schema: dict) -> str:
    node = _resolve(node, schema)
    if "oneOf" in node:
        return " or ".join(dict.fromkeys(_schema_type(alt, schema) for alt in node["oneOf"]))
    if "const" in node:
        return _code(str(node["const"]))
    kind = node.get("type")
    if kind is None and "enum" in node:
        kind = "string"
    if kind == "object" and isinstance(node.get("additionalProperties"), dict):
        return "mapping of id to entry"
    words = {"object": "mapping", "array": "list"}
    if isinstance(kind, list):
        return " or ".join(words.get(k, k) for k in kind)
    return words.get(kind or "object", kind or "mapping")


# -------------------------------------------------------------------------------- tables
def _table(header: tuple[str, ...], rows: list[tuple[str, ...]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "| " + " | ".join("---" for _ in header) + " |"]
    lines += ["| " + " | ".join(cell or " " for cell in row) + " |" for row in rows]
    return lines


def section_rows(name: str) -> list[tuple[str, str, str, str, str]]:
    """One row per key of the config section ``name``: key, type, default, allowed, description."""
    cls = SECTIONS[name]
    props = schema()["$defs"][name]["properties"]
    kinds = cls.kinds()
    rows = []
    for field in dataclasses.fields(cls):
        node = props[field.name]
        rows.append(
            (
                _code(field.name),
                kind_words(kinds[field.name]),
                _code(_json(_default(field))),
                _escape(_allowed(node)),
                _escape(_one_line(node["description"])),
            )
        )
    return rows


def _entry_rows(props: dict, schema: dict) -> list[tuple[str, str, str, str]]:
    rows = []
    for key, node in props.items():
        target = _resolve(node, schema)
        if key in SECTIONS:
            description = f"overrides of the [`{key}`](#{key}) section for this entry"
        else:
            description = node.get("description") or target.get("description", "")
        rows.append((_code(key), _schema_type(node, schema), _escape(_allowed(target)), _escape(_one_line(description))))
    return rows


def _resolution(description: str) -> str:
    """The part of the schema's ``variants`` description that says how values resolve."""
    text = _one_line(description)
    start = text.find("Settings resolve")
    return text[start:] if start >= 0 else text


# ---------------------------------------------------------------------------------- page
def markdown() -> str:
    """The configuration reference page (Markdown for MkDocs), from the schema and the classes."""
    full = schema()
    props = full["properties"]
    out = [
        "<!-- Generated by `python -m stages.config.reference --write` from the settings classes "
        "(stages/config/sections.py) and the config's structure (stages/config/schema.py): edit those, not this page. -->",
        "",
        "# Configuration reference",
        "",
        "Every key a workflow config may hold, with its type, default, allowed values and meaning. "
        "Each is written once, in the settings classes (`stages/config/sections.py`); this page and "
        f"the JSON schema (`{SCHEMA_FILE}`) are generated from them, and every config is checked "
        "against that schema when the DAG is built: an unknown key or a value out of range fails at "
        "once, naming the key and where it is. An omitted key takes its default. "
        f"`{WRITE_COMMAND}` rewrites this page, and a test fails when it is out of date.",
        "",
        _escape(_one_line(full.get("description", ""))),
        "",
        "## Top-level keys",
        "",
    ]
    rows = []
    for key in TOP_LEVEL:
        node = props[key]
        rows.append(
            (
                _code(key),
                _schema_type(node, full),
                _code(_json(node["default"])) if "default" in node else ("required" if key in full.get("required", []) else ""),
                _escape(_allowed(_resolve(node, full))),
                _escape(_one_line(node.get("description", ""))),
            )
        )
    for key in props:
        if key in SECTIONS:
            doc = (SECTIONS[key].__doc__ or "").strip().split("\n\n")[0]
            rows.append((_code(key), "mapping", " ", " ", f"{_escape(_one_line(doc))} [Keys](#{key})."))
    out += _table(("key", "type", "default", "allowed", "description"), rows)

    mesh = full["$defs"]["mesh"]
    out += [
        "",
        "## Entries of `meshes`",
        "",
        "A mesh entry names exactly one source, `path` or `builtin`, and may override the mesh-level stages for this mesh alone.",
        "",
    ]
    out += _table(("key", "type", "allowed", "description"), _entry_rows(mesh["properties"], full))

    prompt = next(alt for alt in props["prompts"]["additionalProperties"]["oneOf"] if alt.get("type") == "object")
    out += [
        "",
        "## Entries of `prompts`",
        "",
        "A prompt is its text, or a mapping with the text, a preset and overrides of the per-cell stages.",
        "",
    ]
    out += _table(("key", "type", "allowed", "description"), _entry_rows(prompt["properties"], full))

    variant = props["variants"]["additionalProperties"]
    out += [
        "",
        "## Entries of `variants`",
        "",
        "A variant is a preset and overrides of the per-cell stages, applied to every mesh x prompt cell.",
        "",
    ]
    out += _table(("key", "type", "allowed", "description"), _entry_rows(variant["properties"], full))

    out += [
        "",
        "## How a cell's values resolve",
        "",
        _escape(_resolution(props["variants"]["description"])),
        "",
        "## Presets",
        "",
        _escape(_one_line(full["$defs"]["preset"]["description"])),
        "",
    ]
    preset_rows = [
        (_code(name), ", ".join(f"`{key}: {_json(value)}`" for key, value in values.items())) for name, values in PRESETS.items()
    ]
    out += _table(("preset", "the `optimize` settings it sets"), preset_rows)

    for name in SECTIONS:
        out += ["", f"## {name}", "", _escape(_sentence(full["$defs"][name]["description"])), ""]
        out += _table(("key", "type", "default", "allowed", "description"), section_rows(name))
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m stages.config.reference",
        description=f"Print, write or check the configuration reference ({PAGE.as_posix()}).",
    )
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--write", action="store_true", help=f"(re)write {PAGE.as_posix()}")
    group.add_argument("--check", action="store_true", help=f"exit 1 when {PAGE.as_posix()} differs from the generated page")
    args = parser.parse_args(argv)
    page = markdown()
    path = REPO_ROOT / PAGE
    if args.write:
        with atomic_path(path) as tmp:
            tmp.write_text(page)
        sys.stderr.write(f"wrote {PAGE.as_posix()}\n")
        return 0
    if args.check:
        if not path.is_file() or read_text(path) != page:
            sys.stderr.write(f"{PAGE.as_posix()} is out of date with the schema and the settings classes: run {WRITE_COMMAND}\n")
            return 1
        sys.stderr.write(f"{PAGE.as_posix()} is up to date\n")
        return 0
    sys.stdout.write(page)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
