"""The one command-line wrapper every stage's ``main`` uses, and logging set-up (the device and
precision policy is :mod:`stages.core.device`).

A stage's ``main`` names its arguments and what to do with them; :func:`stage_main` adds the
shared options (``-v``; for torch stages ``--device`` and ``--threads``), sets up logging to stderr
(rules redirect it to their ``log:`` file), and turns expected failures (bad input, bad settings,
missing CLIP weights) into one clear log line and exit status 2.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable
from typing import Any

from .device import resolve_device, set_torch_threads
from .errors import stage_errors
from .threads import set_cpu_threads

log = logging.getLogger(__name__)


def setup_logging(verbose: bool = False) -> None:
    """Log to stderr (rules redirect it to their ``log:`` file)."""
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
        force=True,
    )


def _positive(text: str) -> int:
    """``--threads``' value: a whole number of at least 1 (argparse reports anything else)."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a whole number of at least 1, got {text!r}")
    return value


def stage_main(
    stage: str,
    doc: str,
    arguments: Callable[[argparse.ArgumentParser], None],
    body: Callable[[argparse.Namespace], Any],
    argv: list[str] | None = None,
    *,
    device: str | None = None,
    threads: bool = False,
) -> int:
    """Parse ``argv`` for ``python -m stages.<stage>`` and run ``body(args)``; return the exit status.

    ``arguments(parser)`` adds the stage's own options. ``device`` (the default device) marks a
    torch stage: it gets ``--device`` (resolved by :func:`resolve_device` into ``args.device``) and
    ``--threads`` (torch's and the ray tracer's threads); ``threads`` gives a stage without torch
    ``--threads`` for the ray tracer alone. Bad input and bad settings exit with status 2 after one log line; anything else
    propagates with its traceback (a bug, not bad input).
    """
    parser = argparse.ArgumentParser(prog=f"python -m stages.{stage}", description=doc.strip().split("\n")[0])
    arguments(parser)
    if device is not None:
        parser.add_argument("--device", default=device, help="cpu, cuda, cuda:1, ... ('auto': CUDA when available)")
    if device is not None or threads:
        parser.add_argument("--threads", type=_positive, default=None, help="CPU threads (torch and the ray tracer)")
    parser.add_argument("-v", "--verbose", action="store_true")
    args = parser.parse_args(argv)
    setup_logging(args.verbose)
    with stage_errors(stage) as status:
        if getattr(args, "threads", None):
            set_cpu_threads(args.threads)
        if device is not None:
            if args.threads:
                set_torch_threads(args.threads)
            args.device = resolve_device(args.device)
        body(args)
    return status.code
