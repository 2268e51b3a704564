"""What a results folder may hold for the stages to read or write: plain files and folders, reached
without a symbolic link inside it. A results folder can come from someone else (a shared run, a
downloaded report), and a link there can point anywhere: a report that followed it would copy
``/etc/shadow`` into its page, a stage that wrote through it would write outside ``results/``. A
FIFO or a device where a file should be would hang the reader or feed it without end.

The *results root* of a path is its nearest ancestor named ``results`` (the workflow's; the folder
itself may be a link, to a larger disk, say); below it every folder and the file itself must be
plain. A path with no such ancestor (a stage run by hand on files of one's own) is checked from
its own folder only.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from .errors import StageInputError

#: the name of the folder the workflow writes under (relative to its working directory)
RESULTS_NAME = "results"


def results_root(path: str | Path) -> Path | None:
    """The nearest ancestor of ``path`` (made absolute, links not followed) named ``results``."""
    absolute = Path(os.path.abspath(path))
    return next((p for p in absolute.parents if p.name == RESULTS_NAME), None)


def link_on_the_way(path: str | Path, root: str | Path) -> Path | None:
    """The first symbolic link among the existing components of ``path`` below ``root`` (``path``
    itself included), or None; ``path`` outside ``root`` counts as its own link."""
    path, root = Path(os.path.abspath(path)), Path(os.path.abspath(root))
    try:
        rel = path.relative_to(root)
    except ValueError:
        return path
    here = root
    for part in rel.parts:
        here = here / part
        try:
            if stat.S_ISLNK(os.lstat(here).st_mode):
                return here
        except FileNotFoundError:
            return None
    return None


def reached_without_link(path: str | Path, root: str | Path) -> bool:
    """``path`` lies under ``root`` with no symbolic link on the way (itself, a folder between)."""
    return link_on_the_way(path, root) is None and Path(os.path.abspath(path)).is_relative_to(os.path.abspath(root))


def file_kind(path: str | Path) -> str:
    """What ``path`` is, links not followed: ``file``, ``folder``, ``link``, ``FIFO``, ``device``,
    ``socket`` or ``missing``."""
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return "missing"
    for test, name in ((stat.S_ISREG, "file"), (stat.S_ISDIR, "folder"), (stat.S_ISLNK, "link"), (stat.S_ISFIFO, "FIFO")):
        if test(mode):
            return name
    return "socket" if stat.S_ISSOCK(mode) else "device"


def _default_root(path: str | Path, root: str | Path | None) -> Path:
    """``root`` when given, else ``path``'s results root, else its own folder."""
    return Path(root) if root is not None else results_root(path) or Path(os.path.abspath(path)).parent


def plain_file(path: str | Path, root: str | Path | None = None) -> bool:
    """``path`` is a regular file (not a link, FIFO or device) reached from ``root`` (default: its
    results root, else its own folder) without a symbolic link on the way."""
    root = _default_root(path, root)
    return file_kind(path) == "file" and reached_without_link(path, root)


def require_plain_file(path: str | Path, root: str | Path | None = None, remedy: str = "") -> Path:
    """``path`` if :func:`plain_file`, else one :class:`StageInputError` saying what it is."""
    root = _default_root(path, root)
    kind = file_kind(path)
    link = link_on_the_way(path, root)
    if link is not None and kind != "missing":
        where = "it is" if Path(link) == Path(os.path.abspath(path)) else f"it is reached through {link}, which is"
        raise StageInputError(path, f"{where} a symbolic link inside {root}: refused (it could point anywhere)", remedy)
    if kind != "file":
        raise StageInputError(path, f"is {'missing' if kind == 'missing' else f'a {kind}'}, not a plain file", remedy)
    return Path(path)


def inside(root: str | Path, name: str, remedy: str = "") -> Path:
    """The plain file ``root/name`` for a ``name`` read from a received file (a report's
    ``figures.json``): relative, no ``..``, reached without a link; else :class:`StageInputError`."""
    rel = Path(str(name))
    if rel.is_absolute() or ".." in rel.parts or not rel.parts:
        raise StageInputError(Path(root) / str(name), f"names {str(name)!r}, which is not a path inside {root}", remedy)
    return require_plain_file(Path(root) / rel, root, remedy)


def check_output_path(path: str | Path) -> None:
    """Refuse to write ``path`` through a symbolic link inside its results root (a stage folder
    that links elsewhere would land the stage's outputs outside ``results/``)."""
    root = results_root(path)
    if root is None:
        return
    link = link_on_the_way(Path(os.path.abspath(path)).parent, root)
    if link is not None:
        raise StageInputError(
            path,
            f"would be written through {link}, a symbolic link inside {root}: outputs go to plain folders only",
            "Remove the link (the run makes the folder itself).",
        )


def read_json_record(path: str | Path, remedy: str = "Rerun the stage that writes it."):
    """A stage's JSON record read as data: a plain file (:func:`require_plain_file`) holding valid
    JSON, else one :class:`StageInputError` naming it."""
    import json

    path = require_plain_file(path, remedy=remedy)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise StageInputError(path, f"is not valid JSON ({' '.join(str(exc).split())[:120]})", remedy) from None
