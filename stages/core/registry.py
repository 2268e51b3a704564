"""A registry of the components of one kind (BRDF models, guidance modes, export formats, light
components): entries found by name, in the order they were registered, without torch.

A settings field whose type is ``Annotated[str, registry]`` takes the registry's names as its
choices, read when a value is checked, not when the class is defined
(:func:`stages.core.settings.kind_of`): so a component registered later (a plug-in, or a test's
toy in :meth:`Registry.temporarily`) is a valid choice at once, and the schema and the
configuration reference list the names registered when they are generated.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Generic, TypeVar

T = TypeVar("T")


class Registry(Generic[T]):
    """Entries of one kind by name. ``kind`` names the kind in errors (``"BRDF"``); ``error``
    builds the exception an unknown name raises (default: ValueError). Iterating gives the names
    (so it serves as a setting's choices); :meth:`entries` the entries."""

    def __init__(self, kind: str, error: Callable[[str], Exception] = ValueError) -> None:
        self.kind = kind
        self._error = error
        self._entries: dict[str, T] = {}

    def register(self, name: str, entry: T) -> T:
        """Add ``entry`` under ``name`` (a name already registered is a ValueError); returns it."""
        if not isinstance(name, str) or not name:
            raise ValueError(f"a {self.kind} is registered under a non-empty name, got {name!r}")
        if name in self._entries:
            raise ValueError(f"a {self.kind} named {name!r} is already registered")
        self._entries[name] = entry
        return entry

    @contextmanager
    def temporarily(self, name: str, entry: T) -> Iterator[T]:
        """``entry`` registered under ``name`` for the block, removed after it (tests, recipes)."""
        self.register(name, entry)
        try:
            yield entry
        finally:
            del self._entries[name]

    def __getitem__(self, name: str) -> T:
        """The entry named ``name``; an unknown name raises ``error`` naming the choices."""
        try:
            return self._entries[name]
        except (KeyError, TypeError):
            raise self._error(f"unknown {self.kind} {name!r}; choose one of {', '.join(self._entries)}") from None

    def get(self, name: str, default: T | None = None) -> T | None:
        return self._entries.get(name, default) if isinstance(name, str) else default

    def __contains__(self, name: object) -> bool:
        return isinstance(name, str) and name in self._entries

    def __iter__(self) -> Iterator[str]:
        return iter(tuple(self._entries))

    def __len__(self) -> int:
        return len(self._entries)

    def names(self) -> tuple[str, ...]:
        """The names, in registration order."""
        return tuple(self._entries)

    def entries(self) -> tuple[T, ...]:
        """The entries, in registration order."""
        return tuple(self._entries.values())

    def items(self) -> tuple[tuple[str, T], ...]:
        return tuple(self._entries.items())

    def values(self) -> tuple[T, ...]:
        return self.entries()

    def keys(self) -> tuple[str, ...]:
        return self.names()

    def __repr__(self) -> str:
        return f"<{self.kind} registry: {', '.join(self._entries)}>"
