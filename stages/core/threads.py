"""How many CPU threads this process's own parallel work may use (the ray tracer's batches: torch
has its own setting). The stages set it from their ``--threads`` (:func:`~stages.core.cli.stage_main`),
which Snakemake fills from each rule's ``threads:``; unset, every CPU this process may run on, or
``OMP_NUM_THREADS`` where that is set and lower (the usual way to share a machine's cores)."""

from __future__ import annotations

import contextlib
import os

_count: int | None = None


def set_cpu_threads(count: int | None) -> None:
    """Use ``count`` threads from now on (None: :func:`cpu_threads`' default)."""
    if count is not None and count < 1:
        raise ValueError(f"the thread count must be at least 1, got {count}")
    global _count
    _count = count


def cpu_threads() -> int:
    """:func:`set_cpu_threads`' count, else the number of CPUs this process may run on (at most
    ``OMP_NUM_THREADS`` when it is a positive integer)."""
    if _count:
        return _count
    cpus = len(os.sched_getaffinity(0))
    omp = os.environ.get("OMP_NUM_THREADS", "")
    return min(cpus, int(omp)) if omp.isdigit() and int(omp) > 0 else cpus


@contextlib.contextmanager
def threads_for(count: int):
    """:func:`set_cpu_threads` to ``count`` inside the block, then back to what it was."""
    global _count
    before = _count
    set_cpu_threads(count)
    try:
        yield
    finally:
        _count = before
