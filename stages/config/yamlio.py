"""Reading a config file as data, bounded: PyYAML's safe loader with the checks a file from someone
else needs before anything walks its values.

* **Size** (:data:`MAX_BYTES`), **nesting depth** (:data:`MAX_DEPTH`) and **expanded size**
  (:data:`MAX_VALUES`): YAML aliases let a 521-byte file stand for 10^8 values (a "billion laughs"),
  which PyYAML builds cheaply by sharing but every later walk (the schema's validation) expands.
  The expanded count is taken on the composed node graph, each shared node counted once per use
  but visited once, before any value is constructed.
* **Duplicate keys**: YAML says a mapping's keys are unique, PyYAML keeps the last silently; a
  second ``optimize:`` block would drop the first one's settings. Refused, naming both lines.
* **Templates**: a top-level ``__use_yte__`` asks Snakemake to evaluate the file as a YTE template,
  which runs Python while Snakemake loads it. The project's loaders refuse such a file
  (:data:`ALLOW_YTE_ENV` lets a user who wrote the template opt in; a config cannot set it).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import yaml

from ..core.errors import ConfigError

#: the largest config file read (bytes); the shipped configs are under 10 kB
MAX_BYTES = 4 * 2**20
#: the deepest nesting of mappings and lists (the schema's is 5)
MAX_DEPTH = 64
#: the most values (scalars, mappings, lists) a file may expand to through its aliases
MAX_VALUES = 200_000
#: the environment variable that lets the workflow go on with a config that used a YTE template
ALLOW_YTE_ENV = "TANGO_ALLOW_YTE"
YTE_KEY = "__use_yte__"


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
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.start}): a config is a YAML text file") from None
    return load_yaml(text, str(path))


def refuse_templates(data: Any, source: str, environ=os.environ) -> None:
    """Refuse a config that asks Snakemake to evaluate it as a YTE template (Python run while the
    file loads), unless :data:`ALLOW_YTE_ENV` is set to 1 by whoever runs the workflow."""
    if isinstance(data, dict) and YTE_KEY in data and environ.get(ALLOW_YTE_ENV) != "1":
        raise ConfigError(
            f"{source}: sets {YTE_KEY}: Snakemake evaluates such a file as a YTE template, running the Python in it "
            f"while it loads the file, before any check of this tool: read it as code; if you wrote it and mean it, "
            f"set {ALLOW_YTE_ENV}=1"
        )
