"""The gate: every file the stages read, write or delete goes through this module.

A results folder can come from someone else (a shared run, a downloaded report), and a link there
can point anywhere: a report that followed it would copy ``/etc/shadow`` into its page, a stage
that wrote or cleared through it would write or delete outside ``results/``. A FIFO or a device
where a file should be would hang the reader or feed it without end, and a file of gigabytes
where a record of kilobytes belongs would fill the memory.

So a read (:func:`open_read`, :func:`read_bytes`, :func:`read_text`, :func:`read_json`,
:func:`copy_file`) opens only a regular file, reached without a symbolic link inside its results
folder, opened without following a link and checked again on the open handle (a file swapped for
a FIFO between the check and the open is refused too), no larger than the limit its caller names;
a write (:func:`atomic_path`, :func:`replace`) and a delete (:func:`remove`, :func:`remove_tree`,
:func:`clear`) happen only after the same checks on the folder they change. Each refusal is one
:class:`~stages.core.errors.StageInputError` naming the file, what it is and what to do.

The *results root* of a path is its nearest ancestor named ``results`` (the workflow's; the folder
itself may be a link, to a larger disk, say); below it every folder and the file itself must be
plain. A path with no such ancestor (a stage run by hand on files of one's own, a package's data)
is checked from its own folder only: the file itself must be a regular file, not a link.

``tests/core/test_gate.py`` walks the code of ``stages/`` and fails on any read, delete or rename
that does not come through here.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import stat
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO

from .errors import StageInputError

#: the name of the folder the workflow writes under (relative to its working directory)
RESULTS_NAME = "results"

MiB = 1 << 20
#: the largest record read: JSON, CSV, TSV and text files (a meta.json with its loss history is
#: about 0.5 MB; a summary of thousands of cells a few MB)
RECORD_LIMIT = 64 * MiB
#: the largest picture read (a 4096 x 4096 RGBA PNG is at most 64 MiB uncompressed)
IMAGE_LIMIT = 512 * MiB
#: the largest array, mesh, asset or weights file read (ray caches, targets, field.pt, model.glb)
DATA_LIMIT = 16 * 1024 * MiB
#: the size of one read of :func:`read_bytes`
CHUNK = 16 * MiB


def results_root(path: str | Path) -> Path | None:
    """The outermost ancestor of ``path`` (made absolute, links not followed) named ``results``: a
    folder of that name further down (which no id may be) is one more folder whose links count."""
    absolute = Path(os.path.abspath(path))
    return next((p for p in reversed(absolute.parents) if p.name == RESULTS_NAME), None)


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


def user_file(path: str | Path) -> Path:
    """A file the user names on purpose (a mesh, an environment map, a config): outside any
    results folder a link is the user's own and is followed (the gate then checks what it points
    to); inside one, ``path`` as it is, under the rules above."""
    return Path(path) if results_root(path) is not None else Path(os.path.realpath(path))


def inside(root: str | Path, name: str, remedy: str = "") -> Path:
    """The plain file ``root/name`` for a ``name`` read from a received file (a report's
    ``figures.json``): relative, no ``..``, reached without a link; else :class:`StageInputError`."""
    if any(ord(c) < 32 or 127 <= ord(c) < 160 for c in str(name)):
        raise StageInputError(root, f"names {str(name)!r}, which holds a control character: not a file name", remedy)
    rel = Path(str(name))
    if rel.is_absolute() or ".." in rel.parts or not rel.parts:
        raise StageInputError(Path(root) / str(name), f"names {str(name)!r}, which is not a path inside {root}", remedy)
    return require_plain_file(Path(root) / rel, root, remedy)


def _check_folder(folder: str | Path, path: str | Path, action: str) -> None:
    """Refuse to change ``folder`` (written into, cleared) when it is reached through a symbolic
    link inside its results root (``path``: what is being changed, for the message)."""
    root = results_root(path)
    if root is None:
        return
    link = link_on_the_way(folder, root)
    if link is not None:
        raise StageInputError(
            path,
            f"would be {action} through {link}, a symbolic link inside {root}: outputs go to plain folders only",
            "Remove the link (the run makes the folder itself).",
        )


def check_output_path(path: str | Path) -> None:
    """Refuse to write ``path`` through a symbolic link inside its results root (a stage folder
    that links elsewhere would land the stage's outputs outside ``results/``)."""
    _check_folder(Path(os.path.abspath(path)).parent, path, "written")


# ---------------------------------------------------------------------------------------- reads
def open_read(path: str | Path, limit: int, root: str | Path | None = None, remedy: str = "") -> BinaryIO:
    """``path`` opened for binary reading once it is a plain file (:func:`require_plain_file`) of at
    most ``limit`` bytes: opened without following a link and without waiting on a FIFO, and checked
    again on the handle. The caller closes it (``with open_read(...) as fh``)."""
    path = require_plain_file(path, root, remedy)
    flags = os.O_RDONLY | os.O_NONBLOCK | os.O_NOFOLLOW | os.O_CLOEXEC  # POSIX (Linux, macOS)
    try:
        fd = os.open(os.path.abspath(path), flags)  # the path checked (a ``..`` resolved by name, not through a link)
    except OSError as exc:
        raise StageInputError(path, f"could not be opened ({exc.strerror or exc})", remedy) from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise StageInputError(path, "changed into something other than a plain file while it was opened", remedy)
        if info.st_size > limit:
            raise StageInputError(path, f"is {info.st_size:,} bytes, more than the {limit:,} such a file may hold", remedy)
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_bytes(path: str | Path, limit: int, root: str | Path | None = None, remedy: str = "") -> bytes:
    """The bytes of the plain file ``path`` (:func:`open_read`); a file that grew past ``limit``
    while it was read is refused too."""
    chunks, size = [], 0
    with open_read(path, limit, root, remedy) as fh:  # in chunks: read(limit) would reserve the whole limit first
        while size <= limit and (chunk := fh.read(min(CHUNK, limit + 1 - size))):
            chunks.append(chunk)
            size += len(chunk)
    data = b"".join(chunks)
    if len(data) > limit:
        raise StageInputError(path, f"holds more than the {limit:,} bytes such a file may hold", remedy)
    return data


def read_text(path: str | Path, limit: int = RECORD_LIMIT, root: str | Path | None = None, remedy: str = "") -> str:
    """The UTF-8 text of the plain file ``path`` (:func:`read_bytes`); text that is not UTF-8 is
    one :class:`StageInputError`."""
    data = read_bytes(path, limit, root, remedy)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise StageInputError(path, f"is not UTF-8 text (byte {exc.start})", remedy) from None


def read_json(path: str | Path, remedy: str = "Rerun the stage that writes it.", limit: int = RECORD_LIMIT) -> Any:
    """A JSON record read as data: a plain file (:func:`read_text`) holding valid JSON, nested at
    most as deep as Python's parser goes; else one :class:`StageInputError` naming it."""
    text = read_text(path, limit, remedy=remedy)
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise StageInputError(path, f"is not valid JSON ({' '.join(str(exc).split())[:120]})", remedy) from None
    except RecursionError:
        raise StageInputError(path, "is nested too deeply to be a record", remedy) from None
    except ValueError as exc:  # a number past Python's digit limit, say
        raise StageInputError(path, f"is not a record of plain values ({' '.join(str(exc).split())[:120]})", remedy) from None


def copy_file(source: str | Path, target: str | Path, limit: int = DATA_LIMIT, remedy: str = "") -> None:
    """Copy the plain file ``source`` (:func:`open_read`) onto ``target``, atomically
    (:func:`atomic_stream`)."""
    with open_read(source, limit, remedy=remedy) as src, atomic_stream(target) as dst:
        shutil.copyfileobj(src, dst)


def place(source: str | Path, target: str | Path, limit: int = DATA_LIMIT, remedy: str = "") -> None:
    """Put the plain file ``source`` at ``target``: a hard link where the file system allows (no
    copy; the entry checked is linked, a link never followed, and a link found there is undone),
    else a copy (:func:`copy_file`)."""
    source = require_plain_file(source, remedy=remedy)
    check_output_path(target)
    try:
        os.link(source, target, follow_symlinks=False)
    except OSError:
        copy_file(source, target, limit, remedy)
        return
    if file_kind(target) != "file":  # the source was swapped for a link between the check and the link
        os.unlink(target)
        raise StageInputError(source, "changed into something other than a plain file while it was linked", remedy)


# -------------------------------------------------------------------------- writes and deletes
@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path in the target's directory; rename it onto ``path`` on success.

    The temporary name keeps the target's suffix (so writers that infer a format from it work)
    and starts with a dot, so a killed job leaves at most a hidden ``.name.tmp-*`` file and
    never a file that looks finished. On error the temporary file is removed. The folder is
    checked (:func:`check_output_path`) before anything is made in it.
    """
    path = Path(path)
    check_output_path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.tmp-", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.chmod(tmp_path, 0o666 & ~_umask())
        os.replace(tmp_path, path)
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def atomic_stream(path: str | Path, mode: str = "wb", **kwargs) -> Iterator[Any]:
    """A file opened for writing (``mode`` "wb" or "w", ``kwargs`` as ``open``'s) at a temporary
    path of :func:`atomic_path`, renamed onto ``path`` when the block ends without an error."""
    if mode not in ("wb", "w"):
        raise ValueError(f"atomic_stream writes a new file, not {mode!r}")
    with atomic_path(path) as tmp, open(tmp, mode, **kwargs) as fh:
        yield fh


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def replace(source: str | Path, target: str | Path) -> None:
    """Rename ``source`` onto ``target`` (one file system), both folders checked as outputs."""
    check_output_path(source)
    check_output_path(target)
    os.replace(source, target)


def remove(path: str | Path, missing_ok: bool = True) -> None:
    """Delete the file (or link, FIFO: the entry, never what it points to) ``path``, once its
    folder is reached without a link inside its results root; a folder is :func:`remove_tree`'s."""
    _check_folder(Path(os.path.abspath(path)).parent, path, "deleted")
    kind = file_kind(path)
    if kind == "folder":
        raise StageInputError(path, "is a folder where a file was to be deleted", "Move it away by hand.")
    if kind == "missing":
        if not missing_ok:
            raise StageInputError(path, "file not found")
        return
    os.unlink(path)


def remove_tree(path: str | Path) -> None:
    """Delete the folder ``path`` and what it holds, once it is a plain folder reached without a
    link inside its results root (a link inside it is removed, not followed); nothing when it is
    missing."""
    _check_folder(path, path, "deleted")
    kind = file_kind(path)
    if kind == "missing":
        return
    if kind != "folder":
        raise StageInputError(path, f"is a {kind} where a folder was to be deleted", "Remove it by hand.")
    shutil.rmtree(path)


def clear(folder: str | Path, pattern: str) -> list[Path]:
    """Delete the files of ``folder`` whose names match ``pattern`` (a glob, one level), once the
    folder is a plain folder reached without a link inside its results root; returns them."""
    _check_folder(folder, folder, "cleared")
    if file_kind(folder) == "missing":
        return []
    if file_kind(folder) != "folder":
        raise StageInputError(folder, f"is a {file_kind(folder)}, not a folder", "Remove it; the run makes the folder itself.")
    gone = [p for p in sorted(Path(folder).glob(pattern)) if file_kind(p) != "folder"]
    for old in gone:
        os.unlink(old)
    return gone
