"""The HTML report at scale: a synthetic 150-cell results tree (scripts/synthetic_results.py:
generated inputs with real GLBs, no optimisation) through the report and html_report stages,
then the folder checked on disk (sizes, relative references, each cell page's own assets) and
in headless Chromium (no console errors, the index interactive within a second, filtering and
sorting, a cell page's viewer drawing its model under the learned light and the studio light,
from disk, from a zipped copy, and over HTTP)."""

from __future__ import annotations

import base64
import functools
import http.server
import json
import threading
import time
import zipfile
from pathlib import Path
from urllib.parse import unquote, urlparse

import numpy as np
import pandas as pd
import pytest
from conftest import assert_not_blank, browser_check, page_references, synthetic_results

from stages import html_report, report
from stages.config.sections import ReportSettings

#: the budget of the issue: the index under 2 MB and interactive within a second at 150 cells
INDEX_BYTES = 2_000_000
INTERACTIVE_MS = 1000


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    results = tmp_path_factory.mktemp("synthetic") / "results"
    cells = synthetic_results(results, meshes=10, prompts=3, decimated=2)
    assert len(cells) == 150
    t0 = time.perf_counter()
    report.run(results, cells, results / "report", json.loads((results / "decimated.json").read_text()))
    t1 = time.perf_counter()
    out = html_report.run(results, results / "report", cells)
    t2 = time.perf_counter()
    return {"results": results, "dir": results / "report", "cells": cells, "out": out, "seconds": (t1 - t0, t2 - t1)}


def test_folder_layout_and_budget(site):
    d, cells = site["dir"], site["cells"]
    index = d / "index.html"
    assert site["out"] == {"cells": 150, "viewers": 150, "index_bytes": index.stat().st_size}
    assert index.stat().st_size < INDEX_BYTES
    assert not list(d.glob(".*.partial"))
    text = index.read_text()
    assert "TEST ONLY: 150 of 150 cells" in text and "<model-viewer" not in text and "<script src" not in text
    refs = page_references(text)
    links = {r for r in refs if r.startswith("cells/") and r.endswith("/index.html")}
    assert links == {f"cells/{'/'.join(c)}/index.html" for c in cells}
    for ref in refs:  # relative, inside the folder, present (or inline)
        if ref.startswith("data:"):
            continue
        assert not urlparse(ref).scheme and not ref.startswith("/"), ref
        target = (d / unquote(ref)).resolve()
        assert target.is_relative_to(d.resolve()) and target.exists(), ref


def test_each_cell_page_refers_only_to_its_own_assets(site):
    d = site["dir"].resolve()
    for cell in site["cells"]:
        folder = d.joinpath("cells", *cell)
        text = (folder / "index.html").read_text()
        for ref in page_references(text):
            if ref.startswith("data:"):
                continue
            target = (folder / unquote(ref)).resolve()
            assert target.exists(), (cell, ref)
            own = target.is_relative_to(folder) or target.parent == d / "viewer" or target == d / "index.html"
            assert own, (cell, ref)
        assert "TEST ONLY" in text.split("<h2")[0]  # the origin banner comes first
        glb = folder / "model.glb"
        assert glb.read_bytes() == site["results"].joinpath(*cell, "export", "model.glb").read_bytes()
        packed = (folder / "assets.js").read_text()  # the same bytes, for a browser reading from disk
        assert packed.startswith("window.TANGO_CELL_ASSETS = ")
        assets = json.loads(packed.removeprefix("window.TANGO_CELL_ASSETS = ").rstrip().rstrip(";"))
        assert base64.b64decode(assets["glb"]) == glb.read_bytes()
        assert base64.b64decode(assets["hdr"]) == (folder / "light.hdr").read_bytes()
    assert (d / "viewer" / "model-viewer.min.js").is_file() and (d / "viewer" / "cell.js").is_file()


def test_like_with_like_figures(site):
    d = site["dir"]
    meta = json.loads((d / "figures.json").read_text())
    titles = {e["title"]: e for e in meta["figures"]}
    assert "Speed / accuracy per mesh x prompt" in titles and "Ablations per mesh x prompt" in titles
    assert all("file" in e for e in meta["figures"]), [e for e in meta["figures"] if "file" not in e]
    robustness = [t for t in titles if t.startswith("Robustness")]
    assert len(robustness) == 2 and all("5,000 faces" in t for t in robustness)
    assert len(meta["groups"]) == 30  # 10 meshes x 3 prompts: one group each, never across them
    for g in meta["groups"]:
        assert g["reference"] == "base"
        assert g["configurations"]["base"] == ["base", "base_seed1"]
        assert g["ablations"] == ["no_normal", "no_spec"] and g["factors"]["it100"] == "iterations, milestones"
    sa = pd.read_csv(d / "speed_accuracy.csv")
    assert len(sa) == 30 * 4 and sa.groupby("group")["pareto"].any().all()
    assert (sa.loc[sa["configuration"] == "base", "seeds"] == 2).all()


def test_index_in_chromium_from_a_zipped_copy(site, tmp_path):
    archive = tmp_path / "report.zip"
    with zipfile.ZipFile(archive, "w") as z:
        for f in site["dir"].rglob("*"):
            if f.is_file():
                z.write(f, f.relative_to(site["dir"]))
    copy = tmp_path / "unzipped"
    zipfile.ZipFile(archive).extractall(copy)
    r = browser_check("index", copy / "index.html", tmp_path / "index.png", "--filter", "shape03 wood", "--mesh", "shape01")
    assert r["errors"] == []
    assert r["interactive_ms"] < INTERACTIVE_MS, r["interactive_ms"]
    assert r["rows"] == 150 and r["filtered_rows"] == 5 and r["shown_label"] == "5"
    assert r["mesh_rows"] == 15 and r["mesh_values"] == ["shape01"]
    assert r["sorted_quality"] == sorted(r["sorted_quality"]) and len(r["sorted_quality"]) == 150
    assert r["sorted_quality_desc"] == sorted(r["sorted_quality"], reverse=True)
    assert r["load_ms"] < INTERACTIVE_MS, r["load_ms"]
    assert r["figures"] >= 6 and r["skipped"] == []
    # the index loads its own thumbnails and figures, never a cell page's assets or a viewer
    assert not any(u.endswith((".glb", ".hdr", "assets.js", "model-viewer.min.js")) for u in r["requests"])


def _cell_requests_ok(requests: list[str], folder: Path, root: Path) -> None:
    for url in requests:
        parsed = urlparse(url)
        if parsed.scheme == "blob":
            continue
        path = Path(unquote(parsed.path)) if parsed.scheme == "file" else root / unquote(parsed.path).lstrip("/")
        assert path.is_relative_to(folder) or path.parent == root / "viewer", url


def test_cell_page_in_chromium_from_disk(site, tmp_path):
    cell = site["cells"][17]
    folder = site["dir"].joinpath("cells", *cell)
    r = browser_check("cell", folder / "index.html", tmp_path / "cell.png")
    assert r["errors"] == [] and r["viewers"] == r["loaded"] == 1
    assert r["environment"].endswith("#light.hdr") and r["environment_studio"] == "neutral"
    assert r["galleries"] == 2 and r["gallery_switch"] is True
    _cell_requests_ok(r["requests"], folder, site["dir"])
    assert any(u.endswith("/assets.js") for u in r["requests"])
    assert_not_blank(tmp_path / "cell.png")
    from PIL import Image

    learned = np.asarray(Image.open(tmp_path / "cell.png").convert("RGB")).astype(float)
    studio = np.asarray(Image.open(tmp_path / "cell_studio.png").convert("RGB")).astype(float)
    assert np.abs(learned - studio).mean() > 2.0, "the light toggle did not change the render"


def test_cell_page_over_http(site, tmp_path):
    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args):
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Quiet, directory=str(site["dir"])))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        cell = site["cells"][3]
        url = f"http://127.0.0.1:{server.server_address[1]}/cells/{'/'.join(cell)}/index.html"
        r = browser_check("cell", url, tmp_path / "cell.png")
    finally:
        server.shutdown()
    assert r["errors"] == [] and r["loaded"] == 1 and r["environment"].endswith("light.hdr")
    assert any(u.endswith("/model.glb") for u in r["requests"]) and not any(u.endswith("assets.js") for u in r["requests"])
    _cell_requests_ok(r["requests"], site["dir"].joinpath("cells", *cell), site["dir"])
    assert_not_blank(tmp_path / "cell.png")


def test_single_file_for_small_grids(site, tmp_path):
    cells = site["cells"][:3]
    out_dir = tmp_path / "report"
    report.run(site["results"], cells, out_dir)
    out = html_report.run(site["results"], out_dir, cells, ReportSettings(single_file=True))
    assert out["viewers"] == 3 and not (out_dir / "cells").exists()
    text = (out_dir / "index.html").read_text()
    # everything inline but the downloads, which link the cells' files where they lie (and the
    # texture sets zipped under the report's downloads/)
    offered = {r for r in page_references(text) if not r.startswith(("data:", "#"))}
    assert offered and all((out_dir / unquote(r)).is_file() for r in offered), offered
    assert {Path(r).name for r in offered} == {"model.glb", "textures.zip"}  # the synthetic cells have no USDZ
    r = browser_check("single", out_dir / "index.html", tmp_path / "single.png")
    assert r["errors"] == [] and r["viewers"] == r["loaded"] == 3
    assert_not_blank(tmp_path / "single.png")
    # each viewer has its own light buttons
    first, *others = r["environments_after_first_studio"]
    assert first == "neutral" and others and all(e.endswith("#light.hdr") for e in others)


def test_ids_that_look_like_numbers_keep_their_pages(site, tmp_path):
    """Ids are text: a mesh "01", a prompt "NA" and a variant "1e3" (all valid ids) keep their
    links, banners and comparison line (a CSV reader would make them 1, NaN and 1000.0)."""
    import shutil

    src, results = site["results"], tmp_path / "results"
    shutil.copytree(src / "shape00" / "normalize", results / "01" / "normalize")
    for variant, new in (("base", "base"), ("no_normal", "1e3")):
        shutil.copytree(src / "shape00" / "wood" / variant, results / "01" / "NA" / new)
    cells = [("01", "NA", "base"), ("01", "NA", "1e3")]
    report.run(results, cells, results / "report")
    html_report.run(results, results / "report", cells)
    index = (results / "report" / "index.html").read_text()
    assert "cells/01/NA/1e3/index.html" in page_references(index)
    page = (results / "report" / "cells" / "01" / "NA" / "1e3" / "index.html").read_text()
    assert "TEST ONLY: 1 of 1 cells" in page and "changes against the reference (base): normal_network (an ablation)" in page


def test_comparison_line_finds_the_cells_own_group():
    """A mesh x prompt can hold several groups (another quality measure, another kind of
    weights); a cell is described by the group it is in, and a cell in none gets no line."""
    from stages.results.site import comparison_text

    groups = [
        {"mesh": "m", "prompt": "p", "reference": "a", "configurations": {"a": ["a"], "b": ["b"]}, "factors": {"b": "lr"}},
        {"mesh": "m", "prompt": "p", "reference": None, "configurations": {"c": ["c", "c2"]}, "factors": {"c": ""}},
        {"mesh": "m", "prompt": "p", "reference": "a", "configurations": {"a": ["a"]}, "duplicates": {"d": "a"}, "factors": {}},
    ]
    assert comparison_text(("m", "p", "b"), groups) == "changes against the reference (a): lr"
    expected = "no reference variant in this mesh x prompt to compare with; seed replicates: c, c2"
    assert comparison_text(("m", "p", "c2"), groups) == expected
    assert "the same settings as a, seed included" in comparison_text(("m", "p", "d"), groups)
    assert comparison_text(("m", "p", "unmeasured"), groups) == ""
    assert comparison_text(("other", "p", "b"), groups) == ""


def test_relit_figures_under_the_relit_picture():
    """The relighting graded against Mitsuba (summary columns, one entry per environment) is printed
    under the relit figure, a line per light: raw, scaled and the true material's ceiling; a cell
    without it gets no line."""
    import pandas as pd

    from stages.results.site import fidelity_lines, relit_lines

    row = pd.DataFrame(
        [
            {  # as summary.json holds them: one entry per environment
                "relit_environments": ["builtin:sunset", "config/envmaps/studio.hdr"],
                "relit_psnr_db": [21.5, 19.25],
                "relit_psnr_scaled_db": [23.0, 20.0],
                "relit_ceiling_psnr_db": [27.0, 25.1],
                "relit_scale": [[1.72, 1.46, 1.12], [1.0, 1.01, 0.99]],
            }
        ]
    )
    lines = relit_lines(row)
    assert lines == [
        "under builtin:sunset: 21.50 dB raw; 23.00 dB after one scale per channel (x 1.72, 1.46, 1.12); "
        "the true material in our renderer (the ceiling): 27.00 dB",
        "under config/envmaps/studio.hdr: 19.25 dB raw; 20.00 dB after one scale per channel (x 1.00, 1.01, 0.99); "
        "the true material in our renderer (the ceiling): 25.10 dB",
    ]
    assert not any("relit" in line for line in fidelity_lines(row))  # under the relit figure, not on the cell line
    old = row.drop(columns=["relit_scale"])  # a summary written before the factors were: the line without them
    expected = "under builtin:sunset: 21.50 dB raw; 23.00 dB after one scale per channel; the true material"
    assert relit_lines(old)[0].startswith(expected)
    assert relit_lines(pd.DataFrame([{"relit_psnr_db": float("nan")}])) == []


def test_the_pages_come_from_autoescaping_templates_that_mark_nothing_safe():
    """Every value reaches a page through a template that escapes it: no template marks a value
    safe, and Python marks safe only the style sheet, our own scripts and pandas' escaped table."""
    from stages.results import site

    env = site.templates()
    assert env.autoescape is True
    hostile = "<script>alert(1)</script>' onerror='x"
    text = env.get_template("macros.html").module.gallery([{"src": hostile, "label": hostile}])
    assert "<script>" not in str(text) and "' onerror=" not in str(text) and "&lt;script&gt;" in str(text)
    for template in site.TEMPLATES.glob("*.html"):
        assert "|safe" not in template.read_text().replace(" ", ""), template
    lines = [line for line in Path(site.__file__).read_text().splitlines() if "Markup(" in line and "import" not in line]
    allowed = ('Markup(read_text(WEB / "report.css"))', "Markup(code)", "Markup(frame.to_html(")
    assert len(lines) == 4 and all(any(a in line for a in allowed) for line in lines), lines
