"""Atomic file output, staged output folders, metadata JSON (settings, seed, versions, timings)
and the origin record (which guidance and weights made a result) that every output repeats."""

from __future__ import annotations

import contextlib
import hashlib
import importlib.metadata
import json
import logging
import platform
import socket
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from .errors import StageInputError
from .safefiles import DATA_LIMIT, atomic_path, check_output_path, open_read, read_json, remove_tree, replace, user_file

log = logging.getLogger(__name__)

#: distributions whose versions every metadata file records (absent ones are reported as null)
TRACKED_PACKAGES = (
    "tango-stylize",
    "numpy",
    "scipy",
    "trimesh",
    "embreex",
    "pymeshlab",
    "torch",
    "open_clip_torch",
    "xatlas",
    "usd-core",
    "snakemake",
)


def package_versions(names: tuple[str, ...] = TRACKED_PACKAGES) -> dict[str, str | None]:
    """Installed versions of ``names`` (``None`` when not installed), plus Python's."""
    out: dict[str, str | None] = {"python": platform.python_version()}
    for name in names:
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = None
    return out


def sha256_of(path: str | Path, chunk: int = 1 << 20) -> str:
    """The SHA-256 of a file: one of a results folder, or one the user named (a link of theirs
    outside any results folder followed, :func:`~stages.core.safefiles.user_file`)."""
    h = hashlib.sha256()
    with open_read(user_file(path), DATA_LIMIT) as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def write_json_atomic(path: str | Path, data: Any) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2, sort_keys=False, default=_json_default) + "\n")


def _json_default(obj: Any) -> Any:
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


class Timer:
    """Named wall-clock sections: ``with timer("load"): ...``; ``timer.seconds`` is a dict."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._start = time.perf_counter()

    @contextlib.contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t0

    def total(self) -> float:
        return time.perf_counter() - self._start


def metadata(
    *,
    stage: str,
    settings: dict[str, Any],
    inputs: dict[str, str | Path],
    outputs: dict[str, str | Path],
    timings: dict[str, float],
    seed: int | None = None,
    extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The metadata record every stage writes next to its outputs."""
    ins: dict[str, Any] = {}
    for key, value in inputs.items():
        p = Path(value)
        ins[key] = {"path": str(value), "sha256": sha256_of(p)} if p.is_file() else str(value)
    return {
        "stage": stage,
        "settings": settings,
        "seed": seed,
        "inputs": ins,
        "outputs": {k: str(v) for k, v in outputs.items()},
        "timings_s": {k: round(v, 6) for k, v in timings.items()},
        "versions": package_versions(),
        "host": {"hostname": socket.gethostname(), "platform": platform.platform()},
        "argv": sys.argv,
        "finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        **(extra or {}),
    }


#: what a record shared outside this machine leaves out: who ran it where, and how
PRIVATE_KEYS = ("host", "argv")


def shareable_meta(meta: Any) -> Any:
    """``meta`` as it may leave the machine (the asset pack): without the host name and platform
    and the command line (:data:`PRIVATE_KEYS`, at any depth), and with the paths of its
    ``inputs`` and ``outputs`` cut to file names (they name the user's folders); settings,
    versions, timings, digests and the origin stay."""
    if isinstance(meta, list):
        return [shareable_meta(v) for v in meta]
    if not isinstance(meta, dict):
        return meta
    out = {}
    for key, value in meta.items():
        if key in PRIVATE_KEYS:
            continue
        if key in ("inputs", "outputs") and isinstance(value, dict):
            value = {k: _file_name(v) for k, v in value.items()}
        out[key] = shareable_meta(value)
    return out


def _file_name(value: Any) -> Any:
    if isinstance(value, dict) and isinstance(value.get("path"), str):
        return {**value, "path": Path(value["path"]).name}
    return Path(value).name if isinstance(value, str) and value else value


# ---- origin: which guidance and weights made a result, carried by every downstream output ----
#: the key under which every stage's ``meta.json`` (and the field file) records the origin
ORIGIN_KEY = "origin"
#: the key of the origin record inside asset files (USD customLayerData, glTF asset.extras)
ORIGIN_METADATA_KEY = "tango_stylize"


def origin_record(
    *,
    guidance: str,
    weights: str,
    test_only: bool,
    image_guided: bool = False,
    label: str | None = None,
    prompt: str | None = None,
) -> dict[str, Any]:
    """What made a trained field, in the form every downstream output repeats.

    ``guidance``: the guidance mode's name; ``weights``: the id of the CLIP weights or of the
    image targets; ``test_only``: made with the tiny random test CLIP; ``image_guided`` and
    ``label``: what the mode says of a result it made (its row in
    :mod:`stages.config.guidance_modes` gives them: :meth:`GuidanceMode.origin_record`). ``label``
    is the one line a person reads (in file metadata, the asset index, the pack's README and the
    report); a test-only result's says ``TEST ONLY`` whatever the mode, and any other needs its
    mode's, which starts with an upper-case warning whenever the result is not a real stylisation.
    """
    if not isinstance(guidance, str) or not guidance:
        raise ValueError(f"guidance must be a guidance mode's name, got {guidance!r}")
    if test_only:
        label = f"TEST ONLY: made with random test weights, not a real stylisation ({weights})"
    elif not label:
        raise ValueError(f"an origin of guidance {guidance!r} needs its mode's label (GuidanceMode.origin_record)")
    return {
        "guidance": guidance,
        "weights": weights,
        "test_only": bool(test_only),
        "image_guided": bool(image_guided),
        "prompt": prompt,
        "label": label,
    }


def read_origin(meta_path: str | Path) -> dict[str, Any]:
    """The origin recorded in an upstream ``meta.json``; a clear error when it has none."""
    meta_path = Path(meta_path)
    if not meta_path.is_file():
        raise StageInputError(meta_path, "file not found", "Run the earlier stages first.")
    record = read_json(meta_path, "Run the earlier stages first.")
    return checked_origin(record.get(ORIGIN_KEY) if isinstance(record, dict) else None, meta_path, "the stage that wrote it")


def checked_origin(origin: Any, path: str | Path, writer: str) -> dict[str, Any]:
    """``origin`` when it is an origin record, else a clear error naming ``path`` and ``writer``."""
    if not isinstance(origin, dict) or "label" not in origin:
        raise StageInputError(
            path,
            "records no origin (guidance and weights), so outputs made from it could not say what made them",
            f"It was written by an older version: rerun {writer} (snakemake --forcerun <rule>).",
        )
    return origin


@contextlib.contextmanager
def staged_outputs(out_dir: str | Path, last: tuple[str, ...] = ("meta.json",)) -> Iterator[Path]:
    """A hidden staging folder inside ``out_dir`` for a job's outputs, moved into place together.

    Write every output under the yielded folder (same relative paths as in ``out_dir``). On
    success each file is renamed into ``out_dir`` (``last``, the metadata, after all others) and
    the folder is removed; on an exception the folder is removed and ``out_dir`` is untouched. A
    job killed before the commit leaves only ``out_dir/.staging-*``, which hides from Snakemake and
    from anyone looking for finished files, and which the next run of the job deletes. The commit
    itself is a handful of renames on one file system (microseconds), not a copy.
    """
    out_dir = Path(out_dir)
    check_output_path(out_dir / ".staging")
    out_dir.mkdir(parents=True, exist_ok=True)
    for stale in out_dir.glob(".staging-*"):
        log.info("removing %s left by a killed run", stale)
        remove_tree(stale)
    stage = Path(tempfile.mkdtemp(prefix=".staging-", dir=out_dir))
    try:
        yield stage
        files = sorted((p for p in stage.rglob("*") if p.is_file()), key=lambda p: (p.name in last, str(p)))
        for path in files:
            target = out_dir / path.relative_to(stage)
            target.parent.mkdir(parents=True, exist_ok=True)
            replace(path, target)
    finally:
        remove_tree(stage)
