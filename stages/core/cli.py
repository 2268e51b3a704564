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
import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .. import _version
from .device import resolve_device, set_torch_threads
from .errors import stage_errors
from .threads import set_cpu_threads

log = logging.getLogger(__name__)


#: libraries whose own INFO lines (trimesh's "triangulating faces" on every quad mesh it reads, ...)
#: are kept out of the user's console unless ``-v``; their warnings still show
THIRD_PARTY_LOGGERS = ("trimesh", "PIL", "matplotlib", "fsspec", "filelock", "urllib3", "httpx", "huggingface_hub")


def setup_logging(verbose: bool = False) -> None:
    """Log to stderr (rules redirect it to their ``log:`` file): the tool's INFO lines, third-party
    libraries' warnings only (:data:`THIRD_PARTY_LOGGERS`; everything with ``verbose``)."""
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
        force=True,
    )
    for name in THIRD_PARTY_LOGGERS:
        logging.getLogger(name).setLevel(logging.DEBUG if verbose else logging.WARNING)


#: the help of options many stages share, by their ``dest`` (a stage's own ``help=`` wins)
COMMON_HELP = {
    "settings": "the stage's settings as one JSON object (the keys of its config section; "
    "python -m stages.config.reference lists them)",
    "out_dir": "the folder the stage writes (it appears whole, or not at all)",
    "transform": "the normalisation's inverse transform (transform.json, from stages.normalize)",
    "bake_dir": "the bake's folder (from stages.bake)",
    "export_dir": "the export's folder (from stages.export)",
    "field": "the trained field (field.pt, from stages.optimize)",
    "eval": "the evaluation ray cache (.npz, from stages.raycache)",
    "mesh": "the normalised mesh (.ply)",
    "name": "the asset files' base name (model.glb, model.usdz, ...)",
    "results": "the results folder of the run",
    "configfile": "one or more config files; a later file's keys override an earlier one's",
    "json": "print JSON instead of text",
    "cells": "the cells to include, each mesh/prompt/variant",
    "verbose": "log debug messages too",
}

_ROLE = re.compile(r":[a-z]+:`~?([^`<]*?)\s*(?:<[^>]*>)?`")  # :func:`x`, :mod:`~a.b`, :ref:`text <target>`


def plain_text(doc: str) -> str:
    """A docstring's first paragraph as plain text for ``--help``: whole (not cut at its first line),
    with reStructuredText's roles and literals reduced to their words (a literal's plural " s" joined)."""
    paragraph = doc.strip().split("\n\n")[0]
    text = _ROLE.sub(lambda m: m.group(1).rsplit(".", 1)[-1] if m.group(0).find("~") > 0 else m.group(1), paragraph)
    text = re.sub(r"``([^`]+)``(?: (s)\b)?", lambda m: m.group(1) + (m.group(2) or ""), text)
    text = re.sub(r"`([^`]+)`_?", r"\1", text)
    text = re.sub(r"(?<![\w*])\*{1,2}([^*\s][^*]*?)\*{1,2}(?![\w*])", r"\1", text)
    return " ".join(text.split())


def stage_parser(stage: str, doc: str) -> argparse.ArgumentParser:
    """The parser of ``python -m stages.<stage>``: the docstring's first paragraph as its description,
    and ``--version``."""
    parser = argparse.ArgumentParser(prog=f"python -m stages.{stage}", description=plain_text(doc))
    parser.add_argument("--version", action="version", version=f"tango-stylize {_version()}")
    return parser


#: the config a command reads when given no ``--configfile``
DEFAULT_CONFIG = "config/config.yaml"


def add_configfile(parser: argparse.ArgumentParser) -> None:
    """``--configfile`` as Snakemake takes it: several files after one flag, or the flag repeated
    (``--configfile a.yaml b.yaml`` or ``--configfile a.yaml --configfile b.yaml``; later files win);
    :func:`stage_main` puts :data:`DEFAULT_CONFIG` where none is given."""
    parser.add_argument(
        "--configfile",
        type=Path,
        nargs="+",
        action="extend",
        metavar="FILE",
        help=f"config file(s), as snakemake takes them; a later file's keys override an earlier one's (default {DEFAULT_CONFIG})",
    )


def _fill_help(parser: argparse.ArgumentParser) -> None:
    """Give each option without its own help the shared one (:data:`COMMON_HELP`)."""
    for action in parser._actions:
        if action.help is None and action.dest in COMMON_HELP:
            action.help = COMMON_HELP[action.dest]


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
    parser = stage_parser(stage, doc)
    arguments(parser)
    if device is not None:
        parser.add_argument("--device", default=device, help="cpu, cuda, cuda:1, ... ('auto': CUDA when available)")
    if device is not None or threads:
        parser.add_argument("--threads", type=_positive, default=None, help="CPU threads (torch and the ray tracer)")
    parser.add_argument("-v", "--verbose", action="store_true")
    _fill_help(parser)
    args = parser.parse_args(argv)
    if getattr(args, "configfile", False) is None:
        args.configfile = [Path(DEFAULT_CONFIG)]
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
