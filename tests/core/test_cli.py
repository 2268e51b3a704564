"""Every command's ``--help`` is whole plain text with a help for each option; ``--version``;
``--configfile`` as Snakemake takes it; malformed ``--settings`` one line, no traceback."""

from __future__ import annotations

import argparse
import importlib
import json
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import REPO

from stages.core.cli import plain_text

#: every ``python -m`` command of the library that parses arguments through stage_main
COMMANDS = sorted(p.stem for p in (REPO / "stages").glob("*.py") if not p.stem.startswith("__")) + ["config"]
#: what reStructuredText leaves in text that was not converted
REST = ("``", ":func:", ":mod:", ":data:", ":class:", ":meth:", ":ref:", "`")


class _Parsed(Exception):
    pass


def parser_of(command: str, monkeypatch) -> argparse.ArgumentParser:
    """The parser ``python -m stages.<command>`` builds, taken where it parses (nothing runs)."""
    seen = {}

    def capture(self, args=None, namespace=None):
        seen["parser"] = self
        raise _Parsed

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", capture)
    module = importlib.import_module("stages.config.workflow" if command == "config" else f"stages.{command}")
    with pytest.raises(_Parsed):
        module.main([])
    return seen["parser"]


@pytest.mark.parametrize("command", COMMANDS)
def test_every_option_has_help_and_the_description_is_plain_and_whole(command, monkeypatch):
    parser = parser_of(command, monkeypatch)
    missing = [a.option_strings or [a.dest] for a in parser._actions if not a.help]
    assert not missing, f"stages.{command}: options without help: {missing}"
    text = parser.format_help()
    assert not [r for r in REST if r in text], text
    description = parser.description
    assert description.endswith((".", ")")) and len(description) > 30, description  # a whole sentence, not a cut line
    assert any(a.option_strings == ["--version"] for a in parser._actions)


def test_plain_text_reduces_roles_and_literals_and_keeps_the_whole_paragraph():
    doc = """export: one ``model.glb`` and :mod:`~stages.assets.formats`, :func:`stages.x.y` and
    ``DistantLight`` s, *emphasis* and **strong** over two lines.

    A second paragraph that help leaves out."""
    assert plain_text(doc) == (
        "export: one model.glb and formats, stages.x.y and DistantLights, emphasis and strong over two lines."
    )
    assert plain_text("a :ref:`page <target>` with 2 * 3 * 4") == "a page with 2 * 3 * 4"


def run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", *args], cwd=REPO, capture_output=True, text=True, timeout=120)


def test_version_and_a_malformed_settings_json(tmp_path):
    from stages import __version__

    proc = run("stages.export", "--version")
    assert proc.returncode == 0 and proc.stdout.strip() == f"tango-stylize {__version__}"
    base = ("stages.normalize", "--input", "builtin:vase", "--mesh", str(tmp_path / "m.ply"))
    base += ("--transform", str(tmp_path / "t.json"), "--meta", str(tmp_path / "meta.json"))
    for bad, said in (("{steps: 1}", "is not valid JSON"), ("[1, 2]", "must be a JSON object")):
        proc = run(*base, "--settings", bad)
        assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
        (line,) = proc.stderr.strip().splitlines()
        assert "--settings for 'normalize'" in line and said in line
    assert not list(tmp_path.iterdir())


def test_configfile_after_one_flag_or_repeated_as_snakemake_takes_it(tmp_path):
    """``--configfile a b`` and ``--configfile a --configfile b`` read the same two files (later
    wins), in the config command, the doctor and the plan."""
    base, overlay = tmp_path / "base.yaml", tmp_path / "overlay.yaml"
    base.write_text("meshes: {vase: {builtin: vase}}\nprompts: {wood: {text: a wooden vase}}\n")
    overlay.write_text("experiment: overlaid\n")
    for form in (("--configfile", str(base), str(overlay)), ("--configfile", str(base), "--configfile", str(overlay))):
        proc = run("stages.config", *form, "--check")
        assert proc.returncode == 0 and "experiment 'overlaid'" in proc.stdout, proc.stderr[-2000:]
        assert "1 mesh x 1 prompt x 1 variant = 1 cell" in proc.stdout
        proc = run("stages.plan", *form, "--no-calibrate", "--results", str(tmp_path / "r"), "--json")
        assert proc.returncode == 0 and json.loads(proc.stdout)["experiment"] == "overlaid", proc.stderr[-2000:]
        proc = run("stages.doctor", *form, "--offline")
        assert f"what a run of {base} + {overlay} needs" in proc.stdout, proc.stdout + proc.stderr[-2000:]
    proc = run("stages.config", "--check")  # none given: config/config.yaml, as before
    assert proc.returncode == 0 and "config/config.yaml" in proc.stdout
    assert Path(REPO, "config", "config.yaml").is_file()


def test_the_tango_command_fronts_the_everyday_commands(tmp_path):
    """``tango`` (pyproject's console script, also ``python -m stages``): its commands, each the
    module's own arguments; an unknown one is one line."""
    from stages import __version__
    from stages.__main__ import COMMANDS

    tango = Path(sys.executable).with_name("tango")
    assert tango.is_file(), f"{tango} missing: pip install -e . (bash scripts/setup.sh) installs the console command"

    def front(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([str(tango), *args], cwd=REPO, capture_output=True, text=True, timeout=300)

    proc = front("--help")
    assert proc.returncode == 0 and all(f"  {name} " in proc.stdout for name in COMMANDS)
    assert front("--version").stdout.strip() == f"tango-stylize {__version__}"
    proc = front("check", "config/demo.yaml")
    assert proc.returncode == 0 and "config/demo.yaml: a valid config of 2 mesh/prompt pairs x 1 variant" in proc.stdout
    proc = front("plan", "--configfile", "config/demo.yaml", "--no-calibrate", "--results", str(tmp_path), "--json")
    assert proc.returncode == 0 and json.loads(proc.stdout)["experiment"] == "demo"
    proc = front("quick", "--help")
    assert proc.returncode == 0 and "--uv-max-overlap" in proc.stdout
    proc = front("demo", "--dry-run", "--directory", str(tmp_path))
    assert proc.returncode == 0 and "This was a dry-run" in proc.stdout + proc.stderr, proc.stderr[-2000:]
    proc = front("stylise")
    assert proc.returncode == 2 and proc.stderr.strip() == (
        "tango: unknown command 'stylise': use one of demo, quick, doctor, plan, check (tango --help)"
    )


def test_third_party_info_lines_stay_out_of_the_console(tmp_path):
    """A quad mesh makes trimesh log "triangulating faces" at INFO: the console shows the tool's
    own lines only (with -v, everything)."""
    import logging

    from stages.core.cli import THIRD_PARTY_LOGGERS, setup_logging

    quad = tmp_path / "quad.obj"
    corners = "".join(f"v {x} {y} {z}\n" for x in (0, 1) for y in (0, 1) for z in (0, 1))
    quad.write_text(corners + "f 1 3 4 2\nf 5 6 8 7\nf 1 2 6 5\nf 3 7 8 4\nf 1 5 7 3\nf 2 4 8 6\n")  # a cube of quads
    base = ("stages.normalize", "--input", str(quad), "--mesh", str(tmp_path / "m.ply"))
    base += ("--transform", str(tmp_path / "t.json"), "--meta", str(tmp_path / "meta.json"))
    proc = run(*base)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "triangulating" not in proc.stderr and "8 vertices, 12 faces" in proc.stderr  # its own line, not the library's
    proc = run(*base, "-v")
    assert "triangulating faces" in proc.stderr  # the library did log it: hidden above, not absent
    try:
        setup_logging(False)
        assert all(not logging.getLogger(n).isEnabledFor(logging.INFO) for n in THIRD_PARTY_LOGGERS)
        assert logging.getLogger("stages.x").isEnabledFor(logging.INFO)
    finally:
        for name in THIRD_PARTY_LOGGERS:
            logging.getLogger(name).setLevel(logging.NOTSET)
