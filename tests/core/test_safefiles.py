"""A results folder is data that may come from someone else: the stages read and write only plain
files reached without a symbolic link inside it (stages/core/safefiles.py), a FIFO or a device is
refused in one line instead of hanging the reader, and a received figures.json or meta file cannot
name a path outside it."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from PIL import Image

from stages.core.errors import StageInputError
from stages.core.provenance import atomic_path, staged_outputs, write_json_atomic
from stages.core.safefiles import file_kind, inside, plain_file, require_plain_file, results_root


def test_a_stage_folder_that_links_elsewhere_is_not_written_through(tmp_path):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    cell = tmp_path / "results" / "exp" / "vase" / "wood" / "base"
    cell.mkdir(parents=True)
    (cell / "relight").symlink_to(elsewhere, target_is_directory=True)
    with pytest.raises(StageInputError, match=r"would be written through .*relight, a symbolic link inside .*results") as err:
        write_json_atomic(cell / "relight" / "meta.json", {"x": 1})
    assert "\n" not in str(err.value)
    with pytest.raises(StageInputError, match="a symbolic link inside"):
        with staged_outputs(cell / "relight"):
            pass
    with pytest.raises(StageInputError, match="a symbolic link inside"):
        write_json_atomic(cell / "relight" / "sub" / "deeper.json", {})
    assert not list(elsewhere.iterdir())


def test_the_results_folder_itself_may_be_a_link_and_other_paths_are_the_callers(tmp_path):
    disk = tmp_path / "big_disk"
    disk.mkdir()
    (tmp_path / "work").mkdir()
    (tmp_path / "work" / "results").symlink_to(disk, target_is_directory=True)
    write_json_atomic(tmp_path / "work" / "results" / "exp" / "meta.json", {"x": 1})
    assert json.loads((disk / "exp" / "meta.json").read_text()) == {"x": 1}
    assert results_root(tmp_path / "work" / "results" / "exp" / "meta.json") == tmp_path / "work" / "results"
    # outside any results folder (a stage run by hand): the caller's own paths
    (tmp_path / "mine").symlink_to(disk, target_is_directory=True)
    with atomic_path(tmp_path / "mine" / "out.txt") as tmp:
        tmp.write_text("ok")
    assert (disk / "out.txt").read_text() == "ok"


def test_links_fifos_and_devices_are_not_plain_files(tmp_path):
    root = tmp_path / "results"
    root.mkdir()
    (root / "real.png").write_bytes(b"x")
    (root / "link.png").symlink_to(root / "real.png")
    os.mkfifo(root / "pipe.png")
    assert [file_kind(root / n) for n in ("real.png", "link.png", "pipe.png", "none.png")] == ["file", "link", "FIFO", "missing"]
    assert file_kind("/dev/null") == "device"
    assert plain_file(root / "real.png") and not plain_file(root / "link.png") and not plain_file(root / "pipe.png")
    with pytest.raises(StageInputError, match="it is a symbolic link inside"):
        require_plain_file(root / "link.png")
    with pytest.raises(StageInputError, match="is a FIFO, not a plain file"):
        require_plain_file(root / "pipe.png")
    for name in ("/etc/passwd", "../outside.png", "a/../../x.png", ""):
        with pytest.raises(StageInputError, match="which is not a path inside"):
            inside(root, name)
    assert inside(root, "real.png") == root / "real.png"


def test_a_received_figures_json_cannot_inline_a_file_from_outside(tmp_path, caplog):
    from stages.results.site import data_uri, figure_entries

    secret = tmp_path / "secret.txt"
    secret.write_text("the password")
    report = tmp_path / "results" / "exp" / "report"
    (report / "figures").mkdir(parents=True)
    Image.new("RGB", (4, 4), "red").save(report / "figures" / "good.png")
    (report / "figures" / "linked.png").symlink_to(secret)
    os.mkfifo(report / "figures" / "pipe.png")
    entries = [
        {"title": n, "file": f} for n, f in [("abs", str(secret)), ("up", "../../../secret.txt"), ("link", "figures/linked.png")]
    ]
    entries += [{"title": "pipe", "file": "figures/pipe.png"}, {"title": "good", "file": "figures/good.png"}]
    (report / "figures.json").write_text(json.dumps({"figures": entries}))
    shown = figure_entries(report, data_uri)  # single-file mode: every figure inlined
    text = json.dumps(shown)
    assert "the password" not in text and "dGhlIHBhc3N3b3Jk" not in text  # nor its base64
    assert [e["src"] is None for e in shown] == [True, True, True, True, False]  # the good one is drawn
    assert shown[-1]["src"].startswith("data:image/png;base64,")
    assert sum("figure not shown" in r.message for r in caplog.records) == 4


def test_a_render_that_is_a_link_a_fifo_or_a_bad_sheet_is_one_line(tmp_path):
    from stages.results.summary import front_tile

    results = tmp_path / "results" / "exp"
    opt = results / "vase" / "wood" / "base" / "optimize"
    (opt / "renders").mkdir(parents=True)
    Image.fromarray(np.zeros((64, 128, 3), np.uint8)).save(opt / "renders" / "real.png")
    sheet = {"front_view": 1, "columns": 2, "tile": 64}
    (opt / "meta.json").write_text(json.dumps({"sheet": sheet}))
    (opt / "renders" / "rgb.png").symlink_to(opt / "renders" / "real.png")
    with pytest.raises(StageInputError, match="it is a symbolic link inside"):
        front_tile(results, ("vase", "wood", "base"))
    (opt / "renders" / "rgb.png").unlink()
    os.mkfifo(opt / "renders" / "rgb.png")
    with pytest.raises(StageInputError, match="is a FIFO, not a plain file"):
        front_tile(results, ("vase", "wood", "base"))
    (opt / "renders" / "rgb.png").unlink()
    (opt / "renders" / "real.png").rename(opt / "renders" / "rgb.png")
    assert front_tile(results, ("vase", "wood", "base"), size=16).size == (16, 16)
    for bad in ({**sheet, "tile": 100_000}, {**sheet, "tile": "64"}, {**sheet, "front_view": 9}, {**sheet, "columns": 0}):
        (opt / "meta.json").write_text(json.dumps({"sheet": bad}))
        with pytest.raises(StageInputError, match="its sheet") as err:
            front_tile(results, ("vase", "wood", "base"))
        assert "\n" not in str(err.value)


def test_a_ray_cache_target_or_meta_that_is_a_link_or_a_fifo_is_one_line(tmp_path):
    from stages.geometry.raycache import RayCache
    from stages.results.summary import _read

    work = tmp_path / "results" / "meshes" / "vase" / "k" / "raycache"
    work.mkdir(parents=True)
    np.savez(tmp_path / "elsewhere.npz", width=np.array(4))
    (work / "train.npz").symlink_to(tmp_path / "elsewhere.npz")
    with pytest.raises(StageInputError, match="it is a symbolic link inside"):
        RayCache(work / "train.npz")
    os.mkfifo(work / "eval.npz")
    with pytest.raises(StageInputError, match="is a FIFO"):
        RayCache(work / "eval.npz")
    os.mkfifo(work / "meta.json")
    with pytest.raises(StageInputError, match="is a FIFO"):
        _read(work / "meta.json")
    assert _read(work / "none.json") is None


def test_a_received_record_that_is_not_json_or_not_the_reports_is_one_line_or_ignored(tmp_path, caplog):
    from stages.core.safefiles import read_json
    from stages.results.site import figure_entries

    report = tmp_path / "results" / "exp" / "report"
    report.mkdir(parents=True)
    (report / "meta.json").write_text("{not json")
    with pytest.raises(StageInputError, match="is not valid JSON") as err:
        read_json(report / "meta.json")
    assert "\n" not in str(err.value)
    for junk in ("[1, 2]", '{"figures": "x"}', '{"figures": [1, {"file": 3}]}'):
        (report / "figures.json").write_text(junk)
        assert all(e["src"] is None for e in figure_entries(report, str))
