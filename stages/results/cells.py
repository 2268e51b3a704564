"""Grid cells as the report stages receive them (``mesh/prompt/variant`` ids)."""

from __future__ import annotations

from ..config.workflow import ID_RE
from ..core.errors import StageInputError


def parse_cells(items: list[str]) -> list[tuple[str, str, str]]:
    """``mesh/prompt/variant`` strings as id triples; each id as the config allows it (a folder
    name: no ``..``, no slashes, no quotes, no newline), else a :class:`StageInputError`."""
    cells = []
    for item in items:
        parts = item.split("/")
        if len(parts) != 3:
            raise StageInputError(None, f"cell {item!r} is not mesh/prompt/variant")
        bad = [p for p in parts if not ID_RE.fullmatch(p)]
        if bad:
            raise StageInputError(
                None,
                f"cell {item!r}: {bad[0]!r} is not an id (letters, digits, '_', '.' and '-', starting with a "
                "letter or digit, at most 64 characters)",
                "Pass the cells the workflow's config names.",
            )
        cells.append(tuple(parts))
    return cells
