"""Errors that carry a file, a problem and a remedy, so a failed job explains itself."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from pathlib import Path


class StageInputError(Exception):
    """Bad input to a stage: names the file, what is wrong with it and what to do.

    Stage CLIs catch it, log the message as one line and exit with status 2, leaving no
    output behind (outputs are only ever renamed into place after success).
    """

    def __init__(self, path: str | Path | None, problem: str, remedy: str = "") -> None:
        self.path = str(path) if path is not None else None
        self.problem = problem
        self.remedy = remedy
        where = f"{self.path}: " if self.path else ""
        tail = f" {remedy}" if remedy else ""
        super().__init__(f"{where}{problem}.{tail}")


class ConfigError(Exception):
    """A configuration that does not follow the schema; the message names the key and where it is."""


class _Status:
    code = 0


@contextlib.contextmanager
def stage_errors(stage: str) -> Iterator[_Status]:
    """For a stage's ``main``: turn expected failures into one clear log line and exit code 2.

    ``with stage_errors("normalize") as status: ...; return status.code``. Unexpected exceptions
    propagate with their traceback (those are bugs, not bad input).
    """
    status = _Status()
    try:
        yield status
    except (StageInputError, ConfigError) as exc:
        logging.getLogger(f"stages.{stage}").error("%s failed: %s", stage, exc)
        status.code = 2
