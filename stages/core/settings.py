"""Frozen, keyword-only settings dataclasses: each setting's type, default, limits and meaning
written once, and the checks derived from them.

Every stage declares its settings as a subclass of :class:`Settings`, each field written with
:func:`setting`::

    iterations: int = setting(1500, "optimisation steps (TANGO: 1500)", ge=1, le=1_000_000)
    background: Literal["black", "white", "noise"] = setting("black", "background of the training images")

The annotation gives the type (``int``, ``float``, ``bool``, ``str``, a ``Literal`` of choices or
``Annotated[str, registry]`` for the names of a :class:`~stages.core.registry.Registry`,
``tuple[X, ...]`` or ``tuple[X, X]`` for a list, ``X | None`` for a value that may be null); the
field's :class:`Spec` the description and the limits. From these alone :meth:`Settings.problems`
checks an instance (one line per problem, naming ``section.key``, the limit and the value), the
config layer generates the JSON schema a workflow config is validated against and the
configuration reference (:mod:`stages.config.schema`, :mod:`stages.config.reference`). A class
adds what one field's limits cannot say (a relation between fields) in :meth:`Settings.relations`.

``from_dict`` builds one from a config section and fails on a key it does not know, naming the key
and the section, so a typo fails when the DAG is built rather than hours into a job.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import types
import typing
from functools import cache
from typing import Any, Literal, Self

from .errors import ConfigError
from .registry import Registry


@dataclasses.dataclass(frozen=True)
class Spec:
    """What a setting means and which values it takes, beyond its type.

    ``doc``: one line for users (the schema's and the reference's description). ``ge``/``gt``/``le``/
    ``lt``: bounds of a number (of each item of a list); ``multiple_of``: an integer's step;
    ``min_items``/``max_items``: a list's length; ``min_length``/``max_length``/``pattern``: a text's
    (of each text of a list; ``pattern`` is a regular expression the whole text must match).
    ``keyed``: whether the setting is part of its stage's work key (False: it only accepts or refuses
    input, and changing it recomputes nothing). ``marks``: names by which a layer above finds the
    settings that matter to it (:meth:`Settings.marked`), each declared where the setting is."""

    doc: str
    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    multiple_of: int | None = None
    min_items: int | None = None
    max_items: int | None = None
    min_length: int | None = None
    max_length: int | None = None
    pattern: str | None = None
    keyed: bool = True
    marks: tuple[str, ...] = ()


def setting(default: Any, doc: str, **limits: Any) -> Any:
    """A settings field: its default and its :class:`Spec` (``doc`` and the limits)."""
    return dataclasses.field(default=default, metadata={"spec": Spec(doc, **limits)})


def spec_of(field: dataclasses.Field) -> Spec:
    """The :class:`Spec` of a settings field (a field written without :func:`setting` has none)."""
    spec = field.metadata.get("spec")
    if spec is None:
        raise TypeError(f"settings field {field.name!r} is not declared with setting(default, doc, ...)")
    return spec


@dataclasses.dataclass(frozen=True)
class Kind:
    """A settings field's type as a config writes it: ``base`` (int, float, bool or str) or
    ``choices`` (a Literal's values), ``nullable``, and for a list its ``item`` kind and, when the
    list has a fixed length, ``length``."""

    base: type | None = None
    choices: tuple | None = None
    nullable: bool = False
    item: Kind | None = None
    length: int | None = None
    #: words a number setting also takes (``int | Literal["auto"]``: a count, or auto)
    words: tuple[str, ...] = ()

    @property
    def switch(self) -> bool:
        """Choices with "on" and "off", where YAML 1.1's bare on/off (booleans) mean the same."""
        return bool(self.choices) and {"on", "off"} <= set(self.choices)


@cache
def kind_of(hint: Any) -> Kind:
    """The :class:`Kind` of a type annotation (a plain type, ``Literal``, ``tuple``, ``X | None``)."""
    if isinstance(hint, types.UnionType) or typing.get_origin(hint) is typing.Union:
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        nullable = len(args) < len(typing.get_args(hint))
        words = [a for a in args if typing.get_origin(a) is Literal]
        numbers = [a for a in args if a in (int, float)]
        if len(args) == 2 and len(words) == 1 and len(numbers) == 1:  # a number or a word: int | Literal["auto"]
            return Kind(base=numbers[0], words=typing.get_args(words[0]), nullable=nullable)
        if len(args) != 1:
            raise TypeError(f"a setting is one type or None (or a number or words), got {hint}")
        return dataclasses.replace(kind_of(args[0]), nullable=True)
    if typing.get_origin(hint) is Literal:
        return Kind(choices=typing.get_args(hint))
    if typing.get_origin(hint) is typing.Annotated and isinstance(hint.__metadata__[0], Registry):
        return Kind(choices=hint.__metadata__[0])  # the registry's names when a value is checked
    if typing.get_origin(hint) is tuple:
        args = typing.get_args(hint)
        if len(args) == 2 and args[1] is Ellipsis:
            return Kind(base=tuple, item=kind_of(args[0]))
        if args and all(a == args[0] for a in args):
            return Kind(base=tuple, item=kind_of(args[0]), length=len(args))
        raise TypeError(f"a list setting holds one type, got {hint}")
    if hint in (int, float, bool, str):
        return Kind(base=hint)
    raise TypeError(f"unsupported settings type {hint}")


def kind_words(kind: Kind) -> str:
    """A kind in the words of a YAML config: ``integer``, ``list of 2 numbers``, ``... or null``."""
    names = {int: "integer", float: "number", bool: "boolean", str: "string"}
    if kind.choices is not None:
        text = "string"
    elif kind.item is not None:
        inner = kind_words(dataclasses.replace(kind.item, nullable=False))
        text = f"list of {kind.length} {inner}s" if kind.length else f"list of {inner}s"
    else:
        text = names[kind.base] + "".join(f" or {w}" for w in kind.words)
    return text + (" or null" if kind.nullable else "")


def _number(x: float) -> str:
    return repr(int(x)) if float(x).is_integer() and abs(x) < 1e15 else repr(x)


def range_words(spec: Spec) -> str:
    """A spec's numeric limits as an interval: ``[1, 1000000]``, ``(0, 1]``, ``>= 0``."""
    low, low_open = (spec.gt, True) if spec.gt is not None else (spec.ge, False)
    high, high_open = (spec.lt, True) if spec.lt is not None else (spec.le, False)
    if low is not None and high is not None:
        return f"{'(' if low_open else '['}{_number(low)}, {_number(high)}{')' if high_open else ']'}"
    if low is not None:
        return f"{'>' if low_open else '>='} {_number(low)}"
    if high is not None:
        return f"{'<' if high_open else '<='} {_number(high)}"
    return ""


def _scalar_problem(kind: Kind, spec: Spec, value: Any) -> str | None:
    """What is wrong with one value (a field's, or one item of a list) under its kind and spec."""
    if value is None:
        return None if kind.nullable else "must be given (not null)"
    if kind.choices is not None:
        return None if value in kind.choices and isinstance(value, str) else f"must be one of {', '.join(map(str, kind.choices))}"
    if kind.words and isinstance(value, str):
        number = "an integer" if kind.base is int else "a number"
        return None if value in kind.words else f"must be {' or '.join(kind.words)} or {number}"
    if kind.base is bool:
        return None if isinstance(value, bool) else "must be true or false"
    if kind.base is str:
        if not isinstance(value, str):
            return "must be a text"
        if spec.min_length is not None and len(value) < spec.min_length:
            return "must not be empty" if spec.min_length == 1 else f"must hold at least {spec.min_length} characters"
        if spec.max_length is not None and len(value) > spec.max_length:
            return f"must hold at most {spec.max_length} characters"
        if spec.pattern is not None and not re.fullmatch(spec.pattern, value):
            return f"must match {spec.pattern}"
        return None
    if isinstance(value, bool) or not isinstance(value, int if kind.base is int else (int, float)):
        number = "an integer" if kind.base is int else "a number"
        return f"must be {' or '.join(kind.words)} or {number}" if kind.words else f"must be {number}"
    if not math.isfinite(value):
        return "must be a finite number"
    outside = (
        (spec.ge is not None and value < spec.ge)
        or (spec.gt is not None and value <= spec.gt)
        or (spec.le is not None and value > spec.le)
        or (spec.lt is not None and value >= spec.lt)
    )
    if outside:
        return f"must be in {range_words(spec)}" if spec.lt is not None or spec.le is not None else f"must be {range_words(spec)}"
    if spec.multiple_of is not None and value % spec.multiple_of:
        return "must be an even number" if spec.multiple_of == 2 else f"must be a multiple of {spec.multiple_of}"
    return None


def value_problem(kind: Kind, spec: Spec, value: Any) -> str | None:
    """What is wrong with a field's value under its kind and spec (None: nothing)."""
    if kind.item is None or value is None:
        return _scalar_problem(kind, spec, value)
    if not isinstance(value, (list, tuple)):
        return f"must be a {kind_words(kind)}"
    n = len(value)
    if kind.length is not None and n != kind.length:
        return f"must hold {kind.length} items"
    if spec.min_items is not None and n < spec.min_items:
        return f"must hold at least {spec.min_items} item{'s' if spec.min_items != 1 else ''}"
    if spec.max_items is not None and n > spec.max_items:
        return f"must hold at most {spec.max_items} items"
    for item in value:
        problem = _scalar_problem(kind.item, spec, item)
        if problem:
            return f"items: each {problem}"
    return None


def _shown(value: Any) -> str:
    """A value as a message quotes it: a text as Python writes it, anything else as YAML reads it."""
    text = repr(value) if isinstance(value, str) else json.dumps(list(value) if isinstance(value, tuple) else value, default=repr)
    return text if len(text) <= 80 else text[:77] + "..."


@dataclasses.dataclass(frozen=True, kw_only=True)
class Settings:
    """Base class; subclasses are ``@dataclass(frozen=True, kw_only=True)`` with every field
    declared by :func:`setting`."""

    #: name of the config section, used in error messages
    section: typing.ClassVar[str] = "settings"

    @classmethod
    @cache
    def kinds(cls) -> dict[str, Kind]:
        """Each field's :class:`Kind`, from its annotation."""
        hints = typing.get_type_hints(cls, include_extras=True)
        return {f.name: kind_of(hints[f.name]) for f in dataclasses.fields(cls)}

    @classmethod
    def specs(cls) -> dict[str, Spec]:
        """Each field's :class:`Spec`, in declaration order."""
        return {f.name: spec_of(f) for f in dataclasses.fields(cls)}

    @classmethod
    def marked(cls, mark: str) -> tuple[str, ...]:
        """The names of the fields whose :class:`Spec` carries ``mark``, in declaration order."""
        return tuple(name for name, spec in cls.specs().items() if mark in spec.marks)

    def __post_init__(self) -> None:
        kinds = self.kinds()
        for name, kind in kinds.items():  # the forms a config may write: a list, a bare on/off
            value = getattr(self, name)
            if kind.item is not None and isinstance(value, list):
                object.__setattr__(self, name, tuple(value))
            elif kind.switch and isinstance(value, bool):
                object.__setattr__(self, name, "on" if value else "off")
        problems = self.problems()
        if problems:
            raise ConfigError(f"{self.section} settings: " + "; ".join(problems))

    def problems(self) -> list[str]:
        """Every problem of this instance: each field against its type and limits, then (when
        those hold) the relations between fields."""
        kinds, lines = self.kinds(), []
        for name, spec in self.specs().items():
            value = getattr(self, name)
            problem = value_problem(kinds[name], spec, value)
            if problem:
                lines.append(f"{self.section}.{name} {problem}, got {_shown(value)}")
        return lines or self.relations()

    def relations(self) -> list[str]:
        """Problems no single field's limits can state (a relation between fields); one line each."""
        return []

    @classmethod
    def from_dict(cls, data: dict[str, Any] | None) -> Self:
        data = dict(data or {})
        names = [f.name for f in dataclasses.fields(cls)]
        unknown = sorted(set(data) - set(names))
        if unknown:
            raise ConfigError(
                f"unknown key(s) {', '.join(repr(k) for k in unknown)} in '{cls.section}' "
                f"settings; allowed keys: {', '.join(sorted(names))}"
            )
        return cls(**data)

    @classmethod
    def from_json(cls, text: str | None) -> Self:
        """The settings from ``--settings``' JSON object; malformed JSON is a one-line :class:`ConfigError`."""
        try:
            data = json.loads(text) if text else {}
        except json.JSONDecodeError as exc:
            raise ConfigError(
                f"--settings for '{cls.section}' is not valid JSON ({exc.msg} at column {exc.colno}); "
                f"give one JSON object of '{cls.section}' keys with double-quoted names"
            ) from None
        if not isinstance(data, dict):
            raise ConfigError(f"--settings for '{cls.section}' must be a JSON object of keys, got {type(data).__name__}")
        return cls.from_dict(data)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def keyed(self) -> dict[str, Any]:
        """The settings that shape the stage's work (those whose :class:`Spec` is ``keyed``)."""
        specs = self.specs()
        return {k: v for k, v in self.to_dict().items() if specs[k].keyed}
