"""Frozen, keyword-only settings dataclasses that reject unknown keys.

Every stage declares its settings as a subclass of :class:`Settings`. ``from_dict`` builds one
from the (already schema-validated) config section and fails on a key it does not know, naming
the key and the section, so a typo fails when the DAG is built rather than hours into a job.
"""

from __future__ import annotations

import dataclasses
import json
import types
import typing
from typing import Any, Self

from .errors import ConfigError


@dataclasses.dataclass(frozen=True, kw_only=True)
class Settings:
    """Base class; subclasses are ``@dataclass(frozen=True, kw_only=True)``."""

    #: name of the config section, used in error messages
    section: typing.ClassVar[str] = "settings"

    @classmethod
    def from_dict(cls, data: dict[str, Any] | None) -> Self:
        data = dict(data or {})
        fields = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - set(fields))
        if unknown:
            raise ConfigError(
                f"unknown key(s) {', '.join(repr(k) for k in unknown)} in '{cls.section}' "
                f"settings; allowed keys: {', '.join(sorted(fields))}"
            )
        kwargs = {}
        hints = typing.get_type_hints(cls)
        for name, value in data.items():
            hint = hints[name]
            # a tuple, or an optional one (``tuple[...] | None``) given a list
            options = typing.get_args(hint) if isinstance(hint, types.UnionType) else (hint,)
            if isinstance(value, list) and any(h is tuple or typing.get_origin(h) is tuple for h in options):
                value = tuple(value)
            kwargs[name] = value
        return cls(**kwargs)

    @classmethod
    def from_json(cls, text: str | None) -> Self:
        return cls.from_dict(json.loads(text) if text else {})

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)
