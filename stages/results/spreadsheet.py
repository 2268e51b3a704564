"""CSV cells a spreadsheet program shows as text, never evaluates.

A cell that starts with ``=``, ``+``, ``-``, ``@``, a tab or a carriage return is a formula to
Excel, LibreOffice and Google Sheets when the CSV is opened (``=HYPERLINK("http://...")`` becomes a
live link; DDE payloads run programs). The OWASP "CSV injection" remedy: such a text cell gets a
leading apostrophe, which these programs read as "text follows". A text that already starts with
an apostrophe gets one more, so :func:`from_spreadsheet` restores every text exactly. Numbers are
left alone (``-0.5`` stays a number); ``summary.json`` holds every value unchanged.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import pandas as pd

from ..core.errors import StageInputError
from ..core.safefiles import RECORD_LIMIT, read_text

#: what makes a spreadsheet cell a formula (and the apostrophe, escaped so the mapping reverses)
FORMULA_START = ("=", "+", "-", "@", "\t", "\r", "'")
#: the full-width forms some spreadsheets (East Asian locales) also read as a formula's start
FULL_WIDTH_START = ("\uff1d", "\uff0b", "\uff0d", "\uff20")


def to_spreadsheet(value: Any) -> Any:
    """``value`` as a CSV cell: a text a spreadsheet would evaluate gets a leading apostrophe, also
    where spaces (any Unicode space) come before the formula's sign or the sign is full-width."""
    if isinstance(value, str) and (
        value.startswith(FORMULA_START) or value.lstrip().startswith(FORMULA_START + FULL_WIDTH_START)
    ):
        return "'" + value
    return value


def from_spreadsheet(value: Any) -> Any:
    """The text :func:`to_spreadsheet` was given (its leading apostrophe removed)."""
    if isinstance(value, str) and value.startswith("'"):
        return value[1:]
    return value


def spreadsheet_rows(rows: list[dict]) -> list[dict]:
    """Every text value of ``rows`` through :func:`to_spreadsheet` (numbers unchanged)."""
    return [{k: to_spreadsheet(v) for k, v in row.items()} for row in rows]


def read_csv(path: Path, remedy: str = "Rerun the stage that writes it.", **kwargs) -> pd.DataFrame:
    """A CSV (or, with ``sep="\t"``, TSV) record read through the gate (a plain file inside its
    results folder, at most :data:`~stages.core.safefiles.RECORD_LIMIT`), ``kwargs`` to pandas; a
    file pandas cannot parse, or without the columns asked for, is one :class:`StageInputError`."""
    text = read_text(path, RECORD_LIMIT, remedy=remedy)
    try:
        return pd.read_csv(io.StringIO(text), **kwargs)
    except pd.errors.EmptyDataError:
        return pd.DataFrame()
    except (pd.errors.ParserError, ValueError) as exc:
        raise StageInputError(
            path, f"is not a table of the columns expected ({' '.join(str(exc).split())[:120]})", remedy
        ) from None


def read_spreadsheet_csv(path: Path, **kwargs) -> pd.DataFrame:
    """A CSV written through :func:`spreadsheet_rows`, its texts restored (``kwargs`` to pandas)."""
    frame = read_csv(path, **kwargs)
    for column in frame.columns:
        if not pd.api.types.is_numeric_dtype(frame[column]) and not pd.api.types.is_bool_dtype(frame[column]):
            frame[column] = frame[column].map(from_spreadsheet)
    return frame
