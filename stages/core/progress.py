"""Progress of a long job that a person can follow: at a steady interval, a log line (the job's
log, through :mod:`logging`) with the count done, the rate and an estimated time left, and a
short line on standard output, which the workflow leaves to the terminal of ``snakemake``
(locally) or to the job's Slurm log, so a terminal running a grid shows where each running job is.

``TANGO_PROGRESS_S`` sets the log interval in seconds (default 10); the terminal line comes at
three times that interval. Nothing here changes what a job computes.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TextIO

log = logging.getLogger(__name__)


def interval_s() -> float:
    """The log interval: ``TANGO_PROGRESS_S`` seconds (default 10)."""
    raw = os.environ.get("TANGO_PROGRESS_S", "10")
    try:
        value = float(raw)
    except ValueError:
        raise ValueError(f"TANGO_PROGRESS_S={raw!r} is not a number of seconds") from None
    if not value > 0:
        raise ValueError(f"TANGO_PROGRESS_S={raw!r} must be > 0")
    return value


def duration(seconds: float) -> str:
    """``3725.2`` -> ``"1h02m05s"``, ``65`` -> ``"1m05s"``, ``4.2`` -> ``"4s"``."""
    s = round(max(seconds, 0.0))
    h, rest = divmod(s, 3600)
    m, s = divmod(rest, 60)
    if h:
        return f"{h}h{m:02d}m{s:02d}s"
    return f"{m}m{s:02d}s" if m else f"{s}s"


def say(out: TextIO, text: str) -> None:
    """One line for the terminal; a closed or broken stream (a terminal gone, a pipe closed)
    never stops the job."""
    try:
        out.write(text + "\n")
        out.flush()
    except (OSError, ValueError):
        pass


def job_label(stage: str, out_dir) -> str:
    """``"optimize vase/wood/full"`` for a cell stage writing ``.../<mesh>/<prompt>/<variant>/<stage>``."""
    from pathlib import Path

    parts = Path(out_dir).parts
    return f"{stage} {'/'.join(parts[-4:-1])}" if len(parts) >= 4 else stage


class Progress:
    """A counted loop of ``total`` steps of which ``initial`` were done before this process (a
    resumed run): :meth:`update` after each step; a line at most every ``every`` seconds and one
    from :meth:`close`. The rate counts only this process's steps and time, so a resumed run's
    ETA is not flattered by the steps it inherited."""

    def __init__(
        self,
        job: str,
        total: int,
        unit: str = "it",
        initial: int = 0,
        every: float | None = None,
        terminal_every: float | None = None,
        clock: Callable[[], float] = time.monotonic,
        terminal: TextIO | None = None,
    ) -> None:
        self.job, self.total, self.unit = job, int(total), unit
        self.initial = self.done = int(initial)
        self.every = interval_s() if every is None else every
        self.terminal_every = 3 * self.every if terminal_every is None else terminal_every
        self.clock = clock
        self.terminal = terminal
        self.t0 = self.last_log = self.last_terminal = clock()
        self.info: dict[str, str] = {}
        self.lines = 0

    def rate(self) -> float | None:
        """Steps per second in this process (None before the first step)."""
        elapsed = self.clock() - self.t0
        steps = self.done - self.initial
        return steps / elapsed if steps > 0 and elapsed > 0 else None

    def eta_s(self) -> float | None:
        rate = self.rate()
        return (self.total - self.done) / rate if rate else None

    def line(self, short: bool = False) -> str:
        rate, eta = self.rate(), self.eta_s()
        pct = 100.0 * self.done / self.total if self.total else 100.0
        parts = [f"{self.done}/{self.total} {self.unit}" + ("" if short else f" ({pct:.0f}%)")]
        parts.append(f"{rate:.2f} {self.unit}/s" if rate else f"- {self.unit}/s")
        parts.append(f"ETA {duration(eta)}" if eta is not None else "ETA -")
        if not short:
            parts.append(f"elapsed {duration(self.clock() - self.t0)}")
            parts += [f"{k} {v}" for k, v in self.info.items()]
        return f"[{self.job}] " + ", ".join(parts) if short else f"{self.job}: " + ", ".join(parts)

    def update(self, n: int = 1, **info) -> None:
        """``n`` more steps done; ``info`` (e.g. ``loss="0.812"``) is shown in the log line."""
        self.done += n
        self.info.update({k: str(v) for k, v in info.items()})
        now = self.clock()
        if now - self.last_log >= self.every:
            self.emit(now)

    def emit(self, now: float | None = None, terminal: bool | None = None) -> None:
        now = self.clock() if now is None else now
        log.info("%s", self.line())
        self.lines += 1
        self.last_log = now
        if terminal or (terminal is None and now - self.last_terminal >= self.terminal_every):
            say(self.terminal or sys.stdout, self.line(short=True))
            self.last_terminal = now

    def close(self) -> None:
        """The final line (log and terminal)."""
        self.emit(terminal=True)


@contextmanager
def heartbeat(job: str, what: str, every: float | None = None, terminal: TextIO | None = None) -> Iterator[None]:
    """For one long call that reports nothing itself (an unwrap, a solver): a line when it starts,
    ``"<what>: still running, <elapsed>"`` at a steady interval from a helper thread, and its
    duration when it ends."""
    every = interval_s() if every is None else every
    t0 = time.monotonic()
    stop = threading.Event()
    out = terminal or sys.stdout
    log.info("%s: %s ...", job, what)

    def beat() -> None:
        n = 0
        while not stop.wait(every):
            n += 1
            elapsed = duration(time.monotonic() - t0)
            log.info("%s: %s: still running, %s", job, what, elapsed)
            if n % 3 == 0:
                say(out, f"[{job}] {what}: {elapsed}")

    thread = threading.Thread(target=beat, name=f"heartbeat-{what}", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()
        log.info("%s: %s done in %s", job, what, duration(time.monotonic() - t0))
