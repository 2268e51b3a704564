"""TANGO stylization workflow: the importable stages behind the Snakemake rules.

Nothing runs at import time: no model loads, no device queries, no global state. ``stages.__version__``
is the version of the ``tango-stylize`` distribution; ``pyproject.toml`` is its one source (CHANGELOG.md,
CITATION.cff and the documentation name the same version, which tests/docs/test_release.py checks).
"""

from __future__ import annotations

import functools

#: the distribution that pyproject.toml's [project] table describes
DISTRIBUTION = "tango-stylize"


@functools.cache
def _version() -> str:
    """The installed distribution's version, else (a source tree that was never installed) the
    version in the repository's pyproject.toml, else ``"0+unknown"``."""
    import importlib.metadata

    try:
        return importlib.metadata.version(DISTRIBUTION)
    except importlib.metadata.PackageNotFoundError:
        pass
    import tomllib
    from pathlib import Path

    pyproject = Path(__file__).resolve().parent.parent / "pyproject.toml"
    try:
        project = tomllib.loads(pyproject.read_text())["project"]
    except (OSError, KeyError, tomllib.TOMLDecodeError):
        return "0+unknown"
    return str(project["version"]) if project.get("name") == DISTRIBUTION and "version" in project else "0+unknown"


def __getattr__(name: str) -> str:
    # read on first use (PEP 562), so that importing the package looks nothing up
    if name == "__version__":
        return _version()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
