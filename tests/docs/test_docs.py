"""The documentation: the generated configuration reference matches its sources, the MkDocs site
builds strictly, every relative link of the README and the pages resolves, and the README stays a
front door whose test command is the one CI runs."""

from __future__ import annotations

import dataclasses
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import REPO, require_tool

from stages.config import reference
from stages.config.schema import schema as load_schema
from stages.config.sections import SECTIONS

README = REPO / "README.md"
DOCS = REPO / "docs"
CI_RUN = REPO / ".ci" / "run"
#: the README is a front door; the measurements and the manual live in docs/
README_MAX_LINES = 250

FENCE = re.compile(r"^(```|~~~).*?^\1", re.M | re.S)
INLINE_CODE = re.compile(r"`[^`\n]*`")
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")


def relative_links(path: Path) -> list[str]:
    """The targets of the Markdown links and images of ``path`` that are relative paths (not URLs,
    not mere anchors), outside code blocks and code spans."""
    text = INLINE_CODE.sub("", FENCE.sub("", path.read_text()))
    targets = []
    for target in LINK.findall(text):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue
        targets.append(target)
    return targets


def section_of(page: str, heading: str) -> str:
    """The text of ``page`` under the level-2 ``heading``, up to the next level-2 heading."""
    match = re.search(rf"^## {re.escape(heading)}\n(.*?)(?=^## |\Z)", page, re.M | re.S)
    assert match, f"the reference has no section '## {heading}'"
    return match.group(1)


# ------------------------------------------------------------------------ configuration reference
def test_configuration_reference_is_up_to_date():
    page = REPO / reference.PAGE
    assert page.is_file(), f"{reference.PAGE} is missing: run {reference.WRITE_COMMAND}"
    assert page.read_text() == reference.markdown(), (
        f"{reference.PAGE} is out of date with workflow/schemas/config.schema.yaml and "
        f"stages/config/sections.py: run {reference.WRITE_COMMAND} and commit the result"
    )


def test_reference_lists_every_top_level_key_section_and_field():
    page = reference.markdown()
    top = section_of(page, "Top-level keys")
    for key in load_schema()["properties"]:
        assert f"| `{key}` |" in top, f"top-level key {key!r} is missing from the reference's top-level table"
    for name, cls in SECTIONS.items():
        part = section_of(page, name)
        for field in dataclasses.fields(cls):
            assert re.search(rf"^\| `{field.name}` \|", part, re.M), f"{name}.{field.name} is missing from the reference"


def test_reference_shows_the_dataclass_defaults_and_the_schema_ranges():
    rows = {row[0]: row for row in reference.section_rows("decimate")}
    assert rows["`target_faces`"][2] == "`5000`" and rows["`target_faces`"][3] == "[4, 10000000]"
    assert rows["`weld_tolerance`"][3] == "[0, 0.01)"
    assert rows["`mode`"][3] == "`faces`, `share`, `budget`"
    rows = {row[0]: row for row in reference.section_rows("raycache")}
    assert rows["`anchor_deg`"][1] == "list of 2 numbers or null" and rows["`anchor_deg`"][2] == "`null`"


def test_reference_command_checks_and_writes(tmp_path, monkeypatch):
    monkeypatch.setattr(reference, "REPO_ROOT", tmp_path)
    assert reference.main(["--check"]) == 1  # no file yet
    (tmp_path / reference.PAGE).parent.mkdir(parents=True)
    (tmp_path / reference.PAGE).write_text(reference.markdown().replace("`1500`", "`1000`"))
    assert reference.main(["--check"]) == 1  # a stale default
    assert reference.main(["--write"]) == 0
    assert (tmp_path / reference.PAGE).read_text() == reference.markdown()
    assert reference.main(["--check"]) == 0


# ------------------------------------------------------------------------------------- the site
def mkdocs_command() -> list[str] | None:
    exe = Path(sys.executable).with_name("mkdocs")
    if exe.is_file():
        return [str(exe)]
    try:
        import mkdocs  # noqa: F401
    except ImportError:
        return None
    return [sys.executable, "-m", "mkdocs"]


def test_site_builds_strictly(tmp_path):
    cmd = mkdocs_command()
    require_tool(cmd is not None, "MkDocs is not installed (pip install -e '.[test]' installs mkdocs-material)")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    out = subprocess.run(
        [*cmd, "build", "--strict", "--config-file", str(REPO / "mkdocs.yml"), "--site-dir", str(tmp_path / "site")],
        cwd=REPO,
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert out.returncode == 0, f"mkdocs build --strict failed:\n{out.stdout}\n{out.stderr}"
    site = tmp_path / "site"
    assert (site / "reference" / "configuration" / "index.html").is_file()
    # offline: MathJax served with the site, and no page loads a script or style from elsewhere
    assert (site / "javascripts" / "vendor" / "mathjax" / "tex-svg.js").stat().st_size > 1_000_000
    fetched = {
        (page.relative_to(site).as_posix(), url)
        for page in site.rglob("*.html")
        for url in re.findall(r'<(?:script|link)[^>]+(?:src|href)="(https?://[^"]+)"', page.read_text())
    }
    assert not fetched, f"pages that fetch from the network: {sorted(fetched)[:5]}"
    method = (site / "method" / "brdf" / "index.html").read_text()
    assert "javascripts/vendor/mathjax/tex-svg.js" in method and "arithmatex" in method


# ---------------------------------------------------------------------------- the README and links
def test_readme_is_a_front_door():
    lines = README.read_text().splitlines()
    assert len(lines) <= README_MAX_LINES, (
        f"README.md has {len(lines)} lines (at most {README_MAX_LINES}): move measurements and details into docs/"
    )


@pytest.mark.parametrize(
    "page",
    [README, *sorted(DOCS.rglob("*.md")), REPO / "config" / "README.md"],
    ids=lambda p: str(p.relative_to(REPO)),
)
def test_relative_links_resolve(page):
    broken = []
    for target in relative_links(page):
        path = target.split("#", 1)[0]
        if path and not (page.parent / path).exists():
            broken.append(target)
    assert not broken, f"{page.relative_to(REPO)} links to files that do not exist: {broken}"


@pytest.mark.parametrize(
    "page",
    [README, *sorted(DOCS.rglob("*.md")), REPO / "config" / "README.md", REPO / "CHANGELOG.md"],
    ids=lambda p: str(p.relative_to(REPO)),
)
def test_pages_hold_no_control_characters(page):
    """A formula written through a string that was not raw loses its backslashes to control
    characters (``\\frac`` becomes a form feed and ``rac``), which the site shows as garbage."""
    bad = [
        # split at newlines only: str.splitlines() also splits at a form feed, hiding it
        (n, repr(line))
        for n, line in enumerate(page.read_text().split("\n"), 1)
        if re.search(r"[\x00-\x08\x0b-\x1f\x7f]", line)
    ]
    assert not bad, f"{page.relative_to(REPO)}: control characters on lines {bad[:5]}"


def test_readme_test_command_is_the_one_ci_runs():
    ci_commands = [line.strip() for line in CI_RUN.read_text().splitlines() if re.search(r"\bpytest\b", line)]
    ci_commands = [c for c in ci_commands if not c.startswith(("#", "echo"))]
    assert len(ci_commands) == 1, f".ci/run should run exactly one pytest command, found {ci_commands}"
    blocks = re.findall(r"^```bash\n(.*?)^```", README.read_text(), re.M | re.S)
    readme_lines = {line.strip() for block in blocks for line in block.splitlines()}
    assert ci_commands[0] in readme_lines, (
        f"the README's test command differs from the one .ci/run runs ({ci_commands[0]!r}): keep them word for word"
    )


#: the pages a user reads (the development pages describe a developer checkout)
USER_PAGES = [README, REPO / "config" / "README.md", *(p for p in sorted(DOCS.rglob("*.md")) if "development" not in p.parts)]


def test_no_user_page_names_the_development_only_folder():
    """A user's clone has no ../shared: the meshes the shipped configs and the documented commands
    use travel with the project (meshes/)."""
    named = [p.relative_to(REPO).as_posix() for p in USER_PAGES if "../shared" in p.read_text()]
    assert not named, f"user pages that name ../shared, which only a developer checkout has: {named}"
