"""Reading a config file as data, bounded: PyYAML's safe loader with the checks a file from someone
else needs before anything walks its values.

* **Size** (:data:`MAX_BYTES`), **nesting depth** (:data:`MAX_DEPTH`) and **expanded size**
  (:data:`MAX_VALUES`): YAML aliases let a 521-byte file stand for 10^8 values (a "billion laughs"),
  which PyYAML builds cheaply by sharing but every later walk (the schema's validation) expands.
  The expanded count is taken on the composed node graph, each shared node counted once per use
  but visited once, before any value is constructed.
* **Duplicate keys**: YAML says a mapping's keys are unique, PyYAML keeps the last silently; a
  second ``optimize:`` block would drop the first one's settings. Refused, naming both lines.
* **Aliases that loop or nest**: an alias inside the value it names (``a: &a [*a]``) stands for
  an infinite value, and a chain of aliases each nesting the one before nests deeper than the
  text does: both are refused, the nesting counted through the aliases against :data:`MAX_DEPTH`.
* **Numbers in YAML 1.1's other forms**: ``0x10``, ``0b10``, ``020`` (octal), ``1:30`` (base 60)
  and ``1_000`` are integers to YAML 1.1 (16, 2, 16, 90, 1000), which a reader of the file would
  not guess; wherever a scalar resolves to an integer or a float it must be written in decimal,
  and the message says which number to write.
* **Templates**: a top-level ``__use_yte__`` asks Snakemake to evaluate the file as a YTE template,
  which runs Python while Snakemake loads it. The project's loaders refuse such a file
  (:data:`ALLOW_YTE_ENV` lets a user who wrote the template opt in). Whether it is set is read
  from the environment the process started with (:func:`initial_environment`), which a template
  that changes ``os.environ`` while Snakemake evaluates it does not change.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import yaml

from ..core.errors import ConfigError, StageInputError
from ..core.safefiles import RECORD_LIMIT, read_bytes, user_file

#: the largest config file read (bytes); the shipped configs are under 10 kB
MAX_BYTES = 4 * 2**20
#: the deepest nesting of mappings and lists (the schema's is 5)
MAX_DEPTH = 64
#: the most values (scalars, mappings, lists) a file may expand to through its aliases
MAX_VALUES = 200_000
#: the environment variable that lets the workflow go on with a config that used a YTE template
ALLOW_YTE_ENV = "TANGO_ALLOW_YTE"
YTE_KEY = "__use_yte__"
#: where Linux shows the environment a process was started with (later changes of
#: ``os.environ`` do not alter it)
INITIAL_ENVIRON = Path("/proc/self/environ")

INT_TAG = "tag:yaml.org,2002:int"
FLOAT_TAG = "tag:yaml.org,2002:float"
#: an integer or a float as a reader expects it: decimal digits, no separators
DECIMAL_INT = re.compile(r"[-+]?(?:0|[1-9][0-9]*)")
DECIMAL_FLOAT = re.compile(r"[-+]?(?:[0-9]+\.[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]+)?|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN)")
#: YAML 1.1's other forms of a number, and what each is in words
OTHER_FORMS = (
    (re.compile(r"[-+]?0b[01_]+"), "a binary number"),
    (re.compile(r"[-+]?0x[0-9a-fA-F_]+"), "a hexadecimal number"),
    (re.compile(r"[-+]?[0-9][0-9_]*(?::[0-5]?[0-9])+(?:\.[0-9_]*)?"), "a base-60 number"),
    (re.compile(r"[-+]?0[0-7_]+"), "an octal number (a leading zero)"),
    (re.compile(r".*_.*"), "a number with digit separators (_)"),
)


def key_path(path: Iterable) -> str:
    """A key path as the messages write it (``raycache -> views``); a key that is not a plain word
    (a newline, a surrogate, a space in it) is written as its escaped repr, so the message stays one
    printable line."""
    path = list(path)
    if not path:
        return "the top level"
    return " -> ".join(str(p) if isinstance(p, int) or re.fullmatch(r"[A-Za-z0-9_.-]+", str(p)) else ascii(p) for p in path)


class _BoundedLoader(yaml.SafeLoader):
    def __init__(self, stream, source: str) -> None:
        super().__init__(stream)
        self.source = source
        self.depth = 0

    def compose_node(self, parent, index):
        self.depth += 1
        try:
            if self.depth > MAX_DEPTH:
                line = self.peek_event().start_mark.line + 1
                raise ConfigError(
                    f"{self.source}: nested deeper than {MAX_DEPTH} levels (line {line}): a config is a few levels deep; "
                    "this file is not one"
                )
            return super().compose_node(parent, index)
        finally:
            self.depth -= 1

    def construct_mapping(self, node, deep=False):
        seen: dict[Any, int] = {}
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=True)
            line = key_node.start_mark.line + 1
            try:
                first = seen.get(key)
            except TypeError:  # an unhashable key: PyYAML's own error follows
                continue
            if first is not None:
                where = f"lines {first} and {line}" if first != line else f"line {line}"
                raise ConfigError(
                    f"{self.source}: key {key!r} appears twice in one mapping ({where}); YAML keeps only "
                    "the last, so the first one's settings would be lost: merge the two into one"
                )
            seen[key] = line
        return super().construct_mapping(node, deep)


def _children(node: yaml.Node) -> list[tuple[yaml.Node, Any]]:
    """A node's children with the key each sits under (a mapping's key sits under itself)."""
    if isinstance(node, yaml.MappingNode):
        children = []
        for key, value in node.value:
            label = key.value if isinstance(key, yaml.ScalarNode) else "?"
            children += [(key, label), (value, label)]
        return children
    if isinstance(node, yaml.SequenceNode):
        return [(v, i) for i, v in enumerate(node.value)]
    return []


def check_graph(node: yaml.Node, source: str, loader: yaml.SafeLoader) -> None:
    """Refuse, on the composed node graph and before any value is built, an alias inside the value
    it names, nesting deeper than :data:`MAX_DEPTH` counted through aliases, and an integer or a
    float written in one of YAML 1.1's other forms (:func:`number_problem`). Each node is visited
    once, without recursion."""
    height: dict[int, int] = {}
    open_nodes: set[int] = set()  # the nodes whose values are being walked: the current node's ancestors
    stack: list[tuple[yaml.Node, tuple, bool]] = [(node, (), False)]
    while stack:
        n, path, done = stack.pop()
        if done:
            open_nodes.discard(id(n))
            height[id(n)] = 1 + max((height[id(c)] for c, _ in _children(n)), default=0)
            if height[id(n)] > MAX_DEPTH:
                raise ConfigError(
                    f"{source}: nested deeper than {MAX_DEPTH} levels through its aliases (*name; line "
                    f"{n.start_mark.line + 1}): a config is a few levels deep; this file is not one"
                )
            continue
        if id(n) in open_nodes:
            raise ConfigError(
                f"{source}: invalid value at {key_path(path)} (line {n.start_mark.line + 1}): an alias (*name) of the "
                "value it stands in, which would hold itself without end: write the value out"
            )
        if id(n) in height:
            continue
        if isinstance(n, yaml.ScalarNode):
            problem = number_problem(n, loader)
            if problem:
                raise ConfigError(f"{source}: invalid value at {key_path(path)} (line {n.start_mark.line + 1}): {problem}")
            height[id(n)] = 1
            continue
        open_nodes.add(id(n))
        stack.append((n, path, True))
        stack.extend((c, (*path, label), False) for c, label in reversed(_children(n)))


def number_problem(node: yaml.ScalarNode, loader: yaml.SafeLoader) -> str | None:
    """What is wrong with a scalar that YAML 1.1 reads as an integer or a float written in another
    form than decimal digits (``0x10``, ``0b10``, ``020``, ``1:30``, ``1_000``); None when nothing is."""
    if node.tag == INT_TAG:
        if DECIMAL_INT.fullmatch(node.value):
            return None
        value = loader.construct_yaml_int(node)
    elif node.tag == FLOAT_TAG:
        if DECIMAL_FLOAT.fullmatch(node.value):
            return None
        value = loader.construct_yaml_float(node)
    else:
        return None
    text = node.value
    kind = next((words for form, words in OTHER_FORMS if form.fullmatch(text)), "a number in a form YAML 1.1 alone reads")
    remedy = f"write {value!r}"
    if kind.startswith("an octal"):
        plain = ("-" if text.startswith("-") else "") + (text.lstrip("+-").lstrip("0_").replace("_", "") or "0")
        remedy += f" (or {plain} if that was meant)" if plain != str(value) else ""
    elif kind == "a base-60 number":
        remedy += f" (or quote it, {text!r}, if it is a text)"
    return f"{text} is {kind}, which YAML 1.1 reads as {value!r}: {remedy}"


def expanded_values(node: yaml.Node, limit: int = MAX_VALUES) -> int:
    """The number of values ``node`` stands for with every alias expanded, counted on the node graph
    (each node visited once; a node used ``k`` times counts ``k`` times), stopping past ``limit``."""
    sizes: dict[int, int] = {}

    def size(n: yaml.Node) -> int:
        if id(n) in sizes:
            return sizes[id(n)]
        if isinstance(n, yaml.MappingNode):
            total = 1 + sum(size(k) + size(v) for k, v in n.value)
        elif isinstance(n, yaml.SequenceNode):
            total = 1 + sum(size(v) for v in n.value)
        else:
            total = 1
        sizes[id(n)] = total = min(total, limit + 1)
        return total

    return size(node)


def load_yaml(text: str, source: str) -> Any:
    """``text`` (a YAML document) as data, or one-line :class:`ConfigError` naming ``source``."""
    if len(text.encode("utf-8", "surrogatepass")) > MAX_BYTES:
        raise ConfigError(f"{source}: {len(text)} characters, more than a config's {MAX_BYTES // 2**20} MiB: not a config file")
    loader = _BoundedLoader(text, source)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        check_graph(node, source, loader)
        count = expanded_values(node)
        if count > MAX_VALUES:
            raise ConfigError(
                f"{source}: its aliases (*name) expand to more than {MAX_VALUES:,} values: a config holds a few hundred; "
                "this file is an alias bomb or not a config"
            )
        return loader.construct_document(node)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{source}: not valid YAML ({' '.join(str(exc).split())})") from None
    finally:
        loader.dispose()


def read_yaml_file(path: Path) -> Any:
    """:func:`load_yaml` of the file ``path`` (not found, not a file, not UTF-8: one line each)."""
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"{path}: config file not found")
    if not path.is_file():
        raise ConfigError(f"{path}: not a file (a config is one YAML file)")
    size = path.stat().st_size
    if size > MAX_BYTES:
        raise ConfigError(f"{path}: {size:,} bytes, more than a config's {MAX_BYTES // 2**20} MiB: not a config file")
    try:
        text = read_bytes(user_file(path), MAX_BYTES).decode("utf-8")
    except StageInputError as exc:
        raise ConfigError(str(exc)) from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.start}): a config is a YAML text file") from None
    return load_yaml(text, str(path))


def initial_environment(source: Path | None = None) -> Mapping[str, str]:
    """The environment this process was started with: on Linux ``/proc/self/environ``
    (:data:`INITIAL_ENVIRON`), which a later change of ``os.environ`` (say, by a template that
    Snakemake evaluates in this process) does not alter; ``os.environ`` where there is no such
    file (macOS, or no ``/proc``)."""
    try:
        raw = read_bytes(source or INITIAL_ENVIRON, RECORD_LIMIT)
    except (OSError, StageInputError):
        return os.environ
    pairs = (entry.partition(b"=") for entry in raw.split(b"\0") if entry)
    return {os.fsdecode(name): os.fsdecode(value) for name, sep, value in pairs if sep}


def refuse_templates(data: Any, source: str, environ: Mapping[str, str] | None = None) -> None:
    """Refuse a config that asks Snakemake to evaluate it as a YTE template (Python run while the
    file loads), unless :data:`ALLOW_YTE_ENV` is set to 1 by whoever runs the workflow: in the
    environment the process started with (``environ``, by default :func:`initial_environment`),
    not one a template may have changed since."""
    environ = initial_environment() if environ is None else environ
    if isinstance(data, dict) and YTE_KEY in data and environ.get(ALLOW_YTE_ENV) != "1":
        raise ConfigError(
            f"{source}: sets {YTE_KEY}: Snakemake evaluates such a file as a YTE template, running the Python in it "
            f"while it loads the file, before any check of this tool: read it as code; if you wrote it and mean it, "
            f"set {ALLOW_YTE_ENV}=1"
        )
