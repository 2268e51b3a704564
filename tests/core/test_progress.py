"""Progress lines of long jobs: steady interval, rate and ETA counted from this process's own
steps, a short line for the terminal, and a heartbeat for calls that report nothing."""

from __future__ import annotations

import io
import logging
import time

import pytest

from stages.core.progress import Progress, duration, heartbeat, interval_s, job_label


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_lines_at_a_steady_interval_with_rate_and_eta(caplog):
    clock, term = Clock(), io.StringIO()
    p = Progress("optimize vase/wood/full", 1000, initial=200, every=10, terminal_every=30, clock=clock, terminal=term)
    with caplog.at_level(logging.INFO, logger="stages.core.progress"):
        for _ in range(400):  # 4 steps per second for 100 s
            clock.t += 0.25
            p.update(loss="0.5")
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 10  # one per 10 s, not one per step
    # after 100 s: 400 steps done here at 4/s (the 200 inherited from a checkpoint do not count
    # towards the rate), 400 left: 100 s
    assert lines[-1] == "optimize vase/wood/full: 600/1000 it (60%), 4.00 it/s, ETA 1m40s, elapsed 1m40s, loss 0.5"
    short = term.getvalue().splitlines()
    assert len(short) == 3 and short[-1] == "[optimize vase/wood/full] 560/1000 it, 4.00 it/s, ETA 1m50s"  # at 90 s
    p.close()
    assert term.getvalue().splitlines()[-1] == "[optimize vase/wood/full] 600/1000 it, 4.00 it/s, ETA 1m40s"


def test_before_the_first_step_and_at_the_end():
    clock = Clock()
    p = Progress("bake", 5, every=1, clock=clock, terminal=io.StringIO())
    assert p.rate() is None and p.eta_s() is None and "ETA -" in p.line()
    clock.t += 2
    p.update(5)
    assert p.eta_s() == 0 and "5/5 it (100%)" in p.line()


def test_duration_and_label_and_interval(monkeypatch):
    assert duration(3725.2) == "1h02m05s" and duration(65) == "1m05s" and duration(4.4) == "4s" and duration(-3) == "0s"
    assert job_label("optimize", "results/exp/vase/wood/full/optimize") == "optimize vase/wood/full"
    assert job_label("bake", "bake") == "bake"
    monkeypatch.setenv("TANGO_PROGRESS_S", "2.5")
    assert interval_s() == 2.5
    for bad in ("0", "-1", "soon"):
        monkeypatch.setenv("TANGO_PROGRESS_S", bad)
        with pytest.raises(ValueError, match="TANGO_PROGRESS_S"):
            interval_s()


def test_heartbeat_reports_a_silent_call_while_it_runs(caplog):
    term = io.StringIO()
    with caplog.at_level(logging.INFO, logger="stages.core.progress"):
        with heartbeat("bake vase/wood/full", "unwrapping", every=0.05, terminal=term):
            time.sleep(0.6)
    lines = [r.getMessage() for r in caplog.records]
    assert lines[0] == "bake vase/wood/full: unwrapping ..."
    beats = [m for m in lines if "still running" in m]
    assert 2 <= len(beats) <= 12, lines  # about 12 at 0.05 s; fewer on a busy machine
    assert lines[-1].startswith("bake vase/wood/full: unwrapping done in ")
    # every third beat also goes to the terminal
    assert len(term.getvalue().splitlines()) == len(beats) // 3
    if len(beats) >= 3:
        assert term.getvalue().startswith("[bake vase/wood/full] unwrapping: ")


def test_a_broken_terminal_never_stops_the_job():
    class Broken(io.StringIO):
        def write(self, text):
            raise BrokenPipeError("the terminal is gone")

    clock = Clock()
    p = Progress("optimize", 10, every=1, terminal_every=1, clock=clock, terminal=Broken())
    for _ in range(10):
        clock.t += 1
        p.update()
    p.close()
    assert p.lines == 11
