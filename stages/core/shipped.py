"""Meshes that travel with the project compressed (``meshes/*.obj.xz``), unpacked where they are named.

A config names a shipped mesh by the path of its unpacked file (``meshes/lamp.obj``). Beside that
path lie the archive (``lamp.obj.xz``) and a ``SHA256SUMS`` file (``sha256sum``'s format) that lists
the unpacked file's SHA-256. The first reader that finds the file missing (:func:`ensure_unpacked`)
decompresses the archive next to it, checks the checksum, and renames the result into place: a
killed unpacking leaves only a hidden temporary file, and a damaged archive stops with one line
naming it. Only files listed in ``SHA256SUMS`` are unpacked, at most :data:`MAX_BYTES` each.
"""

from __future__ import annotations

import hashlib
import logging
import lzma
from pathlib import Path

from .errors import StageInputError
from .safefiles import atomic_stream, open_read, read_text

log = logging.getLogger(__name__)

#: the checksum list beside the archives
SUMS = "SHA256SUMS"
#: the archive's suffix after the file's own name
ARCHIVE = ".xz"
#: the largest unpacked file (a bound on what a damaged or hostile archive can write)
MAX_BYTES = 256 * 1024 * 1024
CHUNK = 1024 * 1024


def listed_sums(folder: Path) -> dict[str, str]:
    """``{file name: sha256 hex}`` of ``folder``'s SHA256SUMS (empty without one)."""
    sums = folder / SUMS
    if not sums.is_file():
        return {}
    out = {}
    for line in read_text(sums).splitlines():
        parts = line.split()
        if len(parts) == 2 and len(parts[0]) == 64:
            out[parts[1].lstrip("*")] = parts[0].lower()
    return out


def shipped_archive(path: str | Path) -> Path | None:
    """The archive ``path`` is unpacked from, when ``path`` names a shipped mesh (its archive beside
    it and its checksum listed), else None."""
    path = Path(path)
    archive = path.with_name(path.name + ARCHIVE)
    return archive if archive.is_file() and path.name in listed_sums(path.parent) else None


def ensure_unpacked(path: str | Path) -> bool:
    """Unpack ``path`` from its shipped archive when the file is missing; True when it did.

    Raises:
        StageInputError: the archive is damaged (not xz, larger than :data:`MAX_BYTES`, or its
            content does not match the listed checksum); nothing is left at ``path``.
    """
    path = Path(path)
    archive = shipped_archive(path)
    if path.exists() or archive is None:
        return False
    expected = listed_sums(path.parent)[path.name]
    remedy = f"Restore the archive (git checkout -- {archive}) and run again."
    digest, size = hashlib.sha256(), 0
    try:
        with open_read(archive, MAX_BYTES, remedy=remedy) as fh, lzma.LZMAFile(fh) as src, atomic_stream(path) as dst:
            while chunk := src.read(CHUNK):
                size += len(chunk)
                if size > MAX_BYTES:
                    raise StageInputError(archive, f"unpacks to more than {MAX_BYTES // 2**20} MiB", remedy)
                digest.update(chunk)
                dst.write(chunk)
            if digest.hexdigest() != expected:
                raise StageInputError(archive, f"unpacks to a file whose SHA-256 is not the one {SUMS} lists", remedy)
    except (lzma.LZMAError, EOFError) as exc:
        raise StageInputError(archive, f"is not a whole xz archive ({exc})", remedy) from exc
    log.info("%s: unpacked from %s (%.1f MB, SHA-256 checked)", path, archive.name, size / 1e6)
    return True
