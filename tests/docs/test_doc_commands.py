"""The commands the documentation shows work as written.

Every shell command of README.md, docs/**/*.md, config/**/*.md and of the comments of the YAML
files in config/ and profiles/ is collected (fenced ``bash``/``sh``/``console`` blocks, ``$ ``
lines of other fenced blocks, indented code lines, and inline code that starts like a command:
``python -m stages.``, ``python -m benchmarks.``, ``python scripts/``, ``snakemake``,
``bash scripts/``), split at ``&&``, ``;`` and pipes, with continuation lines joined, trailing
comments, ``source .venv/bin/activate`` and the ``.venv/bin/`` prefix dropped, and placeholders
(``path/to/chair.obj``, ``config/<name>.yaml``) replaced by real files. Each is then checked
cheaply, one test per command, named by page, line and command:

- ``snakemake ...``: a dry run (``--dry-run --quiet``) of the repository's workflow in a scratch
  working directory (``config/`` linked into it), so that ``--unlock`` or ``--delete-all-output``
  never touch the repository's own ``.snakemake/`` or ``results/``;
- ``python -m stages.quick ...``: its own ``--dry-run``, the config written to a scratch folder;
- ``python -m stages.config ...``: run (it only reads and prints); output lines that a ``$ ``
  block shows must be what it prints, in order;
- any other ``python -m stages.X``, ``python -m benchmarks.X.Y``, ``python scripts/X.py``: the
  documented arguments parsed by the module's own parser (captured when its ``main`` calls
  ``parse_args``, which then stops before any work): an unknown flag, a missing required
  argument or a bad choice fails;
- every repository file the command names (config files, meshes, scripts) exists;
- commands with elisions (``...``) and synopses (``[--preset fast|balanced|...]``): every option
  they name exists, takes a value exactly when shown with one, and a listed choice set equals
  the real one.

Identical dry runs are made once per test session, shared by the test workers. What cannot be
checked here is exempted in :data:`EXEMPT`, each with its reason; a command that is neither
checked nor exempted fails.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import hashlib
import io
import json
import os
import re
import runpy
import shlex
import shutil
import subprocess
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path
from unittest import mock

import pytest
from conftest import REPO, SHARED_MESHES, exclusive, snakemake_env

from stages.__main__ import COMMANDS, equivalent
from stages.config.presets import PRESETS
from stages.config.sections import MATERIALS
from stages.core.shipped import shipped_archive

PAGES = [
    REPO / "README.md",
    *sorted((REPO / "docs").rglob("*.md")),
    *sorted((REPO / "config").rglob("*.md")),
]
YAML_FILES = [*sorted((REPO / "config").rglob("*.yaml")), *sorted((REPO / "profiles").rglob("*.yaml"))]

#: commands that are not checked here, each with its reason (matched against the command as
#: normalised: the ``.venv/bin/`` prefix dropped, placeholders replaced)
EXEMPT: dict[str, str] = {
    r"^bash scripts/setup\.sh\b": "installs the environment (torch, Mitsuba, Blender, npm packages): minutes and the network",
    r"^python3 -m venv\b": "creates a virtual environment (a system set-up step)",
    r"^pip install\b": "installs packages (a system set-up step)",
    r"^bash scripts/slurm-cluster\.sh\b": "starts a one-node Slurm cluster as root (the Slurm tests run it)",
    r"^bash scripts/fetch_uv_meshes\.sh\b": "downloads Debian packages (tests/assets/test_kept_layout.py runs it)",
    r"^bash scripts/fetch_gltf_assets\.sh\b": "downloads Debian source tarballs (tests/assets/test_kept_layout.py runs it)",
    r"^python -m pytest\b": "the test suite itself",
    r"^mkdocs build\b": "tests/docs/test_docs.py::test_site_builds_strictly runs it",
    r"^mkdocs serve\b": "a server that runs until stopped",
    r"^python -m http\.server\b": "a server that runs until stopped",
    r"^(ruff|snakefmt|lint-imports)\b": "the style checks that .ci/run runs after the tests",
}
#: shell utilities around the project's commands (``| sort -u``, ``xargs rm``): not the project's
SHELL_UTILITIES = {"ls", "sort", "grep", "xargs", "rm", "cd", "cat", "head", "tail", "echo", "cp", "mkdir"}
#: placeholders in the documented commands and the real values the checks use instead
PLACEHOLDERS: list[tuple[str, str]] = [
    (r"path/to/chair\.obj", "builtin:vase"),  # any mesh: a built-in one is in every checkout
    (r"\bMESH\b", "builtin:vase"),
    (r'"PROMPT"', '"a vase made of wood"'),
    (r"config/quick/<name>\.yaml", "config/tiny.yaml"),  # what the quick command writes: an experiment config
    (r"config/<name>\.yaml", "config/tiny.yaml"),
    (r"(?<![\w/])(config/)?(OTHER|X)\.yaml", "config/tiny.yaml"),
    (r"results/<experiment>", "results/demo-offline"),
    (r"stages\.<\w+>", "stages.normalize"),  # any stage
    (r"benchmarks\.<topic>\.<name>", "benchmarks.workflow.gate"),  # any benchmark
    (r"--configfile C\b", "--configfile config/tiny.yaml"),
    (r"\bmesh/prompt/variant\b", "vase/wood/full"),
    (r"\bOVERLAY\b", "config/overlays/offline.yaml"),  # an overlay of the page's own: any overlay
    (r"(?<=synthetic_results\.py )OUT\b", "/tmp/synthetic-results"),
]
#: Snakemake options the dry runs leave out, so that commands that differ only in them share one
#: (their spelling and values are still checked by Snakemake's own parser): how the jobs run
#: (cores, printing, keep-going, resources, rerun triggers), and what a dry run cannot do or would
#: do instead of building the DAG, which is the stronger check
NOT_IN_DRY_RUN = {
    **dict.fromkeys(
        ["--cores", "-c", "--jobs", "-j", "-n", "--dry-run", "-p", "--printshellcmds", "--quiet", "-q"], "how jobs run"
    ),
    **dict.fromkeys(["--keep-going", "-k", "--resources", "--rerun-incomplete", "--rerun-triggers"], "how jobs run"),
    "--report": "the report is made from a finished run's results",
    "--use-conda": "conda is not part of the project's environment",
    "--unlock": "unlocks instead of building the DAG",
    "--lint": "lints instead of building the DAG (CI's style checks run it)",
    "--delete-all-output": "lists files instead of building the DAG",
}
#: options whose values a stage checks after parsing rather than with argparse ``choices``
CHECKED_CHOICES = {("stages.quick", "--preset"): sorted(PRESETS), ("stages.quick", "--image-guided"): list(MATERIALS)}
#: options whose values are files a command writes (not checked for existence)
OUTPUT_OPTIONS = {"--out", "--report", "--site-dir", "--mesh", "--transform", "--meta", "--config-dir"}
#: repository entries a path argument may start with (results/ is made by runs, not checked)
REPO_ENTRIES = {"config", "profiles", "benchmarks", "scripts", "stages", "workflow", "docs", "tests", "Snakefile"}
INPUT_SUFFIXES = (".yaml", ".yml", ".obj", ".ply", ".stl", ".off", ".glb", ".gltf", ".hdr", ".exr", ".py", ".sh", ".json")

COMMAND_START = re.compile(
    r"^(?:python -m (?:stages|benchmarks)\b|python (?:benchmarks|scripts)/|snakemake(?:\s|$)|bash scripts/|python -m http\.server"
    r"|mkdocs\s|tango\s)"
)
#: what may come before a command: a subshell, the environment's activation, ``time``, ``.venv/bin/``
COMMAND_PREFIX = re.compile(r"^(?:\(\s*|source \.venv/bin/activate\s*&&\s*|time\s+|\.venv/bin/)+")
INLINE = re.compile(r"(?<!`)`((?:[^`\n]|\n(?![ \t]*\n))+)`(?!`)")
FENCE = re.compile(r"^([ \t]*)(`{3,}|~{3,})[ \t]*([\w+-]*)")
SHELL_LANGS = {"bash", "sh", "shell", "console"}
SHELL_OPERATORS = {"&&", "||", ";", "|", "&", "(", ")"}


# ------------------------------------------------------------------------------------ collection
@dataclass(frozen=True)
class Shown:
    """A command line as a page shows it: where, its text, and the output lines shown under it."""

    where: str
    text: str
    output: tuple[str, ...] = ()


@dataclass(frozen=True)
class Case:
    """One command to check: ``argv`` is the command after normalisation (prefixes dropped,
    placeholders replaced); ``partial`` when it elides arguments (``...``) or is a synopsis."""

    where: str
    shown: str
    argv: tuple[str, ...]
    partial: bool = False
    synopsis: bool = False
    output: tuple[str, ...] = ()

    @property
    def command(self) -> str:
        return " ".join(self.argv)


def _line_of(text: str, index: int) -> int:
    return text.count("\n", 0, index) + 1


def _logical_lines(lines: list[tuple[int, str]]) -> list[tuple[int, str]]:
    """``(line number, text)`` with backslash continuations joined onto their first line."""
    out: list[tuple[int, str]] = []
    pending: tuple[int, str] | None = None
    for number, line in lines:
        if pending is not None:
            number, line = pending[0], pending[1] + " " + line.strip()
        if line.rstrip().endswith("\\"):
            pending = (number, line.rstrip()[:-1].rstrip())
            continue
        pending = None
        out.append((number, line))
    if pending is not None:
        out.append(pending)
    return out


def markdown_commands(path: Path) -> list[Shown]:
    """The commands of a Markdown page: its shell code blocks, ``$ `` lines (with the output shown
    under them) of its other code blocks, indented code lines and inline code that starts like a
    command."""
    rel = path.relative_to(REPO)
    lines = path.read_text().splitlines()
    found: list[Shown] = []
    prose = list(lines)  # the page with its fenced blocks blanked, for inline code
    i = 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        indent, marker, lang = m.group(1), m.group(2), m.group(3).lower()
        start, j = i, i + 1
        while j < len(lines) and not (lines[j].strip().startswith(marker) and set(lines[j].strip()) == {marker[0]}):
            j += 1
        body = [
            (n + 1, line[len(indent) :] if line.startswith(indent) else line.lstrip())
            for n, line in enumerate(lines[start + 1 : j], start + 1)
        ]
        for n in range(start, min(j + 1, len(lines))):
            prose[n] = ""
        i = j + 1
        prompt = lang == "console" or lang not in SHELL_LANGS
        entries: list[tuple[int, str, list[str]]] = []
        for number, line in _logical_lines(body):
            if line.startswith("$ "):
                entries.append((number, line[2:], []))
            elif not prompt:
                entries.append((number, line, []))
            elif entries:
                entries[-1][2].append(line)
        for number, line, output in entries:
            if line.strip() and not line.lstrip().startswith("#"):
                found.append(Shown(f"{rel}:{number}", line.strip(), tuple(output)))
    # indented code blocks: a line of 4+ spaces after a blank line that starts like a command
    for n, line in enumerate(prose):
        if line.startswith("    ") and n and not prose[n - 1].strip() and COMMAND_START.match(line.strip()):
            found.append(Shown(f"{rel}:{n + 1}", line.strip()))
    text = "\n".join(prose)
    for m in INLINE.finditer(text):
        code = " ".join(m.group(1).split())
        if COMMAND_START.match(COMMAND_PREFIX.sub("", code)) or _is_choice_fragment(code):
            found.append(Shown(f"{rel}:{_line_of(text, m.start())}", code))
    return sorted(found, key=lambda s: int(s.where.rsplit(":", 1)[1]))


def yaml_commands(path: Path) -> list[Shown]:
    """The commands quoted in the comments of a YAML file: inline code, and text from a command's
    start to the end of its line (or to the parenthesis that closes around it)."""
    rel = path.relative_to(REPO)
    found: list[Shown] = []
    blocks: list[list[tuple[int, str]]] = [[]]
    for number, line in enumerate(path.read_text().splitlines(), 1):
        m = re.match(r"^\s*#\s?(.*)$", line)
        if m:
            blocks[-1].append((number, m.group(1)))
        elif blocks[-1]:
            blocks.append([])
    for block in blocks:
        if not block:
            continue
        text = "\n".join(line for _, line in block)
        spans = []
        for m in INLINE.finditer(text):
            spans.append((m.start(), m.end()))
            code = " ".join(m.group(1).split())
            if COMMAND_START.match(COMMAND_PREFIX.sub("", code)):
                found.append(Shown(f"{rel}:{block[0][0] + _line_of(text, m.start()) - 1}", code))
        command = r"(?:python -m (?:stages|benchmarks)\.|python (?:benchmarks|scripts)/|snakemake |bash scripts/)"
        starts = re.finditer(command, text)
        for m in starts:
            if any(a <= m.start() < b for a, b in spans):
                continue
            rest = text[m.start() :].split("\n", 1)[0]
            depth = 0
            for k, ch in enumerate(rest):  # stop at a parenthesis that closes around the command
                depth += {"(": 1, ")": -1}.get(ch, 0)
                if depth < 0:
                    rest = rest[:k]
                    break
            found.append(Shown(f"{rel}:{block[0][0] + _line_of(text, m.start()) - 1}", rest.strip()))
    return found


def _is_choice_fragment(code: str) -> bool:
    """Inline code such as ``--stage bake|export``: options of the command shown before it."""
    return bool(re.match(r"^--[\w-]+[ =]\S*\w\|\w", code))


def _substitute(text: str) -> str:
    for pattern, value in PLACEHOLDERS:
        text = re.sub(pattern, value, text)
    return text


def _expand_for_loops(text: str) -> list[str]:
    """``for c in a b; do BODY; done REST`` as one ``BODY REST`` per value (other text as it is)."""
    m = re.match(r"^for (\w+) in ([^;]+); do (.*?); done(.*)$", text)
    if not m:
        return [text]
    name, values, body, rest = m.groups()
    return [re.sub(rf"\$\{{?{name}\}}?", value, body) + rest for value in values.split()]


def _is_synopsis(text: str) -> bool:
    return "[-" in text or bool(re.search(r"\w\|\w", text))


def segments(shown: Shown) -> list[Case]:
    """The commands of one shown line: split at ``&&``, ``;``, ``|`` and subshell parentheses,
    with environment assignments, ``time``, ``source .venv/bin/activate`` and ``.venv/bin/``
    dropped, trailing comments and redirections removed and placeholders replaced."""
    text = _substitute(shown.text)
    if _is_synopsis(text):
        # `[--configfile ...]`: any values; `[--overlay FILE]...`: repeatable
        text = re.sub(r"(--[\w-]+) \.\.\.", r"\1 VALUES", text)
        words = shlex.split(re.sub(r"\[|\]|\.\.\.", " ", text), comments=True)
        return [Case(shown.where, shown.text, tuple(_normalise(words)), partial=True, synopsis=True)]
    cases = []
    for line in _expand_for_loops(text):
        lexer = shlex.shlex(line, posix=True, punctuation_chars=True)
        lexer.whitespace_split = True
        tokens = list(lexer)
        parts: list[list[str]] = [[]]
        skip = False
        for token in tokens:
            if skip:
                skip = False
            elif token in SHELL_OPERATORS:
                parts.append([])
            elif token in (">", ">>", "<", "2>"):
                skip = True  # and the file name after it
            else:
                parts[-1].append(token)
        for part in parts:
            argv = _normalise(part)
            if not argv or argv[:2] == ["source", ".venv/bin/activate"] or argv[0] in SHELL_UTILITIES:
                continue
            # `python -m stages.optimize` alone names the program (its arguments elided)
            partial = "..." in argv or (argv[0] == "python" and len(argv) == len(program_words(argv)))
            cases.append(
                Case(shown.where, shown.text, tuple(a for a in argv if a != "..."), partial=partial, output=shown.output)
            )
    return cases


def _normalise(words: list[str]) -> list[str]:
    while words and re.match(r"^[A-Z_][A-Z0-9_]*=", words[0]):
        words = words[1:]  # environment assignments
    if words and words[0] == "time":
        words = words[1:]
    if words and words[0].startswith(".venv/bin/"):
        words = [words[0].removeprefix(".venv/bin/"), *words[1:]]
    if len(words) > 1 and words[0] == "tango" and words[1] in COMMANDS:
        words = equivalent(words[1:])  # the front command checked as the command it stands for
    return words


def collect() -> list[Case]:
    cases: list[Case] = []
    for path in PAGES:
        previous: Case | None = None
        for shown in markdown_commands(path):
            if _is_choice_fragment(shown.text):
                # options of the command shown just before, e.g. `--stage bake|export` after it
                assert previous is not None, f"{shown.where}: the choice list {shown.text!r} follows no command"
                words = shlex.split(_substitute(shown.text))
                cases.append(Case(shown.where, shown.text, (*program_words(previous.argv), *words), partial=True, synopsis=True))
                continue
            new = segments(shown)
            cases += new
            if new:
                previous = new[-1]
    for path in YAML_FILES:
        for shown in yaml_commands(path):
            cases += segments(shown)
    return cases


def program_words(argv: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """The words that name the program: ``python -m stages.x``, ``python scripts/x.py``, ``snakemake``."""
    if tuple(argv[:2]) == ("python", "-m"):
        return tuple(argv[:3])
    if argv and argv[0] == "python":
        return tuple(argv[:2])
    return tuple(argv[:1])


def exemption(case: Case) -> str | None:
    for pattern, reason in EXEMPT.items():
        if re.search(pattern, case.command):
            return reason
    return None


CASES = collect()
CHECKED = [c for c in CASES if exemption(c) is None]


# ---------------------------------------------------------------------------- parsers and runs
class _Captured(BaseException):
    """Raised by the patched ``parse_args``: carries the parser, stops the module before any work."""

    def __init__(self, parser: argparse.ArgumentParser):
        super().__init__()
        self.parser = parser


def target_of(argv: tuple[str, ...]) -> str:
    """``stages.x`` or ``benchmarks.x.y`` (a module), ``scripts/x.py`` (a script) or ``snakemake``."""
    if argv[0] == "snakemake":
        return "snakemake"
    assert argv[0] == "python" and len(argv) > 1, f"not a command this test knows how to check: {shlex.join(argv)}"
    if argv[1] == "-m":
        assert argv[2].startswith(("stages", "benchmarks")), f"python -m {argv[2]} is not one of the project's modules"
        return argv[2]
    return argv[1]


def arguments_of(argv: tuple[str, ...]) -> list[str]:
    return list(argv[len(program_words(argv)) :])


def source_of(target: str) -> Path:
    if target.endswith(".py"):
        return REPO / target
    base = REPO / Path(*target.split("."))
    return base / "__main__.py" if base.is_dir() else base.with_suffix(".py")


def parses_arguments(source: Path) -> bool:
    """Whether a module parses arguments (itself or in the ``main`` it imports, as
    ``stages/config/__main__.py`` does): one that does not is never run here, it would do its work."""
    text = source.read_text()
    if re.search(r"\bparse_args\(|\bstage_main\(", text):
        return True
    m = re.search(r"^from (\.+)(\w+) import main$", text, re.M)
    return bool(m) and parses_arguments(source.parents[len(m.group(1)) - 1] / f"{m.group(2)}.py")


@functools.cache
def parser_of(target: str) -> argparse.ArgumentParser | None:
    """The module's own argument parser, captured when its ``main`` calls ``parse_args`` (which
    then stops it); ``None`` for a script that takes no arguments (it is never run here)."""
    if target == "snakemake":
        from snakemake.cli import get_argument_parser

        return get_argument_parser()
    source = source_of(target)
    assert source.is_file(), f"{source.relative_to(REPO)} does not exist"
    if not parses_arguments(source):
        return None

    def capture(self, args=None, namespace=None):
        raise _Captured(self)

    saved_path, saved_argv, saved_modules = list(sys.path), sys.argv, set(sys.modules)
    try:
        sys.argv = [str(source)]
        with (
            warnings.catch_warnings(),  # runpy's note that the package imported the module first
            mock.patch.object(argparse.ArgumentParser, "parse_args", capture),
            contextlib.redirect_stdout(io.StringIO()),
            contextlib.redirect_stderr(io.StringIO()),
        ):
            warnings.simplefilter("ignore", RuntimeWarning)
            if target.endswith(".py"):
                runpy.run_path(str(source), run_name="__main__")
            else:
                runpy.run_module(target, run_name="__main__", alter_sys=True)
    except _Captured as captured:
        return captured.parser
    finally:
        sys.path[:], sys.argv = saved_path, saved_argv
        for name in set(sys.modules) - saved_modules:  # the benchmarks' and scripts' own modules
            file = getattr(sys.modules[name], "__file__", None) or ""
            if file.startswith((str(REPO / "benchmarks"), str(REPO / "scripts"), str(REPO / "tests"))):
                del sys.modules[name]
    raise AssertionError(f"{target} finished without parsing its arguments")


def parse_error(parser: argparse.ArgumentParser, args: list[str]) -> str | None:
    """argparse's complaint about ``args`` (an unknown or missing argument, a bad value), or None."""
    err = io.StringIO()
    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
            parser.parse_args(args)
    except SystemExit as exit_:
        if exit_.code not in (0, None):
            lines = err.getvalue().strip().splitlines()
            return " ".join(line for line in lines if "error:" in line) or "\n".join(lines) or f"exit status {exit_.code}"
    return None


def option_errors(target: str, parser: argparse.ArgumentParser, words: list[str], synopsis: bool) -> list[str]:
    """What is wrong with the options a partial command or a synopsis names: unknown options,
    a value shown for an option that takes none (or none for one that needs one), a choice
    list other than the real choices, a required option missing from a synopsis."""
    errors = []
    actions = parser._option_string_actions
    for k, word in enumerate(words):
        if not word.startswith("-") or word in ("-", "--"):
            continue
        name, _, inline = word.partition("=")
        action = actions.get(name)
        if action is None:
            errors.append(f"unknown option {name}")
            continue
        value = inline or (words[k + 1] if k + 1 < len(words) and not words[k + 1].startswith("-") else None)
        if not synopsis:
            continue
        takes = action.nargs != 0
        metavar_like = value is not None and (value.isupper() or "|" in value or value.startswith("config/"))
        if not takes and metavar_like:
            errors.append(f"{name} takes no value, shown with {value!r}")
        if takes and value is None and action.nargs in (None, 1, "+"):
            errors.append(f"{name} needs a value")
        if value and "|" in value:
            real = action.choices or CHECKED_CHOICES.get((target, name))
            if real is None:
                errors.append(f"{name} shows choices {value!r} but takes any value")
                continue
            shown, real = set(value.split("|")), set(real)
            # a list may leave out the default ("--stage bake|export|... for the others")
            if shown - real or real - shown - {action.default}:
                errors.append(f"{name} shows the choices {value!r}; the real ones are {'|'.join(sorted(real))}")
    if synopsis:
        for action in parser._actions:
            if action.required and action.option_strings and not set(action.option_strings) & set(words):
                errors.append(f"the required option {action.option_strings[-1]} is missing")
    return errors


def named_paths(argv: tuple[str, ...]) -> list[str]:
    """The repository files a command names as inputs: config files, meshes, scripts (not the
    files it writes, nor results/, which runs make)."""
    paths = []
    for before, word in zip(("", *argv), argv, strict=False):
        if before in OUTPUT_OPTIONS:
            continue
        value = word.split("=", 1)[1] if word.startswith("--") and "=" in word else word
        if not value or value.startswith(("-", "/")) or re.match(r"^[a-z_]+:", value) or " " in value:
            continue
        first = value.split("/")[0]
        if first in ("results", ".snakemake", ".cache"):
            continue  # made by runs (a fresh clone has none): e.g. --forcerun results/.../meta.json
        if first == "..":
            if value.startswith("../shared/meshes/") and not SHARED_MESHES.is_dir() and not os.environ.get("CI"):
                continue  # a developer checkout's meshes (CI runs beside ../shared: checked there)
            paths.append(value)
        elif first in REPO_ENTRIES or value.endswith(INPUT_SUFFIXES):
            paths.append(value)
    return paths


def scratch_folder(tmp_path_factory) -> Path:
    """A folder shared by the test workers of this session (identical runs are made once). Not a
    session fixture of this module: tests/conftest.py would then keep its slow tests together."""
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # the workers' folders are popen-gw<N> inside the session's
    path = root / "doc-commands"
    path.mkdir(exist_ok=True)
    return path


def shared_run(scratch: Path, key: str, cmd, timeout: int) -> dict:
    """``cmd(work)`` (a command line, given a fresh folder) run once per session and key, under a
    lock that the other workers wait for: ``{"returncode", "output"}``."""
    digest = hashlib.sha256(key.encode()).hexdigest()[:16]
    done = scratch / f"{digest}.json"
    with exclusive(scratch / f"{digest}.lock"):
        if not done.is_file():
            work = scratch / digest
            shutil.rmtree(work, ignore_errors=True)
            work.mkdir()
            env = {**snakemake_env(work), "TANGO_PLAN_CALIBRATE": "0"}  # the quick dry run's plan: no calibration
            try:
                proc = subprocess.run(cmd(work), cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout)
                result = {"returncode": proc.returncode, "output": proc.stdout + proc.stderr}
            except subprocess.TimeoutExpired:
                result = {"returncode": -1, "output": f"did not finish in {timeout} s"}
            tmp = done.with_suffix(".tmp")
            tmp.write_text(json.dumps(result))
            tmp.replace(done)
    return json.loads(done.read_text())


def snakemake_dry_run(scratch: Path, args: list[str]) -> dict:
    """A dry run of the workflow with ``args`` in a scratch working directory that sees the
    repository's ``config/`` (the configs' relative paths, such as an environment map, resolve)."""

    def cmd(work: Path) -> list[str]:
        (work / "config").symlink_to(REPO / "config")
        return [sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"), "--directory", str(work)] + [
            *args,
            "--dry-run",
            "--quiet",
        ]

    return shared_run(scratch, "snakemake " + shlex.join(args), cmd, timeout=180)


def without_options(parser: argparse.ArgumentParser, args: list[str], options) -> list[str]:
    """``args`` without ``options`` and their values (as many as the parser takes)."""
    out, k = [], 0
    while k < len(args):
        name = args[k].split("=", 1)[0]
        if name not in options:
            out.append(args[k])
            k += 1
            continue
        nargs = parser._option_string_actions[name].nargs
        k += 1
        if "=" in args[k - 1] or nargs == 0:
            continue
        values = 1 if nargs in (None, "?") else len(args) if nargs in ("*", "+") else nargs
        while values and k < len(args) and not args[k].startswith("-"):
            k, values = k + 1, values - 1
    return out


def shown_output_errors(shown: tuple[str, ...], printed: str) -> list[str]:
    """The output lines a page shows under a ``$ `` command that the command does not print, in
    that order (whitespace runs compared as one space; ``...`` skips any lines)."""
    printed_lines = [" ".join(line.split()) for line in printed.splitlines()]
    errors, at = [], 0
    for line in shown:
        line = " ".join(line.split())
        if not line or line == "...":
            continue
        try:
            at = printed_lines.index(line, at) + 1
        except ValueError:
            errors.append(f"the page shows {line!r}, which the command does not print (in that order)")
    return errors


# ----------------------------------------------------------------------------------------- checks
def check(case: Case, scratch: Path) -> None:
    """Everything that :mod:`this test <tests.docs.test_doc_commands>` checks of one command."""
    say = f"{case.where}: `{case.shown}`"
    # (a mesh that travels with the project compressed counts: the first reader unpacks it)
    missing = [p for p in named_paths(case.argv) if not (REPO / p).exists() and shipped_archive(REPO / p) is None]
    assert not missing, f"{say} names files that do not exist: {missing}"
    target = target_of(case.argv)
    args = arguments_of(case.argv)
    parser = parser_of(target)
    if parser is None:
        assert not args, f"{say}: {target} takes no arguments"
        return
    if case.partial:
        errors = option_errors(target, parser, args, case.synopsis)
        assert not errors, f"{say}: " + "; ".join(errors)
        return
    error = parse_error(parser, args)
    assert error is None, f"{say}: {error}"
    errors = option_errors(target, parser, args, synopsis=False)  # no abbreviations
    assert not errors, f"{say}: " + "; ".join(errors)
    if target == "snakemake":
        run = snakemake_dry_run(scratch, without_options(parser, args, NOT_IN_DRY_RUN))
        assert run["returncode"] == 0, f"{say}: its dry run failed:\n{run['output'][-3000:]}"
    elif target == "stages.quick":
        extra = [] if "--dry-run" in args else ["--dry-run"]

        def cmd(work: Path) -> list[str]:
            return [sys.executable, "-m", "stages.quick", *args, *extra, "--config-dir", str(work / "quick")]

        run = shared_run(scratch, "quick " + shlex.join(args), cmd, timeout=300)
        assert run["returncode"] == 0, f"{say}: its dry run failed:\n{run['output'][-3000:]}"
    elif target == "stages.config":  # it only reads the config and prints
        proc = subprocess.run([sys.executable, "-m", target, *args], cwd=REPO, capture_output=True, text=True, timeout=120)
        assert proc.returncode == 0, f"{say} failed:\n{proc.stdout}\n{proc.stderr}"
        errors = shown_output_errors(case.output, proc.stdout)
        assert not errors, f"{say}: " + "; ".join(errors)


def runs_a_process(case: Case) -> bool:
    """Whether checking ``case`` starts a dry run (a few seconds; shared by identical commands)."""
    return not case.partial and case.argv[0] == "snakemake" or case.argv[:3] == ("python", "-m", "stages.quick")


@pytest.mark.parametrize(
    "case",
    [pytest.param(c, marks=[pytest.mark.slow(minutes=0.1)] if runs_a_process(c) else []) for c in CHECKED],
    ids=[f"{c.where} {c.command[:80]}" for c in CHECKED],
)
def test_documented_command_works(case, tmp_path_factory):
    check(case, scratch_folder(tmp_path_factory))


def test_the_pages_show_commands():
    """The collection finds what the pages show (a broken collector would check nothing)."""
    assert len(CHECKED) > 100
    places = {c.where.split(":")[0] for c in CHECKED}
    assert {"README.md", "config/README.md", "config/demo-offline.yaml", "docs/getting-started.md"} <= places


def test_every_exemption_is_used():
    for pattern in EXEMPT:
        assert any(re.search(pattern, c.command) for c in CASES), f"the exemption {pattern!r} matches no documented command"


# ------------------------------------------------------------------------- the quoted error message
def test_the_quoted_configuration_error_is_what_the_workflow_prints(tmp_path):
    """docs/guide/configuration.md quotes the message of a misspelled mesh key: it is the line
    that Snakemake prints for such a config (its folder set to the one the page shows)."""
    page = REPO / "docs" / "guide" / "configuration.md"
    quoted = [line for line in page.read_text().splitlines() if line.startswith("invalid configuration:")]
    assert len(quoted) == 1, "configuration.md should quote one 'invalid configuration:' message"
    m = re.match(r"^invalid configuration: (\S+): unknown key\(s\) '(\w+)' at meshes -> (\w+);", quoted[0])
    assert m, f"the quoted message does not read as an unknown mesh key: {quoted[0]!r}"
    shown_path, key, mesh = m.groups()
    config = tmp_path / Path(shown_path).name
    config.write_text(json.dumps({"meshes": {mesh: {key: "meshes/vase.obj"}}, "prompts": {"wood": "a vase made of wood"}}))
    args = ["--snakefile", str(REPO / "Snakefile"), "--directory", str(tmp_path), "--configfile", str(config), "-n"]
    proc = subprocess.run(
        [sys.executable, "-m", "snakemake", *args],
        cwd=REPO,
        env=snakemake_env(tmp_path),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode != 0
    printed = [line.replace(str(config), shown_path) for line in (proc.stdout + proc.stderr).splitlines()]
    assert quoted[0] in printed, f"Snakemake prints:\n{proc.stdout}{proc.stderr}\nthe page quotes:\n{quoted[0]}"


# ----------------------------------------------------------------------------- the checks can fail
def test_the_collector_reads_blocks_continuations_chains_and_comments(tmp_path, monkeypatch):
    page = tmp_path / "page.md"
    page.write_text(
        "Run `python -m stages.plan --configfile\nconfig/tiny.yaml` first.\n\n"
        "```bash\n"
        "# a comment\n"
        "source .venv/bin/activate && snakemake --cores 2 \\\n    --configfile config/tiny.yaml   # trailing\n"
        '.venv/bin/python -m stages.quick path/to/chair.obj "a chair" --image-guided wood\n'
        "```\n\n"
        "```\n$ python -m stages.config --configfile config/tiny.yaml\nline one\n...\n```\n"
    )
    monkeypatch.setattr(sys.modules[__name__], "REPO", tmp_path)
    cases = [c for shown in markdown_commands(page) for c in segments(shown)]
    assert [(c.where, c.command) for c in cases] == [
        ("page.md:1", "python -m stages.plan --configfile config/tiny.yaml"),
        ("page.md:6", "snakemake --cores 2 --configfile config/tiny.yaml"),
        ("page.md:8", "python -m stages.quick builtin:vase a chair --image-guided wood"),
        ("page.md:12", "python -m stages.config --configfile config/tiny.yaml"),
    ]
    assert cases[-1].output == ("line one", "...")


@pytest.mark.parametrize(
    "text, complaint",
    [
        ("python -m stages.render.envmap --name studio", "--out"),  # a required option missing
        ("python -m stages.plan --configfile config/tiny.yaml --jsn", "unrecognized arguments"),
        ("python -m stages.plan --configfile config/nonexistent.yaml", "do not exist"),
        ("python -m benchmarks.training.fast_job --mesh vase --levers defaults --no-such-flag", "unrecognized arguments"),
        ("python benchmarks/fast_job.py --mesh vase", "do not exist"),  # the scripts before the package
        ("python -m stages.quick MESH [--image-guided wood|metal|plaster]", "the real ones are"),
        ("python -m stages.doctor [--json FILE]", "takes no value"),
        ("python -m stages.quick ... --imaged-guided", "unknown option"),
        ("python -m stages.plan --configfile config/tiny.yaml --js", "unknown option --js"),  # argparse's abbreviation
        ("snakemake --cores 2 --configfle config/tiny.yaml", "unrecognized arguments"),
        ("snakemake --cores 2 --configfile config/nonexistent.yaml", "do not exist"),
        ("snakemake --cores 2 --configfile config/tiny.yaml --until no_such_rule", "No rule to produce no_such_rule"),
    ],
)
def test_a_wrong_command_fails(text, complaint, tmp_path_factory):
    cases = segments(Shown("page.md:1", text))
    with pytest.raises(AssertionError, match=re.escape(complaint)):
        for case in cases:
            check(case, scratch_folder(tmp_path_factory))
