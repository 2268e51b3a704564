"""The C allocator's handling of freed memory while training (``optimize.keep_freed_memory``).

A training step allocates and frees the same few hundred megabytes every step: the networks'
activations (25 MB each at a paper step's 24,500 points and width 256), the renderer's and CLIP's
intermediates. glibc's malloc gives a freed block back to the kernel once the free memory at the
top of its heap passes the trim threshold (by default twice the largest block freed so far), so
the next step takes the same memory again page by page: 20,000-170,000 page faults per paper step
on a 2-core CPU, each a trip through the kernel (and, in a virtual machine, the hypervisor) that
zeroes a page. Raising the trim threshold keeps the memory with the process for the next step;
the mmap threshold at its largest (32 MiB on 64-bit) makes every block under it come from the
heap, where the kept memory is. The process's resident memory stays at its step's peak, which it
reached every step anyway. Other allocators (musl, macOS, Windows) are left as they are.
"""

from __future__ import annotations

import ctypes
import logging
import platform
from typing import Any

from .device import lever_choice

log = logging.getLogger(__name__)

#: ``mallopt``'s parameters, from glibc's ``malloc.h``
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
#: blocks of at least this many bytes are still mapped on their own and unmapped when freed:
#: glibc's largest mmap threshold on 64-bit (``HEAP_MAX_SIZE / 2``; ``mallopt`` refuses more)
MMAP_THRESHOLD = 32 * 2**20
#: free memory at the top of the heap kept for reuse before malloc trims it: the largest value
#: ``mallopt`` takes (an ``int``), so in effect never
TRIM_THRESHOLD = 2**31 - 1


def glibc() -> Any | None:
    """The process's C library when it is glibc (whose ``mallopt`` parameters these are), else None."""
    if platform.system() != "Linux":
        return None
    try:
        libc = ctypes.CDLL(None)
    except OSError:
        return None
    return libc if hasattr(libc, "gnu_get_libc_version") and hasattr(libc, "mallopt") else None


def glibc_version(libc: Any) -> str:
    """glibc's version, e.g. ``"2.36"``."""
    libc.gnu_get_libc_version.restype = ctypes.c_char_p
    return libc.gnu_get_libc_version().decode()


def allocator_plan(settings: list[str | bool]) -> str:
    """What training's :func:`keep_freed_memory` would do under each of ``settings`` on this
    machine, without doing it (the doctor's line): e.g. ``"keeps freed memory while training (glibc
    2.36; keep_freed_memory: auto)"``, ``"as it is (keep_freed_memory: off)"``."""
    libc = glibc()
    parts = []
    for choice in dict.fromkeys(lever_choice(s, "keep_freed_memory") for s in settings):
        why = _left_as_is(choice, libc)
        if why is None:
            parts.append(f"keeps freed memory while training (glibc {glibc_version(libc)}; keep_freed_memory: {choice})")
        else:
            parts.append(f"as it is ({why})")
    return "; ".join(parts)


def _left_as_is(choice: str, libc: Any | None) -> str | None:
    """Why the allocator is left as it is under ``choice`` (one of auto, on, off) with ``libc``
    (:func:`glibc`), before asking glibc anything; None where glibc is to be asked."""
    if choice == "off":
        return "keep_freed_memory: off"
    return "the C library is not glibc" if libc is None else None


def keep_freed_memory(setting: str | bool) -> tuple[bool, str]:
    """Ask the C allocator to keep freed memory for the next step (``setting``: ``auto``, ``on``,
    ``off``; booleans mean on and off), for the whole process from now on. Returns whether it
    does, and what runs, for the metadata: ``"glibc 2.36 malloc keeps freed memory (...)"`` or
    ``"the C allocator as it is (<why>)"``. ``auto`` and ``on`` do it where the C library is
    glibc; ``on`` elsewhere, or where glibc refuses the values, warns."""
    choice = lever_choice(setting, "keep_freed_memory")
    libc = glibc() if choice != "off" else None
    why = _left_as_is(choice, libc)
    if why is None:
        version = glibc_version(libc)
        # both are asked for, in this order, whatever the first answers
        refused = [
            name
            for name, param, value in (("mmap", M_MMAP_THRESHOLD, MMAP_THRESHOLD), ("trim", M_TRIM_THRESHOLD, TRIM_THRESHOLD))
            if libc.mallopt(param, value) != 1
        ]
        if not refused:
            return True, (
                f"glibc {version} malloc keeps freed memory (mmap threshold {MMAP_THRESHOLD // 2**20} MiB, "
                f"trim threshold {TRIM_THRESHOLD / 2**30:.0f} GiB)"
            )
        why = f"glibc {version} refused the {' and '.join(refused)} threshold"
    if choice == "on":
        log.warning("keep_freed_memory asked for, but %s: the C allocator runs as it is", why)
    return False, f"the C allocator as it is ({why})"
