"""Grid cells as the report stages receive them (``mesh/prompt/variant`` ids)."""

from __future__ import annotations

from ..core.errors import StageInputError


def parse_cells(items: list[str]) -> list[tuple[str, str, str]]:
    cells = []
    for item in items:
        parts = item.split("/")
        if len(parts) != 3:
            raise StageInputError(None, f"cell {item!r} is not mesh/prompt/variant")
        cells.append(tuple(parts))
    return cells
