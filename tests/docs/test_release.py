"""The release metadata agree: pyproject.toml holds the version, and stages.__version__, the latest
release of CHANGELOG.md (Keep a Changelog 1.1.0), CITATION.cff (CFF 1.2.0) and the documentation
name the same one."""

from __future__ import annotations

import datetime
import importlib.metadata
import re
import tomllib

import pytest
import yaml
from conftest import REPO

import stages

PYPROJECT = REPO / "pyproject.toml"
CHANGELOG = REPO / "CHANGELOG.md"
CITATION = REPO / "CITATION.cff"
DOCS_CHANGELOG = REPO / "docs" / "changelog.md"
MKDOCS = REPO / "mkdocs.yml"

SEMVER = r"(0|[1-9]\d*)\.(0|[1-9]\d*)\.(0|[1-9]\d*)"
#: a release heading of Keep a Changelog: "## [1.2.3] - 2026-11-21"
RELEASE = re.compile(rf"^## \[(?P<version>{SEMVER})\] - (?P<date>\d{{4}}-\d{{2}}-\d{{2}})$")
#: the kinds of change Keep a Changelog 1.1.0 names, in its order
KINDS = ("Added", "Changed", "Deprecated", "Removed", "Fixed", "Security")
#: the keys CFF 1.2.0 requires, and the ones a release of this tool carries
CFF_REQUIRED = ("cff-version", "message", "title", "authors")
CFF_RELEASE = ("version", "date-released", "license")


def project_version() -> str:
    project = tomllib.loads(PYPROJECT.read_text())["project"]
    assert project["name"] == stages.DISTRIBUTION, "stages.DISTRIBUTION names another distribution than pyproject.toml"
    return project["version"]


def changelog_sections() -> list[tuple[str, str]]:
    """``(level-2 heading, its text)`` for each level-2 section of CHANGELOG.md."""
    text = CHANGELOG.read_text()
    parts = re.split(r"^(## .*)$", text, flags=re.M)
    return [(parts[i].strip(), parts[i + 1]) for i in range(1, len(parts), 2)]


def releases() -> list[tuple[str, datetime.date]]:
    out = []
    for heading, _ in changelog_sections():
        m = RELEASE.match(heading)
        if m:
            out.append((m["version"], datetime.date.fromisoformat(m["date"])))
    return out


def test_pyproject_version_is_semantic():
    assert re.fullmatch(SEMVER, project_version()), f"pyproject.toml's version {project_version()!r} is not x.y.z"


def test_stages_version_is_pyprojects():
    assert stages.__version__ == project_version(), (
        f"stages.__version__ is {stages.__version__!r} but pyproject.toml says {project_version()!r}: the installed "
        "metadata is stale; run bash scripts/setup.sh (or pip install -e .) again"
    )


def test_stages_version_falls_back_to_pyproject_without_metadata(monkeypatch):
    def not_installed(name):
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(importlib.metadata, "version", not_installed)
    stages._version.cache_clear()
    try:
        assert stages.__version__ == project_version()
    finally:
        stages._version.cache_clear()


def test_changelog_follows_keep_a_changelog():
    text = CHANGELOG.read_text()
    assert text.startswith("# Changelog\n"), "CHANGELOG.md starts with '# Changelog'"
    assert "https://keepachangelog.com/en/1.1.0/" in text and "https://semver.org/" in text
    sections = changelog_sections()
    assert sections and sections[0][0] == "## [Unreleased]", "the first section of CHANGELOG.md is '## [Unreleased]'"
    for heading, _ in sections[1:]:
        assert RELEASE.match(heading), f"CHANGELOG.md: {heading!r} is not a release heading '## [x.y.z] - YYYY-MM-DD'"
    for heading, body in sections:
        kinds = re.findall(r"^### (.*)$", body, flags=re.M)
        unknown = [k for k in kinds if k not in KINDS]
        assert not unknown, f"CHANGELOG.md, {heading}: {unknown} are not among {KINDS}"
        assert len(set(kinds)) == len(kinds), f"CHANGELOG.md, {heading}: a kind of change appears twice"
        assert kinds == sorted(kinds, key=KINDS.index), f"CHANGELOG.md, {heading}: kinds out of the order {KINDS}"
        for kind, entries in re.findall(r"^### ([^\n]*)\n(.*?)(?=^### |\Z)", body, flags=re.M | re.S):
            assert re.search(r"^- ", entries, flags=re.M), f"CHANGELOG.md, {heading}: '### {kind}' has no entry"
    found = releases()
    assert found, "CHANGELOG.md has no release"
    versions = [tuple(int(x) for x in v.split(".")) for v, _ in found]
    assert versions == sorted(versions, reverse=True) and len(set(versions)) == len(versions), (
        "CHANGELOG.md's releases go from the newest down, each once"
    )
    dates = [d for _, d in found]
    assert dates == sorted(dates, reverse=True), "CHANGELOG.md's release dates go from the newest down"


def test_latest_release_is_pyprojects_version():
    version, _ = releases()[0]
    assert version == project_version(), (
        f"CHANGELOG.md's latest release is {version} but pyproject.toml says {project_version()}: move the "
        "Unreleased entries under a new release heading when the version changes"
    )


@pytest.fixture(scope="module")
def citation() -> dict:
    data = yaml.safe_load(CITATION.read_text())
    assert isinstance(data, dict), "CITATION.cff is a YAML mapping"
    return data


def test_citation_has_the_cff_keys(citation):
    missing = [k for k in (*CFF_REQUIRED, *CFF_RELEASE) if k not in citation]
    assert not missing, f"CITATION.cff lacks {missing}"
    assert str(citation["cff-version"]) == "1.2.0"
    assert isinstance(citation["message"], str) and citation["message"].strip()
    assert isinstance(citation["title"], str) and citation["title"].strip()
    authors = citation["authors"]
    assert isinstance(authors, list) and authors, "CITATION.cff names at least one author"
    for author in authors:
        assert isinstance(author, dict) and (author.get("name") or author.get("family-names")), (
            f"CITATION.cff: an author is an entity with a name or a person with family-names, not {author!r}"
        )
    assert citation["license"] == tomllib.loads(PYPROJECT.read_text())["project"]["license"]["text"]


def test_citation_is_the_latest_release(citation):
    version, date = releases()[0]
    assert str(citation["version"]) == project_version() == version
    # CFF wants a date string; quoted in the file, so YAML does not turn it into a date
    assert isinstance(citation["date-released"], str), "CITATION.cff: quote date-released ('YYYY-MM-DD')"
    assert datetime.date.fromisoformat(citation["date-released"]) == date, (
        f"CITATION.cff's date-released {citation['date-released']} is not the date of release {version} in CHANGELOG.md"
    )


def test_citation_cites_the_tango_paper(citation):
    refs = citation.get("references") or []
    tango = [r for r in refs if r.get("title", "").startswith("TANGO: Text-driven Photorealistic and Robust 3D Stylization")]
    assert len(tango) == 1, "CITATION.cff's references hold the TANGO paper once"
    paper = tango[0]
    assert paper["type"] == "conference-paper" and paper["year"] == 2022
    assert [a["family-names"] for a in paper["authors"]] == ["Chen", "Chen", "Lei", "Zhang", "Jia"]
    for ref in refs:
        assert {"type", "title", "authors"} <= set(ref), f"a CFF reference needs type, title and authors: {ref}"


def test_docs_state_the_version():
    version = project_version()
    page = DOCS_CHANGELOG.read_text()
    stated = re.findall(rf"describes tango-stylize ({SEMVER})", page)
    assert [m[0] for m in stated] == [version], f"docs/changelog.md should say 'describes tango-stylize {version}'"
    assert '--8<-- "CHANGELOG.md:entries"' in page, "docs/changelog.md includes CHANGELOG.md's entries"
    footer = yaml.safe_load(MKDOCS.read_text())["copyright"]
    assert re.findall(SEMVER, footer) == [tuple(version.split("."))], f"mkdocs.yml's copyright should name {version}"
