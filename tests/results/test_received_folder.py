"""A results folder received from someone else, with links, FIFOs and odd records where the
report expects its files: the report, the HTML report and the plan read, write and delete only
through the gate (stages/core/safefiles.py), so each is one line, nothing outside the folder is
read into a page, and nothing outside it is deleted or rewritten."""

from __future__ import annotations

import json
import os
import shutil
import signal
from pathlib import Path

import pytest
from conftest import synthetic_results

from stages import html_report, report
from stages.config.sections import ReportSettings
from stages.core.errors import StageInputError

SECRET = "the-password-is-swordfish"


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """A one-mesh, one-prompt synthetic tree with its report written (the folder form)."""
    results = tmp_path_factory.mktemp("made") / "results"
    cells = synthetic_results(results, meshes=1, prompts=1)
    report.run(results, cells, results / "report", json.loads((results / "decimated.json").read_text()))
    html_report.run(results, results / "report", cells)
    return results, cells


@pytest.fixture
def received(made, tmp_path):
    """A copy of the made tree (as it would arrive), and a secret file outside it."""
    results, cells = made
    copy = tmp_path / "inbox" / "results"
    shutil.copytree(results, copy, symlinks=True)
    secret = tmp_path / "secret.csv"
    secret.write_text(f"mesh,prompt,variant\n{SECRET},x,y\n")
    return copy, cells, secret


def _written(folder: Path) -> str:
    return "".join(p.read_text(errors="replace") for p in folder.rglob("*") if p.is_file() and p.suffix in (".html", ".js"))


@pytest.mark.parametrize("name", ["speed_accuracy.csv", "summary.json"])
@pytest.mark.parametrize("single_file", [False, True])
def test_a_linked_record_is_one_line_and_never_inlined(received, name, single_file):
    results, cells, secret = received
    (results / "report" / name).unlink()
    (results / "report" / name).symlink_to(secret)
    with pytest.raises(StageInputError, match=f"{name}: it is a symbolic link inside") as err:
        html_report.run(results, results / "report", cells, ReportSettings(single_file=single_file))
    assert "\n" not in str(err.value)
    assert SECRET not in _written(results / "report")


def test_a_linked_summary_csv_is_neither_read_nor_offered(received):
    """The pages read summary.json; the summary.csv they offer for download must be the plain
    file the report wrote, never a link to something else."""
    results, cells, secret = received
    (results / "report" / "summary.csv").unlink()
    (results / "report" / "summary.csv").symlink_to(secret)
    html_report.run(results, results / "report", cells)
    index = (results / "report" / "index.html").read_text()
    assert "href='summary.csv'" not in index and "speed_accuracy.csv" in index
    assert SECRET not in _written(results / "report")


def test_a_summary_that_is_not_its_rows_is_one_line(received):
    results, cells, _ = received
    (results / "report" / "summary.json").write_text(json.dumps([{"mesh": 1, "prompt": "p", "variant": "v"}]))
    with pytest.raises(StageInputError, match="summary.json: is not the list of rows the report stage writes"):
        html_report.run(results, results / "report", cells)


def test_a_linked_or_malformed_loss_record_is_one_line(received):
    results, cells, secret = received
    loss = results.joinpath(*cells[0]) / "optimize" / "loss.csv"
    loss.unlink()
    loss.symlink_to(secret)
    with pytest.raises(StageInputError, match="loss.csv: it is a symbolic link inside"):
        report.run(results, cells, results / "report")
    loss.unlink()
    loss.write_text("step,value\n1,2\n")  # not the columns the optimisation writes
    with pytest.raises(StageInputError, match="loss.csv: is not a table of the columns expected"):
        report.run(results, cells, results / "report")


def test_a_linked_figures_folder_keeps_the_pictures_it_points_to(received, tmp_path):
    results, cells, _ = received
    pictures = tmp_path / "Pictures"
    pictures.mkdir()
    (pictures / "holiday.png").write_bytes(b"\x89PNG holiday")
    shutil.rmtree(results / "report" / "figures")
    (results / "report" / "figures").symlink_to(pictures, target_is_directory=True)
    with pytest.raises(StageInputError, match="figures, a symbolic link inside"):
        report.run(results, cells, results / "report")
    assert [p.name for p in pictures.iterdir()] == ["holiday.png"]


@pytest.mark.parametrize("single_file", [False, True])
def test_a_linked_report_folder_is_refused_before_anything_in_it_changes(received, tmp_path, single_file):
    results, cells, _ = received
    target = tmp_path / "elsewhere"
    (results / "report" / "figures.json").unlink()  # a report received without its figures' record
    shutil.move(results / "report", target)
    (results / "report").symlink_to(target, target_is_directory=True)
    before = {p: p.stat().st_mtime_ns for p in target.rglob("*")}
    with pytest.raises(StageInputError, match="symbolic link inside"):
        html_report.run(results, results / "report", cells, ReportSettings(single_file=single_file))
    assert {p: p.stat().st_mtime_ns for p in target.rglob("*")} == before


@pytest.mark.parametrize("kind", ["fifo", "zero"])
def test_a_fifo_or_endless_meta_json_does_not_stop_the_plan(received, kind, caplog):
    """The plan reads earlier runs' meta.json files for its estimate: a FIFO (which used to hang
    every Snakemake start) or a link to /dev/zero (which used to grow without end) is left out,
    with a warning naming it."""
    from stages.plan import earlier_step_seconds

    results, cells, _ = received
    meta = results.joinpath(*cells[0]) / "optimize" / "meta.json"
    meta.unlink()
    if kind == "fifo":
        os.mkfifo(meta)
    else:
        meta.symlink_to("/dev/zero")

    def hung(*_):
        raise TimeoutError("the plan hung on the record")

    previous = signal.signal(signal.SIGALRM, hung)
    signal.alarm(20)  # a hang fails the test instead of stopping the run
    try:
        assert earlier_step_seconds(results.parent, "any", "cpu") is None  # as results/<experiment>/...
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    assert "meta.json" in caplog.text and "left out of the estimate" in caplog.text


def test_a_record_of_odd_figures_is_left_out_of_the_plan(received):
    """Figures the plan reads from earlier runs that are no figures (a text, a bool, an integer
    past float's range, NaN) leave the record out, in no traceback."""
    from stages.plan import earlier_step_seconds, positive_figure

    assert [positive_figure(v) for v in ("2", True, 10**400, float("nan"), -1.0, 0.5)] == [None] * 5 + [0.5]
    results, cells, _ = received
    meta = results.joinpath(*cells[0]) / "optimize" / "meta.json"
    meta.write_text('{"seconds_per_iteration": 1' + "0" * 400 + ', "device": "cpu", "settings": {}}')
    assert earlier_step_seconds(results.parent, "any", "cpu") is None
