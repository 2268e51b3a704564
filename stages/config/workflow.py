"""Loading and validating the workflow config, and resolving per-mesh and per-cell settings.

Used by ``workflow/rules/common.smk`` when the DAG is built and by tests. Validation is against
the schema generated from the settings classes (:mod:`.schema`); every error names the offending key and where it sits
(``meshes -> vase -> pth``), plus cross-reference checks the schema cannot express (grid ids that
do not exist).
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import logging
import math
import re
import sys
import unicodedata
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

from ..core.cli import add_configfile, stage_main
from ..core.errors import ConfigError
from ..core.shipped import shipped_archive
from .presets import PRESETS
from .schema import PROMPT_CHARS, schema
from .sections import FACE_BUDGET_FIELDS, PATH_PATTERN, SECTIONS, OptimizeSettings
from .yamlio import key_path, read_yaml_file, refuse_templates

log = logging.getLogger(__name__)

#: where the NVIDIA driver lists the GPUs it sees (one folder per GPU)
NVIDIA_GPUS = Path("/proc/driver/nvidia/gpus")
#: stages whose settings are per mesh (overridable in a mesh entry)
MESH_STAGES = ("normalize", "decimate", "raycache", "target")
#: stages after optimize whose settings are per grid cell (overridable per prompt and variant)
CELL_STAGES = ("bake", "export", "relight", "metrics", "roundtrip", "lod")
#: the folder under ``results/`` that holds mesh-level work (normalize, decimate, raycache,
#: target), shared by every experiment; so no experiment may be called this
MESH_WORK = "meshes"
#: an experiment's name: a folder under ``results/``
EXPERIMENT_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.+-]{0,127}")
#: a mesh, prompt or variant id: a folder name (the schema's ``$defs/id``, which a test holds equal)
ID_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
#: mesh ids taken by the experiment's own folders (``results/<experiment>/<id>/``), and why
RESERVED_MESH_IDS = {"report": "results/<experiment>/report/ holds the experiment's report, its tables and its pack"}
#: the name no id and no experiment may take: a folder of that name inside results/ would be taken
#: for the results folder itself, which alone may be a link (stages.core.safefiles)
RESERVED_NAME = "results"
#: the CPU threads of the rules whose jobs take more than one (their ``threads:`` read this; the
#: plan counts with it): the ray tracer and Mitsuba use every thread they get. Every other rule's
#: jobs take one, as their work is small operations that a second thread barely speeds up, but
#: optimize's, which follow the cell's guidance (:meth:`WorkflowConfig.optimize_threads`)
RULE_THREADS = {"raycache": 2, "target": 2}


def settings_digest(obj: Any) -> str:
    """12 hex digits of the SHA-256 of ``obj`` as canonical JSON (sorted keys): the key of a
    piece of mesh-level work, equal exactly when the settings that shape it are equal."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, separators=(",", ":")).encode()).hexdigest()[:12]


def experiment_name(config: dict, configfiles: list[str | Path]) -> str:
    """The experiment's name: the config's ``experiment`` key, else the stem of its config file
    (the stems joined by ``+`` when several files make up the config). Its outputs live in
    ``results/<name>/``."""
    name = config.get("experiment") or "+".join(Path(f).stem for f in configfiles) or "config"
    if not EXPERIMENT_RE.fullmatch(str(name)) or name == MESH_WORK or str(name).lower() == RESERVED_NAME:
        raise ConfigError(
            f"experiment name {name!r} (from {'the key `experiment`' if config.get('experiment') else 'the config file name'}) "
            f"must be letters, digits, '_', '.', '+' or '-', starting with a letter or digit, and neither "
            f"{MESH_WORK!r} (results/{MESH_WORK}/ holds the mesh-level work all experiments share) nor "
            f"{RESERVED_NAME!r} (the results folder's own name): "
            "set `experiment: <name>` in the config"
        )
    return str(name)


#: a key path as the messages write it (``raycache -> views``)
_where = key_path


def _describe(error) -> str:
    """One readable line for a jsonschema error."""
    from jsonschema.exceptions import best_match

    where = _where(error.absolute_path)
    v = error.validator
    if v == "additionalProperties":
        allowed = sorted(error.schema.get("properties", {}))
        extra = sorted(set(error.instance) - set(allowed))
        if error.absolute_path and error.absolute_path[0] == "variants" and len(error.absolute_path) == 2:
            return (
                f"unknown key(s) {', '.join(repr(k) for k in extra)} at {where}: a variant holds a "
                f"preset and per-cell stage overrides ({', '.join(allowed)}); mesh-level stages are "
                "overridden per mesh"
            )
        return f"unknown key(s) {', '.join(repr(k) for k in extra)} at {where}; allowed keys: {', '.join(allowed) or '(none)'}"
    if v == "required":
        return f"missing required key at {where}: {error.message}"
    if v == "oneOf" and error.absolute_path and error.absolute_path[0] == "meshes":
        return f"mesh {where} needs exactly one of 'path' or 'builtin'"
    if v == "oneOf" and list(error.absolute_path) == ["grid"]:
        return "grid must be 'all' or a list of {mesh: <id>, prompt: <id>} entries"
    if v == "pattern" and error.validator_value == PATH_PATTERN and isinstance(error.instance, str):
        noun = "mesh path" if list(error.absolute_path)[:1] == ["meshes"] else "path"
        return f"invalid {noun} at {where}: {_short(error.instance)} {path_problem(error.instance)}"
    if v == "pattern" and isinstance(error.instance, str) and CONTROL.search(error.instance):
        found = _short(error.instance)
        return f"invalid value at {where}: {found} holds {odd_character(error.instance)}: write it on one line, without it"
    if v == "pattern" and v in error.schema:
        return (
            f"invalid id {error.instance!r} at {where}: ids name result folders, so use letters, "
            "digits, '_', '-' and '.' only (starting with a letter or digit)"
        )
    if v == "oneOf" and len(error.absolute_path) == 2 and error.absolute_path[0] == "prompts":
        text = error.instance if isinstance(error.instance, str) else None
        if isinstance(error.instance, dict):
            text = error.instance.get("text")
            inner = [e for e in error.context or [] if e.relative_path or e.validator in ("additionalProperties", "required")]
            if inner and not (isinstance(text, str) and (len(text) > PROMPT_CHARS or CONTROL.search(text) or blank(text))):
                return _describe(best_match(inner))  # a bad key or value inside the prompt's own overrides
        if isinstance(text, str) and len(text) > PROMPT_CHARS:
            return (
                f"prompt {error.absolute_path[1]!r}: {len(text)} characters, at most {PROMPT_CHARS} (CLIP reads 77 tokens, about "
                "300 characters): shorten it"
            )
        if isinstance(text, str) and CONTROL.search(text):
            return f"prompt {error.absolute_path[1]!r} holds {odd_character(text)}: write it on one line, without it"
        if isinstance(text, str) and blank(text):
            return _blank_prompt(error.absolute_path[1])
        return f"prompt {error.absolute_path[1]!r} must be a text or {{text: ..., preset/optimize/bake/relight/lod: ...}}"
    bounds = {"maximum": "at most", "exclusiveMaximum": "below", "minimum": "at least", "exclusiveMinimum": "above"}
    if v in bounds and any("anchor" in str(p) for p in error.absolute_path):
        found, limit = _short(error.instance), f"{bounds[v]} {error.validator_value}"
        return f"invalid value at {where}: {found} is not an angle of the anchor view: choose {limit}"
    if v in ("maximum", "exclusiveMaximum", "maxItems"):
        found = f"{len(error.instance)} items" if v == "maxItems" else _short(error.instance)
        most = f"fewer than {error.validator_value}" if v == "exclusiveMaximum" else f"at most {error.validator_value}"
        return (
            f"invalid value at {where}: {found}, past this tool's limit (a job past it cannot fit a workstation; "
            f"the configuration reference lists every limit): choose {most}"
        )
    if v in ("minimum", "exclusiveMinimum", "minItems"):
        found = f"{len(error.instance)} items" if v == "minItems" else _short(error.instance)
        least = f"more than {error.validator_value}" if v == "exclusiveMinimum" else f"at least {error.validator_value}"
        return f"invalid value at {where}: {found} is too small: choose {least}"
    if v == "maxLength" and "propertyNames" in error.schema_path:
        count = len(error.instance)
        return f"invalid id {_short(error.instance)} at {where}: {count} characters, at most {error.validator_value}: shorten it"
    if v == "maxLength":
        return f"invalid value at {where}: {len(error.instance)} characters, at most {error.validator_value}: shorten it"
    if v == "type":
        types = [error.validator_value] if isinstance(error.validator_value, str) else list(error.validator_value)
        found = _short(error.instance)
        if "integer" in types and isinstance(error.instance, float) and error.instance.is_integer():
            return f"invalid value at {where}: {found} is not an integer: write {int(error.instance)}"
        number = _text_number(error.instance, types)
        if number is not None:
            kind = "a number" if "number" in types else "an integer"
            return (
                f"invalid value at {where}: {found} is a text to YAML 1.1, not {kind} (it reads decimal digits as a "
                f"number, a float with a point and a signed exponent: 1.0e-3): write {number!r}"
            )
        return f"invalid value at {where}: {found} is not of type {' or '.join(types)}"
    message = error.message if len(error.message) <= 300 else error.message[:299] + "…"
    return f"invalid value at {where}: {message}"


#: what a one-line text (a prompt, an object noun) and a path may not hold: control characters, line
#: and paragraph separators, bidirectional overrides and isolates
CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f\u2028\u2029\u202a-\u202e\u2066-\u2069]")
#: names of the control characters a message names in words
CONTROL_NAMES = {
    "\n": "a newline",
    "\t": "a tab",
    "\r": "a carriage return",
    "\x85": "a next-line character",
    "\u2028": "a line separator",
    "\u2029": "a paragraph separator",
}
#: the Unicode categories of characters that show nothing: format characters (zero-width spaces
#: and joiners, U+2060, U+FEFF), spaces (U+00A0 among them), controls, line and paragraph separators
INVISIBLE = frozenset({"Cf", "Zs", "Cc", "Zl", "Zp"})
#: bidirectional overrides and isolates, which show text in another order than it is stored
BIDI = re.compile(r"[\u202a-\u202e\u2066-\u2069]")


def blank(text: str) -> bool:
    """Whether ``text`` shows nothing: empty, or only characters of the :data:`INVISIBLE` categories
    (a zero-width space is as blank as an empty prompt)."""
    return all(unicodedata.category(c) in INVISIBLE for c in text)


def _blank_prompt(prompt_id) -> str:
    return (
        f"prompt {prompt_id!r} is blank (nothing in it shows: spaces or invisible characters only): write what the "
        "object should look like"
    )


def odd_character(text: str) -> str:
    """The first character of :data:`CONTROL` in ``text``, in words with its code point:
    ``a control character (U+2028, a line separator)``, ``a bidirectional control (U+202E)``."""
    found = CONTROL.search(text)
    if found is None:
        return "a character it may not hold"
    c = found.group()
    if BIDI.fullmatch(c):
        return f"a bidirectional control (U+{ord(c):04X})"
    name = CONTROL_NAMES.get(c)
    return f"a control character (U+{ord(c):04X}{f', {name}' if name else ''})"


def path_problem(path: str) -> str:
    """What a path that fails :data:`~stages.config.sections.PATH_PATTERN` holds, and what to do."""
    if "{" in path or "}" in path:
        return (
            "holds a brace; Snakemake reads {...} in a file name as a wildcard and would fill it in: rename the file "
            "(or link it under a name without braces)"
        )
    return (
        f"holds {odd_character(path)}, which makes a file name look other than it is: rename the file (or link it "
        "under a plain name)"
    )


def _text_number(value: Any, types: list[str]) -> int | float | None:
    """The number that a text standing where the schema wants one of ``types`` stands for, when
    YAML 1.1 left it a text: ``'0o20'`` (16), ``'1e-3'`` (0.001); None when it is no number, or not
    an integer where one is wanted."""
    if not isinstance(value, str) or not {"integer", "number"} & set(types):
        return None
    try:
        return int(value, 0)
    except ValueError:
        pass
    try:
        number = float(value)
    except ValueError:
        return None
    if "number" in types:
        return number if math.isfinite(number) else None
    return int(number) if math.isfinite(number) and number.is_integer() else None


def _short(value: Any, chars: int = 80) -> str:
    """``repr(value)``, cut to ``chars`` characters."""
    text = repr(value)
    return text if len(text) <= chars else text[: chars - 1] + "…"


def validate(config: dict, source: str = "config") -> None:
    """Raise :class:`ConfigError` listing every schema violation of ``config``, and every prompt or
    ``object`` noun that shows nothing (:func:`blank`), which no schema pattern can state."""
    lines = _problems(schema(), config)
    lines += [line for line in _blank_texts(config) if line not in lines]
    if lines:
        raise ConfigError(f"{source}: " + "; ".join(lines))


def _problems(schema: dict, data: Any) -> list[str]:
    """One line per problem of ``data`` under ``schema``: each NaN or infinite number (NaN passes
    every minimum and maximum, each comparison being false), then one line per key and value, its
    type error first (a string is not also "above the maximum")."""
    validator = _strict_validator()(schema)
    errors = sorted(validator.iter_errors(data), key=lambda e: (list(e.absolute_path), e.validator))
    bad = _non_finite(data)
    lines = [f"invalid value at {_where(path)}: {value} is not a finite number" for path, value in bad]
    lines += [
        f"invalid text at {_where(path)}: it holds a lone surrogate ({ascii(value)[1:-1][:60]}), half of a character that "
        "is not text: remove it"
        for path, value in _lone_surrogates(data)
    ]

    def key(path, instance) -> tuple:  # a key and its value (ids share their mapping's path)
        return (tuple(path), repr(instance)[:200])

    first: dict[tuple, Any] = {key(path, value): None for path, value in bad}
    for e in sorted(errors, key=lambda e: e.validator != "type"):
        first.setdefault(key(e.absolute_path, e.instance), e)
    lines += [
        _describe(e)
        for e in errors
        if e.validator in ("required", "additionalProperties") or first[key(e.absolute_path, e.instance)] is e
    ]
    return list(dict.fromkeys(lines))


def _blank_texts(config: Any) -> list[str]:
    """One line per prompt text and per mesh's ``object`` noun that is a text showing nothing."""
    lines = []
    prompts = config.get("prompts") if isinstance(config, dict) else None
    for prompt_id, entry in prompts.items() if isinstance(prompts, dict) else ():
        text = entry.get("text") if isinstance(entry, dict) else entry
        if isinstance(text, str) and blank(text):
            lines.append(_blank_prompt(prompt_id))
    meshes = config.get("meshes") if isinstance(config, dict) else None
    for mesh_id, entry in meshes.items() if isinstance(meshes, dict) else ():
        noun = entry.get("object") if isinstance(entry, dict) else None
        if isinstance(noun, str) and blank(noun):
            lines.append(
                f"invalid value at {_where(['meshes', mesh_id, 'object'])}: {_short(noun)} is blank (nothing in it "
                "shows): write the noun that replaces {object} in the prompts, or leave the key out (the mesh id)"
            )
    return lines


#: UTF-16 surrogates: a YAML "\ud800" escape gives one alone, which no file name, log or UTF-8 text can hold
SURROGATE = re.compile(r"[\ud800-\udfff]")


def _lone_surrogates(node: Any, path: tuple = ()) -> list[tuple[tuple, str]]:
    """``(path, text)`` of every key or string value of a parsed config that holds a surrogate."""
    if isinstance(node, str):
        return [(path, node)] if SURROGATE.search(node) else []
    if isinstance(node, dict):
        hits = [((*path, key), key) for key in node if isinstance(key, str) and SURROGATE.search(key)]
        return hits + [hit for key, value in node.items() for hit in _lone_surrogates(value, (*path, key))]
    if isinstance(node, list):
        return [hit for i, value in enumerate(node) for hit in _lone_surrogates(value, (*path, i))]
    return []


@cache
def _strict_validator():
    """JSON Schema's 2020-12 validator with ``integer`` meaning an integer, not also a float with
    no fraction (``8.0``: the schema's integers are counts and sizes, which a float breaks later)."""
    import jsonschema

    base = jsonschema.Draft202012Validator
    checker = base.TYPE_CHECKER.redefine("integer", lambda _, x: isinstance(x, int) and not isinstance(x, bool))
    return jsonschema.validators.extend(base, type_checker=checker)


def _non_finite(node: Any, path: tuple = ()) -> list[tuple[tuple, float]]:
    """``(path, value)`` of every NaN or infinite number in a parsed config."""
    if isinstance(node, float) and not math.isfinite(node):
        return [(path, node)]
    if isinstance(node, dict):
        return [hit for key, value in node.items() for hit in _non_finite(value, (*path, key))]
    if isinstance(node, list):
        return [hit for i, value in enumerate(node) for hit in _non_finite(value, (*path, i))]
    return []


@dataclass(frozen=True)
class Cell:
    mesh: str
    prompt: str
    variant: str


class WorkflowConfig:
    """A validated config with helpers the rules use (all pure; no file is written)."""

    def __init__(self, config: dict, source: str = "config") -> None:
        validate(config, source)
        for section in ("meshes", "prompts", "variants"):
            for key in config.get(section) or {}:
                if str(key).lower() == RESERVED_NAME:
                    raise ConfigError(
                        f"{source}: {section} -> {key}: the id {key!r} is reserved (the results folder's own name, "
                        "which no folder inside it may take): rename it"
                    )
        for mesh_id in config["meshes"]:
            if mesh_id.lower() in RESERVED_MESH_IDS:  # (a file system may ignore case)
                raise ConfigError(
                    f"{source}: meshes -> {mesh_id}: the mesh id {mesh_id!r} is reserved "
                    f"({RESERVED_MESH_IDS[mesh_id.lower()]}): rename the mesh (its `object` noun can stay {mesh_id!r})"
                )
        self.raw = copy.deepcopy(config)
        self.source = source
        self.meshes: dict[str, dict] = self.raw["meshes"]
        self.prompts: dict[str, str] = {k: (v if isinstance(v, str) else v["text"]) for k, v in self.raw["prompts"].items()}
        self.prompt_presets: dict[str, str | None] = {
            k: (None if isinstance(v, str) else v.get("preset")) for k, v in self.raw["prompts"].items()
        }
        self.variants: dict[str, dict] = self.raw.get("variants") or {"base": {}}
        grid = self.raw.get("grid", "all")
        if grid == "all":
            pairs = [(m, p) for m in self.meshes for p in self.prompts]
        else:
            pairs = [(g["mesh"], g["prompt"]) for g in grid]
            problems = []
            for i, (m, p) in enumerate(pairs):
                if m not in self.meshes:
                    problems.append(f"grid -> {i} -> mesh: {m!r} is not a mesh id ({', '.join(self.meshes)})")
                if p not in self.prompts:
                    problems.append(f"grid -> {i} -> prompt: {p!r} is not a prompt id ({', '.join(self.prompts)})")
            if problems:
                raise ConfigError(f"{source}: " + "; ".join(problems))
        self.pairs = list(dict.fromkeys(pairs))
        for m, p in self.pairs:
            if len(self.prompt_text(m, p)) > PROMPT_CHARS:
                raise ConfigError(
                    f"{source}: prompt {p!r} for mesh {m!r}: {len(self.prompt_text(m, p))} characters with "
                    f"{{object}} replaced, at most {PROMPT_CHARS}: shorten the prompt or the mesh's `object` noun"
                )
        self._keys: dict[str, dict[str, str]] = {}
        # Build every mesh's stage settings now so bad values fail when the DAG is built.
        for mesh_id in self.meshes:
            for stage in MESH_STAGES:
                self.stage_settings(mesh_id, stage)
        for cell in self.cells:
            self.optimize_settings(cell.prompt, cell.variant)
            for stage in CELL_STAGES:
                self.cell_stage_settings(stage, cell.prompt, cell.variant)
        self.report_settings()

    # ---- ids -------------------------------------------------------------------------------
    @property
    def device(self) -> str:
        """Where the torch stages run: ``auto``, ``cpu`` or ``cuda`` (their ``--device``)."""
        return self.raw.get("device", "auto")

    def gpu_jobs(self, driver: Path = NVIDIA_GPUS) -> int:
        """The ``gpu`` resource a torch job asks for: 1 when it will run on a GPU (``cuda``, or
        ``auto`` where the NVIDIA driver lists a GPU under ``driver``), else 0. Decided without
        importing torch (the DAG stays torch-free); ``auto`` still falls back to the CPU inside
        the stage if torch cannot use the GPU."""
        if self.device == "cpu":
            return 0
        if self.device == "cuda":
            return 1
        return int(driver.is_dir() and any(driver.iterdir()))

    def job_threads(self, rule: str) -> int:
        """The CPU threads of ``rule``'s jobs (:data:`RULE_THREADS`; 1 for the others) but
        optimize's (per cell: :meth:`optimize_threads`)."""
        return RULE_THREADS.get(rule, 1)

    def optimize_threads(self, prompt_id: str, variant_id: str) -> int:
        """The CPU threads of a cell's optimize job (the rule's ``threads``): its guidance mode's
        :attr:`~stages.config.guidance_modes.GuidanceMode.cpu_threads` on a CPU run, 2 where the
        job runs on a GPU (the CPU only feeds it)."""
        if self.gpu_jobs():
            return 2
        return self.optimize_settings(prompt_id, variant_id).guidance_mode().cpu_threads

    @property
    def grid_meshes(self) -> list[str]:
        """Mesh ids that appear in the grid, in config order."""
        used = {m for m, _ in self.pairs}
        return [m for m in self.meshes if m in used]

    @property
    def cells(self) -> list[Cell]:
        return [Cell(m, p, v) for m, p in self.pairs for v in self.variants]

    def grid_text(self) -> str:
        """The grid in words, as it is made: ``"2 meshes x 2 prompts x 1 variant = 4 cells"`` where
        every mesh meets every prompt, else ``"2 mesh/prompt pairs x 1 variant = 2 cells"``."""

        def count(n: int, word: str, plural: str = "") -> str:
            return f"{n} {word if n == 1 else plural or word + 's'}"

        meshes, prompts = len(self.grid_meshes), len({p for _, p in self.pairs})
        if len(self.pairs) == meshes * prompts:
            made = f"{count(meshes, 'mesh', 'meshes')} x {count(prompts, 'prompt')}"
        else:
            made = count(len(self.pairs), "mesh/prompt pair")
        return f"{made} x {count(len(self.variants), 'variant')} = {count(len(self.cells), 'cell')}"

    # ---- per-mesh --------------------------------------------------------------------------
    def mesh_source(self, mesh_id: str) -> str:
        entry = self.meshes[mesh_id]
        return f"builtin:{entry['builtin']}" if "builtin" in entry else entry["path"]

    def mesh_file(self, mesh_id: str) -> str | None:
        """The mesh's file when it is a file that exists (Snakemake input), else None; for a mesh
        that travels with the project compressed, its archive (the same input before and after the
        first run unpacks it, :mod:`stages.core.shipped`)."""
        entry = self.meshes[mesh_id]
        if "path" not in entry:
            return None
        archive = shipped_archive(entry["path"])
        if archive is not None:
            return str(archive)
        return entry["path"] if Path(entry["path"]).is_file() else None

    def stage_dict(self, mesh_id: str, stage: str) -> dict[str, Any]:
        """Global section of ``stage`` updated by the mesh's own override (shallow, per key)."""
        merged = dict(self.raw.get(stage) or {})
        merged.update(self.meshes[mesh_id].get(stage) or {})
        return merged

    def stage_settings(self, mesh_id: str, stage: str):
        if stage not in MESH_STAGES:
            raise ValueError(f"{stage!r} is not a per-mesh stage ({', '.join(MESH_STAGES)})")
        cls = SECTIONS[stage]
        try:
            return cls.from_dict(self.stage_dict(mesh_id, stage))
        except ConfigError as exc:
            raise ConfigError(f"{self.source}: mesh {mesh_id!r}: {exc}") from exc

    # ---- per-cell ----------------------------------------------------------------------------
    def optimize_layers(self, prompt_id: str, variant_id: str) -> list[tuple[str, dict[str, Any]]]:
        """The optimize overrides of a cell, least specific first, each named by where it comes from.

        Order (later wins): the config's ``optimize`` section < the prompt's preset < the prompt's
        ``optimize`` overrides < the variant's preset < the variant's ``optimize`` overrides. The
        more specific level wins (a variant over a prompt over the base section); within a level,
        explicit keys win over the level's preset. Keys no layer sets keep their schema defaults.
        """
        layers: list[tuple[str, dict[str, Any]]] = [("config optimize section", dict(self.raw.get("optimize") or {}))]
        prompt = self.raw["prompts"][prompt_id]
        variant = self.variants[variant_id] or {}
        for level, entry in ((f"prompt {prompt_id!r}", prompt), (f"variant {variant_id!r}", variant)):
            if not isinstance(entry, dict):
                continue
            if entry.get("preset"):
                layers.append((f"preset {entry['preset']!r} of {level}", dict(PRESETS[entry["preset"]])))
            if entry.get("optimize"):
                layers.append((f"{level} optimize overrides", dict(entry["optimize"])))
        return layers

    def optimize_dict(self, prompt_id: str, variant_id: str) -> dict[str, Any]:
        """Resolved optimize overrides of a cell (see :meth:`optimize_layers` for the order)."""
        merged: dict[str, Any] = {}
        for _, layer in self.optimize_layers(prompt_id, variant_id):
            merged.update(layer)
        return merged

    def cell_stage_layers(self, stage: str, prompt_id: str, variant_id: str) -> list[tuple[str, dict[str, Any]]]:
        """Overrides of a per-cell stage after optimize, least specific first: the config's
        section < the prompt's overrides < the variant's overrides."""
        layers: list[tuple[str, dict[str, Any]]] = [(f"config {stage} section", dict(self.raw.get(stage) or {}))]
        prompt = self.raw["prompts"][prompt_id]
        if isinstance(prompt, dict) and prompt.get(stage):
            layers.append((f"prompt {prompt_id!r} {stage} overrides", dict(prompt[stage])))
        variant = self.variants[variant_id] or {}
        if variant.get(stage):
            layers.append((f"variant {variant_id!r} {stage} overrides", dict(variant[stage])))
        return layers

    def explain(self, cell: Cell, stage: str = "optimize") -> list[tuple[str, Any, str]]:
        """How one cell's settings of ``stage`` were resolved: ``(key, value, source)`` for every
        setting, where source is the layer that set it last, or "default" (the settings class,
        which the schema mirrors)."""
        if stage == "optimize":
            layers = self.optimize_layers(cell.prompt, cell.variant)
            resolved = self.optimize_settings(cell.prompt, cell.variant)
        elif stage in MESH_STAGES:
            layers = [(f"config {stage} section", dict(self.raw.get(stage) or {}))]
            layers.append((f"mesh {cell.mesh!r} {stage} overrides", dict(self.meshes[cell.mesh].get(stage) or {})))
            resolved = self.stage_settings(cell.mesh, stage)
        else:
            layers = self.cell_stage_layers(stage, cell.prompt, cell.variant)
            resolved = self.cell_stage_settings(stage, cell.prompt, cell.variant)
        source = {}
        for name, layer in layers:
            for key in layer:
                source[key] = name
        return [(f.name, getattr(resolved, f.name), source.get(f.name, "default")) for f in dataclasses.fields(resolved)]

    def optimize_settings(self, prompt_id: str, variant_id: str):
        try:
            return OptimizeSettings.from_dict(self.optimize_dict(prompt_id, variant_id))
        except ConfigError as exc:
            raise ConfigError(f"{self.source}: prompt {prompt_id!r}, variant {variant_id!r}: {exc}") from exc

    def cell_stage_settings(self, stage: str, prompt_id: str, variant_id: str):
        """Settings of a per-cell stage after optimize (bake, export, relight): the config's
        section, updated by the prompt's and then the variant's overrides of that stage."""
        if stage not in CELL_STAGES:
            raise ValueError(f"{stage!r} is not a per-cell stage after optimize ({', '.join(CELL_STAGES)})")
        cls = SECTIONS[stage]
        merged: dict[str, Any] = {}
        for _, layer in self.cell_stage_layers(stage, prompt_id, variant_id):
            merged.update(layer)
        try:
            return cls.from_dict(merged)
        except ConfigError as exc:
            raise ConfigError(f"{self.source}: prompt {prompt_id!r}, variant {variant_id!r}: {exc}") from exc

    def report_settings(self):
        """The ``report`` section, its variant names checked against the config's variants."""
        try:
            settings = SECTIONS["report"].from_dict(self.raw.get("report"))
        except ConfigError as exc:
            raise ConfigError(f"{self.source}: {exc}") from exc
        named = ([settings.reference] if settings.reference is not None else []) + list(settings.ablations or ())
        unknown = [v for v in named if v not in self.variants]
        if unknown:
            raise ConfigError(
                f"{self.source}: report names variant(s) {', '.join(repr(v) for v in unknown)} that the config does not "
                f"define (variants: {', '.join(self.variants)})"
            )
        return settings

    def decimation_pairs(self) -> dict[str, str]:
        """Decimated mesh id -> a full-resolution mesh id with the same source (robustness)."""
        full = {self.mesh_source(m): m for m in self.grid_meshes if not self.decimated(m)}
        return {m: full[self.mesh_source(m)] for m in self.grid_meshes if self.decimated(m) and self.mesh_source(m) in full}

    def candidate_prompts(self, mesh_id: str) -> list[str]:
        """The texts of every prompt of the grid, for ``mesh_id`` (R-precision candidates)."""
        ids = list(dict.fromkeys(p for _, p in self.pairs))
        return [self.prompt_text(mesh_id, p) for p in ids]

    def clip_specs(self) -> list:
        """Every real (non-test) CLIP the grid needs: guidance models, then evaluation models."""
        specs = set()
        for c in self.cells:
            s = self.optimize_settings(c.prompt, c.variant)
            if s.guidance_mode().uses_clip and not s.clip_tiny_test:
                specs.add(s.clip_spec())
            m = self.cell_stage_settings("metrics", c.prompt, c.variant)
            if m.clip and not m.clip_tiny_test:
                specs.add(m.clip_spec())
        return sorted(specs, key=lambda spec: (spec.section != "optimize", str(spec)))

    def target_material(self, prompt_id: str, variant_id: str) -> str | None:
        """The procedural material whose Mitsuba targets a cell trains on, or None when the cell
        needs none (CLIP guidance, or image targets rendered by our own SG renderer)."""
        s = self.optimize_settings(prompt_id, variant_id)
        return s.target_material if s.mitsuba_targets() else None

    def target_jobs(self, meshes: set[str] | None = None) -> list[tuple[str, str]]:
        """The Mitsuba target jobs of this config, one per ``(mesh, material)`` that some cell
        trains on, sorted; ``meshes``: only those of these meshes (e.g. the ones a run still has
        to render)."""
        jobs = {(c.mesh, m) for c in self.cells if (m := self.target_material(c.prompt, c.variant))}
        return sorted(j for j in jobs if meshes is None or j[0] in meshes)

    def roundtrip_cells(self) -> list[Cell]:
        """The cells whose assets go through Blender (``roundtrip.enabled``)."""
        return [c for c in self.cells if self.cell_stage_settings("roundtrip", c.prompt, c.variant).enabled]

    def face_budget_fields(self, mesh_id: str) -> dict[str, Any]:
        """With ``decimate.mode: budget``, the mesh's ray-cache settings that set its face budget
        (:data:`FACE_BUDGET_FIELDS`), which the decimate job reads; else nothing, so that other
        ray-cache edits neither rerun nor re-key a decimation that does not read them."""
        if self.stage_settings(mesh_id, "decimate").mode != "budget":
            return {}
        cache = self.stage_settings(mesh_id, "raycache").to_dict()
        return {k: cache[k] for k in FACE_BUDGET_FIELDS}

    def mesh_work_keys(self, mesh_id: str) -> dict[str, str]:
        """The key of each piece of the mesh's mesh-level work (``normalize``, ``decimate`` when
        enabled, ``raycache``, ``target``): a digest of the mesh's source and of the settings of
        that stage and of every stage before it. Two experiments whose keys are equal share the
        folder ``results/meshes/<mesh>/<key>/<stage>/`` and so never recompute each other's work;
        a changed setting gives a new key (and leaves the old folder to the experiments using it)."""
        if mesh_id not in self._keys:
            keys = {
                "normalize": settings_digest(
                    {"source": self.mesh_source(mesh_id), "normalize": self.stage_settings(mesh_id, "normalize").keyed()}
                )
            }
            traced = keys["normalize"]
            if self.decimated(mesh_id):
                keys["decimate"] = traced = settings_digest(
                    {
                        "normalize": keys["normalize"],
                        "decimate": self.stage_settings(mesh_id, "decimate").to_dict(),
                        "raycache": self.face_budget_fields(mesh_id),
                    }
                )
            keys["raycache"] = settings_digest({"mesh": traced, "raycache": self.stage_settings(mesh_id, "raycache").to_dict()})
            keys["target"] = settings_digest(
                {
                    "normalize": keys["normalize"],
                    "raycache": keys["raycache"],
                    "target": self.stage_settings(mesh_id, "target").to_dict(),
                }
            )
            self._keys[mesh_id] = keys
        return self._keys[mesh_id]

    def decimated(self, mesh_id: str) -> bool:
        return bool(self.stage_settings(mesh_id, "decimate").enabled)

    def prompt_text(self, mesh_id: str, prompt_id: str) -> str:
        noun = self.meshes[mesh_id].get("object", mesh_id)
        return self.prompts[prompt_id].replace("{object}", noun)


def parse_cell(text: str, cfg: WorkflowConfig) -> Cell:
    """``mesh/prompt/variant`` (the variant may be left out when the config has one) -> a grid cell."""
    parts = text.split("/")
    if len(parts) == 2 and len(cfg.variants) == 1:
        parts.append(next(iter(cfg.variants)))
    if len(parts) != 3:
        raise ConfigError(f"cell {text!r} is not mesh/prompt/variant")
    cell = Cell(*parts)
    if cell not in cfg.cells:
        cells = ", ".join(f"{c.mesh}/{c.prompt}/{c.variant}" for c in cfg.cells[:12])
        raise ConfigError(
            f"{cfg.source}: {text!r} is not a cell of the grid (cells: {cells}{', ...' if len(cfg.cells) > 12 else ''})"
        )
    return cell


def main(argv: list[str] | None = None) -> int:
    """``python -m stages.config --configfile C [overlay ...] --cell mesh/prompt/variant [--stage optimize]``:
    print how one cell's settings were resolved, key by key, with where each value came from.
    ``--check``: read the config as the workflow will and refuse what its start refuses, by the same
    code (:func:`workflow_config`: the bounded reader, templates refused, every key against the
    schema and the settings, the experiment's name), without Snakemake, and say so in one line: how
    to look at a config received from someone else before running it. Whether the CLIP weights and
    the tools the run needs are here is the doctor's to say (``python -m stages.doctor``).
    ``--mesh-work``: print the folders of the mesh-level work the experiment uses, one per line
    (``results/meshes/<mesh>/<key>``; the folders of other keys serve other experiments or none)."""

    def arguments(parser):
        add_configfile(parser)
        parser.add_argument("--cell", help="mesh/prompt/variant")
        parser.add_argument(
            "--stage",
            default="optimize",
            choices=("optimize", *CELL_STAGES, *MESH_STAGES),
            help="whose settings --cell explains (default optimize)",
        )
        parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
        parser.add_argument("--mesh-work", action="store_true", help="print the experiment's mesh-level work folders")
        parser.add_argument(
            "--check", action="store_true", help="check a config (a received one, say) as data, without Snakemake: one line"
        )

    def body(args):
        cfg, experiment = workflow_config(args.configfile)
        files = ", ".join(map(str, args.configfile))
        if args.check:  # refused by now if the workflow's start would refuse it
            doctor = "python -m stages.doctor --configfile " + " ".join(map(str, args.configfile))
            sys.stdout.write(
                f"{files}: a valid config of {cfg.grid_text()}; no template, every key within its bounds; "
                f"experiment {experiment!r}. "
                f"Whether its weights and tools are here: {doctor}\n"
            )
            return
        if args.mesh_work:
            folders = {f"results/{MESH_WORK}/{m}/{key}" for m in cfg.grid_meshes for key in cfg.mesh_work_keys(m).values()}
            sys.stdout.write("".join(f"{f}\n" for f in sorted(folders)))
            return
        if args.cell is None:
            raise ConfigError("give --cell mesh/prompt/variant (or --mesh-work, or --check)")
        rows = cfg.explain(parse_cell(args.cell, cfg), args.stage)
        if args.json:
            sys.stdout.write(json.dumps([{"key": k, "value": v, "source": s} for k, v, s in rows], indent=1) + "\n")
            return
        width = max(len(k) for k, _, _ in rows)
        vwidth = min(max(len(json.dumps(v)) for _, v, _ in rows), 40)
        sys.stdout.write(f"{args.stage} settings of {args.cell} ({files}); later sources win:\n")
        for k, v, src in rows:
            sys.stdout.write(f"  {k:<{width}}  {json.dumps(v):<{vwidth}}  {src}\n")

    return stage_main("config", main.__doc__, arguments, body, argv)


def workflow_config(configfiles: Sequence[str | Path], loaded: dict | None = None) -> tuple[WorkflowConfig, str]:
    """The config the workflow builds its jobs from and the experiment's name, after every check of
    the workflow's start, here and in ``workflow/rules/common.smk`` alike: each file read through the
    bounded reader (:func:`read_yaml`: size, depth, aliases, numbers, duplicate keys, templates),
    the config against the schema and every cell's settings (:class:`WorkflowConfig`), the
    experiment's name (:func:`experiment_name`). ``loaded``: the config as Snakemake loaded and
    merged the files (the workflow's); None: the files merged here as Snakemake merges them. One line
    of :class:`ConfigError` for the first refusal."""
    source = ", ".join(str(p) for p in configfiles)
    merged: dict = {}
    for path in configfiles:
        merged = merge_config(merged, read_yaml(Path(path)))
    config = merged if loaded is None else loaded
    cfg = WorkflowConfig(config, source)
    try:
        experiment = experiment_name(config, list(configfiles))
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None
    return cfg, experiment


def load_config_file(path: str | Path) -> WorkflowConfig:
    """The config of one file, checked as the workflow checks it (:func:`workflow_config`)."""
    return workflow_config([path])[0]


def read_yaml(path: Path) -> dict:
    """A config file's mapping, read as bounded data (:mod:`stages.config.yamlio`: size, depth,
    aliases, numbers, duplicate keys, templates), or a one-line error naming the file."""
    data = read_yaml_file(Path(path))
    refuse_templates(data, str(path))
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level, got {type(data).__name__}")
    return data


def merge_config(base: dict, update: dict) -> dict:
    """``base`` updated by ``update`` as Snakemake merges several --configfile files: mappings
    key by key (recursively), anything else replaced."""
    out = dict(base)
    for key, value in update.items():
        out[key] = merge_config(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def load_config_files(paths: list[str | Path]) -> WorkflowConfig:
    """The config made of several files, later ones updating earlier ones (as ``snakemake
    --configfile a.yaml b.yaml``), checked as the workflow checks it (:func:`workflow_config`)."""
    return workflow_config(paths)[0]


if __name__ == "__main__":
    raise SystemExit(main())
