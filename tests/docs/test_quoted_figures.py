"""One source per figure: the headline table and every figure a page quotes come from the records
the benchmarks write (benchmarks/figures/records/*.json, ``python -m benchmarks.records``), and the user's
pages state no measured time, dB or size of their own."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys

import pytest
from conftest import REPO

RECORDS = REPO / "benchmarks" / "figures" / "records"
HEADLINE = REPO / "docs" / "measurements" / "index.md"
#: a quoted figure (benchmarks/records.py's pattern, written here again: tests never import a benchmark)
QUOTE = re.compile(r"<!--fig:([\w.-]+)-->(.*?)<!--/fig-->", re.S)

#: the pages a user reads first: every measured figure on them is quoted from a record
USER_PAGES = [
    REPO / "README.md",
    REPO / "docs" / "index.md",
    REPO / "docs" / "getting-started.md",
    REPO / "docs" / "limitations.md",
    REPO / "docs" / "glossary.md",
    *sorted((REPO / "docs" / "guide").glob("*.md")),
]
#: a measured-looking figure: a number (or a range) with a unit of time, image quality or size
FIGURE = re.compile(
    r"(?<![\w.])\d[\d.,]*(?:\s?[-–]\s?\d[\d.,]*)?(?:\s|&nbsp;)?(?:ms|s|min|h|dB|[kKMGT]i?B)(?![\w])"
    r"(?:\s\d+\s?s\b)?"
)
#: figures on user pages that are not measurements: limits, settings and formats, each with why
NOT_MEASURED: dict[str, str] = {
    "security.md:4 GiB": "a limit the zip reader enforces",
    "security.md:64 MiB": "the record reader's limit",
    "security.md:512 MiB": "the picture reader's limit",
    "security.md:16 GiB": "the array and mesh reader's limit",
    "security.md:4 MiB": "the config reader's limit",
    "security.md:1 MB": "the size of a hostile prompt the tests feed",
    "slurm.md:4-8 GB": "the Slurm profile's memory requests (settings)",
    "slurm.md:150 s": "the length the Slurm test sizes its optimisation to (a setting of the test)",
    "assets.md:35 dB": "the bake's aim, not a measurement",
}


def stripped(text: str) -> str:
    """``text`` without code (fenced blocks, inline spans), quoted figures and HTML comments."""
    text = re.sub(r"^([ \t]*)(`{3,}|~{3,}).*?^\1\2[ \t]*$", "", text, flags=re.M | re.S)
    text = QUOTE.sub("", text)
    text = re.sub(r"<!--.*?-->", "", text, flags=re.S)
    return re.sub(r"`[^`\n]*`", "", text)


def records_command(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "benchmarks.records", *args], cwd=REPO, capture_output=True, text=True)


def test_the_pages_are_what_the_records_make():
    proc = records_command("--check")
    assert proc.returncode == 0, proc.stderr + "\nrun python -m benchmarks.records --write"


def test_every_record_is_whole_and_the_table_holds_them_all():
    found = {p.stem: json.loads(p.read_text()) for p in RECORDS.glob("*.json")}
    assert len(found) >= 20
    table = HEADLINE.read_text().split("<!-- headline:start -->")[1].split("<!-- headline:end -->")[0]
    for rid, r in found.items():
        assert r["id"] == rid and all(r.get(k) for k in ("what", "value", "date", "commit", "machine", "command", "page")), rid
        assert re.fullmatch(r"\d{4}-\d{2}-\d{2}.*", r["date"]), rid
        assert f"| {r['value'].replace('|', chr(92) + '|')}" in table, rid
        assert (HEADLINE.parent / r["page"].split("#")[0]).resolve().is_file(), (rid, r["page"])
    rows = [line for line in table.splitlines() if line.startswith("| ") and not line.startswith(("| figure", "| ---"))]
    assert len(rows) == len(found)


def test_a_stale_or_unknown_quote_fails_the_check(tmp_path):
    """A record whose value changed makes the pages stale until --write; a quote of no record fails."""
    folder = tmp_path / "records"
    shutil.copytree(RECORDS, folder)
    page = tmp_path / "page.md"
    rid = "demo.wall_time"
    value = json.loads((folder / f"{rid}.json").read_text())["value"]
    page.write_text(f"It took <!--fig:{rid}-->{value}<!--/fig--> here.\n")
    args = ("--records", str(folder), "--page", str(page))
    assert records_command("--check", *args).returncode == 0
    data = json.loads((folder / f"{rid}.json").read_text())
    (folder / f"{rid}.json").write_text(json.dumps({**data, "value": "9 min 9 s"}))
    proc = records_command("--check", *args)
    assert proc.returncode == 1 and "out of date" in proc.stderr
    assert records_command("--write", *args).returncode == 0
    assert "<!--fig:demo.wall_time-->9 min 9 s<!--/fig-->" in page.read_text()
    page.write_text(page.read_text() + "<!--fig:no.such-->1 s<!--/fig-->\n")
    proc = records_command("--check", *args)
    assert proc.returncode == 1 and "'no.such', which no record" in proc.stderr


@pytest.mark.parametrize("page", USER_PAGES, ids=lambda p: str(p.relative_to(REPO)))
def test_user_pages_state_no_figure_of_their_own(page):
    found = [m.group(0) for m in FIGURE.finditer(stripped(page.read_text()))]
    own = [f for f in found if f"{page.name}:{f}" not in NOT_MEASURED]
    assert not own, (
        f"{page.relative_to(REPO)} states measured figures that come from no record: {own}. Quote a record "
        "(<!--fig:ID-->value<!--/fig-->, benchmarks/figures/records/), link the measurements page, or drop the figure"
    )


def test_the_figure_pattern_finds_what_it_should():
    text = "took 4 min 0 s, 0.773-0.842 s a step, 29.41 dB, 1.0 GB and 290 MB; x 2 s; ids v2s; 3.6 GB."
    assert [m.group(0) for m in FIGURE.finditer(text)] == [
        "4 min 0 s",
        "0.773-0.842 s",
        "29.41 dB",
        "1.0 GB",
        "290 MB",
        "2 s",
        "3.6 GB",
    ]
    assert not list(FIGURE.finditer(stripped("`snakemake --cores 2` and <!--fig:a.b-->4 min<!--/fig-->\n```\n9 s\n```\n")))


def test_every_exemption_names_a_figure_a_page_states():
    stated = {f"{p.name}:{m.group(0)}" for p in USER_PAGES for m in FIGURE.finditer(stripped(p.read_text()))}
    assert not set(NOT_MEASURED) - stated, sorted(set(NOT_MEASURED) - stated)
