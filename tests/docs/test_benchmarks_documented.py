"""The benchmarks and the documentation agree: every benchmark module (``benchmarks/<topic>/<name>.py``)
is listed on the benchmarks page (docs/development/benchmarks.md) with its command, ``python -m
benchmarks.<topic>.<name>``, and every such command in the documentation, the changelog, the
configs' comments and the code's docstrings names a benchmark that exists (as does every
``benchmarks/...`` file they name); no command runs a benchmark as a script any more. The modules
are found by their files, never imported (tests/docs/test_doc_commands.py parses the documented
commands' arguments with each module's own parser)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from conftest import REPO

BENCHMARKS = REPO / "benchmarks"
PAGE = REPO / "docs" / "development" / "benchmarks.md"
#: the modules of benchmarks/ that are not benchmarks: the package's and topics' ``__init__`` and
#: the shared library
LIBRARY = {"common", "records"}
#: the library modules run as commands (the documentation's records), not benchmarks
TOOLS = {"benchmarks.records"}
#: text that names benchmarks: the documentation site and what it includes, the configs and
#: profiles (their comments show commands), the code and the tests (docstrings, messages)
TEXTS = sorted(
    {
        REPO / "README.md",
        REPO / "ARCHITECTURE.md",
        REPO / "CHANGELOG.md",
        *(REPO / "docs").rglob("*.md"),
        *(REPO / "config").rglob("*.md"),
        *(REPO / "config").rglob("*.yaml"),
        *(REPO / "profiles").rglob("*.yaml"),
        *(REPO / "stages").rglob("*.py"),
        *(REPO / "tests").rglob("*.py"),
        *(REPO / "scripts").rglob("*"),
        *BENCHMARKS.rglob("*.py"),
        *BENCHMARKS.rglob("*.md"),
        *BENCHMARKS.rglob("*.sh"),
        *BENCHMARKS.rglob("*.json"),
    }
    # this file, and the test of the commands, whose failing examples name a script that is gone
    - {Path(__file__), REPO / "tests" / "docs" / "test_doc_commands.py"}
)
#: ``python -m benchmarks.x.y`` (its words possibly split over a line, as prose wraps them)
COMMAND = re.compile(r"python\s+-m\s+(benchmarks(?:\.\w+)+)")
#: a file of benchmarks/ named by its path
FILE = re.compile(r"(?<![\w./{}-])benchmarks/[\w/.-]*\w")


def benchmark_modules() -> list[str]:
    """``benchmarks.<topic>.<name>`` for every benchmark file, found on disk."""
    found = []
    for path in sorted(BENCHMARKS.glob("*/*.py")):
        if path.stem != "__init__" and path.stem not in LIBRARY:
            found.append(".".join(path.relative_to(REPO).with_suffix("").parts))
    return found


def read(path: Path) -> str:
    try:
        return path.read_text()
    except (UnicodeDecodeError, IsADirectoryError):
        return ""


def test_the_benchmarks_are_a_package_of_topics():
    """A package with one folder per topic, each a package with a description; nothing but the
    shared library beside them (a benchmark left at the top would not be found below)."""
    assert (BENCHMARKS / "__init__.py").is_file()
    topics = [d for d in BENCHMARKS.iterdir() if d.is_dir() and d.name not in ("figures", "__pycache__")]
    assert len(topics) >= 5, topics
    for topic in topics:
        assert (topic / "__init__.py").read_text().strip().startswith('"""'), f"{topic.name}: a package with a description"
    top = {p.stem for p in BENCHMARKS.glob("*.py")} - {"__init__"}
    assert top == LIBRARY, f"only the shared library sits at the top of benchmarks/: {sorted(top - LIBRARY)}"
    assert len(benchmark_modules()) >= 30


@pytest.mark.parametrize("module", benchmark_modules())
def test_every_benchmark_is_listed_with_its_command(module):
    """Its row on the benchmarks page starts with its command; its own docstring shows it too."""
    start = f"| `python -m {module}"
    rows = [line for line in PAGE.read_text().splitlines() if line.startswith((f"{start} ", f"{start}`"))]
    assert len(rows) == 1, f"{PAGE.relative_to(REPO)} lists `python -m {module}` in {len(rows)} rows (one expected)"
    source = (REPO / Path(*module.split("."))).with_suffix(".py").read_text()
    assert f"python -m {module}" in source, f"{module}'s docstring shows how to run it"


def test_every_command_and_file_named_exists():
    """Every ``python -m benchmarks...`` names a benchmark module (or the package's library is
    not run), every ``benchmarks/...`` path exists, and no ``python benchmarks/x.py`` is left."""
    modules = set(benchmark_modules()) | TOOLS
    wrong = []
    for path in TEXTS:
        text = read(path)
        where = path.relative_to(REPO)
        for m in COMMAND.finditer(text):
            if m[1] not in modules:
                wrong.append(f"{where}: `python -m {m[1]}` is not a benchmark")
        for m in FILE.finditer(text):
            name = m[0].rstrip(".")
            if not (REPO / name).exists() and "<" not in name and "*" not in name:
                wrong.append(f"{where}: {name} does not exist")
        for m in re.finditer(r"python\s+benchmarks/\S+", text):
            wrong.append(f"{where}: `{m[0]}` runs a benchmark as a script (python -m benchmarks.<topic>.<name>)")
    assert not wrong, "\n".join(wrong)


def test_the_collector_finds_what_it_should():
    """The patterns above on hand-made text (a broken pattern would pass everything)."""
    text = "run `python -m\nbenchmarks.training.optimize --steps 2` or benchmarks/render/precision.py's table"
    assert [m[1] for m in COMMAND.finditer(text)] == ["benchmarks.training.optimize"]
    assert [m[0] for m in FILE.finditer(text)] == ["benchmarks/render/precision.py"]
    assert not FILE.search("results/x/benchmarks/optimize.tsv {CELL}/benchmarks/x.tsv")
