"""The documentation's pictures and examples (benchmarks/workflow/doc_pictures.py) carry the commit
they were made at, and none is older than the last change to what it shows."""

from __future__ import annotations

import json
import re
import subprocess

import pytest
from conftest import REPO

DOCS = REPO / "docs"
MANIFEST = DOCS / "pictures.json"


def git(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True)


def entries() -> dict:
    return json.loads(MANIFEST.read_text())


def test_every_picture_and_example_is_recorded_and_used():
    found = entries()
    assert {"demo.png", "report_index.png", "report_cell.png", "examples/doctor.md", "examples/plan.md"} <= set(found)
    pages = "\n".join(p.read_text() for p in [REPO / "README.md", *DOCS.rglob("*.md")])
    for name, e in found.items():
        assert (DOCS / name).is_file(), name
        assert re.fullmatch(r"[0-9a-f]{7,40}", e["commit"]) and e["shows"], name
        assert name in pages or f"docs/{name}" in pages, f"{name} is shown on no page"


def test_the_pngs_carry_their_commit():
    from PIL import Image

    for name, e in entries().items():
        if name.endswith(".png"):
            with Image.open(DOCS / name) as img:
                assert img.text.get("tango-stylize:commit") == e["commit"], name
        else:
            assert f"commit {e['commit']}" in (DOCS / name).read_text(), name


@pytest.mark.parametrize("name", sorted(entries()))
def test_no_picture_is_older_than_what_it_shows(name):
    """The last commit that changed a path the picture shows is its own commit or an ancestor of it;
    else the picture shows code that has changed since: make them again
    (python -m benchmarks.workflow.doc_pictures results/demo after the demo)."""
    if not (REPO / ".git").exists() or git("rev-parse", "HEAD").returncode != 0:
        pytest.skip("not a git checkout: no history to compare with")
    if git("rev-parse", "--is-shallow-repository").stdout.strip() == "true":
        pytest.skip("a shallow clone: the history that says what changed after a picture is not here")
    e = entries()[name]
    made = git("rev-parse", "--verify", f"{e['commit']}^{{commit}}")
    assert made.returncode == 0, f"{name}: its commit {e['commit']} is not in this history"
    last = git("log", "-1", "--format=%H", "--", *e["shows"]).stdout.strip()
    assert last, f"{name}: no commit changed {e['shows']}"
    fresh = git("merge-base", "--is-ancestor", last, e["commit"]).returncode == 0
    assert fresh, (
        f"docs/{name} was made at {e['commit']}, before {last[:8]} changed what it shows ({', '.join(e['shows'])}): "
        "run the demo, then python -m benchmarks.workflow.doc_pictures results/demo"
    )
