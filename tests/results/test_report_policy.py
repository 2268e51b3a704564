"""The report's pages state a Content-Security-Policy before anything they load: only the report's
own files, and only the inline style sheet and scripts each page holds (by their SHA-256), in the
folder form and the one-file form; headless Chromium shows every page without a violation and
refuses a script or a remote image that is not the page's own."""

from __future__ import annotations

import base64
import hashlib
import json
from html.parser import HTMLParser
from pathlib import Path

import pytest
from conftest import browser_check, synthetic_results

from stages import html_report, report
from stages.config.sections import ReportSettings


@pytest.fixture(scope="module")
def pages(tmp_path_factory) -> dict:
    """A ten-cell synthetic report in both forms."""
    results = tmp_path_factory.mktemp("policy") / "results"
    cells = synthetic_results(results, meshes=2, prompts=1)
    report.run(results, cells, results / "report", json.loads((results / "decimated.json").read_text()))
    html_report.run(results, results / "report", cells)
    single = results.parent / "single"
    report.run(results, cells[:2], single)
    html_report.run(results, single, cells[:2], ReportSettings(single_file=True))
    folder = results / "report"
    return {
        "index": folder / "index.html",
        "cells": [folder.joinpath("cells", *c, "index.html") for c in cells],
        "single": single / "index.html",
    }


class Head(HTMLParser):
    """A page's elements in order (tag and attributes) and its inline scripts' and styles' text."""

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.tags, self.inline, self._open = [], {"script": [], "style": []}, None

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))
        self._open = tag if tag in ("script", "style") and "src" not in dict(attrs) else None
        if self._open:
            self.inline[tag].append("")

    def handle_data(self, data):
        if self._open:
            self.inline[self._open][-1] += data

    def handle_endtag(self, tag):
        self._open = None


def policy_of(page: Path) -> tuple[dict[str, list[str]], Head]:
    head = Head()
    head.feed(page.read_text())
    first, second = head.tags[2], head.tags[3]  # html, head, then the charset and the policy
    assert first == ("meta", {"charset": "utf-8"}) and second[0] == "meta", head.tags[:4]
    assert second[1]["http-equiv"] == "Content-Security-Policy"
    directives = {}
    for part in second[1]["content"].split(";"):
        name, *sources = part.split()
        directives[name] = sources
    return directives, head


def sha(text: str) -> str:
    return "'sha256-" + base64.b64encode(hashlib.sha256(text.encode()).digest()).decode() + "'"


def test_every_page_states_its_policy_first(pages):
    for page in [pages["index"], *pages["cells"], pages["single"]]:
        policy, head = policy_of(page)
        assert policy["default-src"] == ["'self'"] and policy["object-src"] == ["'none'"], page
        assert policy["base-uri"] == ["'none'"] and policy["form-action"] == ["'none'"]
        assert policy["img-src"] == ["'self'", "data:", "blob:"] and policy["connect-src"] == ["'self'", "data:", "blob:"]
        sources = [s for values in policy.values() for s in values]
        assert not any(s.startswith(("http", "*")) or s in ("'unsafe-inline'", "'unsafe-eval'") for s in sources), page
        # every inline script and style sheet allowed by its hash, and nothing else inline
        scripts = {s for s in policy["script-src"] if s.startswith("'sha256-")}
        assert scripts == {sha(code) for code in head.inline["script"]}, page
        assert len(head.inline["style"]) == 1 and sha(head.inline["style"][0]) in policy["style-src"]
        for tag, attrs in head.tags:  # the files it loads are its own: relative paths or data: URIs
            src = attrs.get("src")
            assert src is None or not src.split(":")[0].isalpha() or src.startswith("data:"), (page, tag, src)


def test_the_pages_show_in_chromium_without_a_violation(pages, tmp_path):
    r = browser_check("cell", pages["cells"][0], tmp_path / "cell.png")
    assert r["errors"] == [] and r["loaded"] == 1
    assert browser_check("index", pages["index"], tmp_path / "index.png")["errors"] == []
    r = browser_check("single", pages["single"], tmp_path / "single.png")
    assert r["errors"] == [] and r["loaded"] == 2


def test_chromium_refuses_what_is_not_the_pages_own(pages, tmp_path):
    """A script put into the page and a remote image are refused, and the page still works."""
    page = pages["index"].with_name("tampered.html")
    text = pages["index"].read_text()
    beacon = "<img src='https://evil.example/p.png?victim=1'><script>document.title = 'ran'</script>"
    page.write_text(text.replace("<h2>Summary</h2>", "<h2>Summary</h2>" + beacon, 1))
    r = browser_check("index", page, tmp_path / "tampered.png")
    assert "request failed: https://evil.example/p.png?victim=1 csp" in r["errors"]  # blocked before the network
    refused = [e for e in r["errors"] if "Content Security Policy" in e]
    assert any(e.startswith("Executing inline script violates") for e in refused), r["errors"]
    assert any(e.startswith("Loading the image 'https://evil.example/") for e in refused), r["errors"]
    assert r["rows"] == 10  # its own script still ran
