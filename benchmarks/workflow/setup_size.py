"""The disk the set-up takes: ``.venv`` (torch, the project and its extras), ``.venv-blender``
(Blender as a module), ``node_modules`` (the viewer, the validator, the browser driver, MathJax),
and the largest pieces inside (torch, Mitsuba with Dr.Jit, the libLLVM wheel: the bytes their
RECORD files list); the folders counted in the file system's blocks, as ``du`` does. Run it with
the project's environment (``.venv/bin/python``).

    python -m benchmarks.workflow.setup_size            # print the sizes
    python -m benchmarks.workflow.setup_size --record   # and write the records the README quotes
"""

from __future__ import annotations

import argparse
from pathlib import Path

from benchmarks.records import disk_bytes, write_record

REPO = Path(__file__).resolve().parents[2]
#: the largest pieces of ``.venv``, by their distributions (sized from their RECORD files)
PIECES = {
    "torch": ("torch",),
    "Mitsuba 3 and Dr.Jit": ("mitsuba", "drjit"),
    "libLLVM (karellen-llvm-core)": ("karellen-llvm-core",),
}


def distribution_bytes(name: str) -> int:
    """The bytes of an installed distribution's files, as its RECORD lists them (0 when absent)."""
    import importlib.metadata

    try:
        files = importlib.metadata.distribution(name).files or []
    except importlib.metadata.PackageNotFoundError:
        return 0
    return sum(f.size or 0 for f in files)


def gb(n: int) -> str:
    return f"{n / 1e9:.1f} GB" if n >= 1e9 else f"{n / 1e9:.2f} GB"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--record", action="store_true", help="write the records the documentation quotes")
    args = parser.parse_args(argv)
    folders = {name: REPO / name for name in (".venv", ".venv-blender", "node_modules")}
    sizes = {name: disk_bytes(p) for name, p in folders.items() if p.is_dir()}
    if ".venv" not in sizes:
        parser.error(f"no {folders['.venv']}: run bash scripts/setup.sh first")
    pieces = {what: sum(map(distribution_bytes, dists)) for what, dists in PIECES.items()}
    for name, n in sizes.items():
        print(f"{name:<16}{gb(n):>10}")
    for what, n in pieces.items():
        print(f"  {what:<30}{gb(n):>10}")
    total = sum(sizes.values())
    print(f"{'all':<16}{gb(total):>10}")
    if args.record:
        parts = ", ".join(f"`{name}` {gb(n)}" for name, n in sizes.items())
        inside = "; in `.venv`: " + ", ".join(f"{what} {gb(n)}" for what, n in pieces.items() if n)
        command = "`bash scripts/setup.sh`, then `python -m benchmarks.workflow.setup_size --record`"
        what = "the set-up's disk (`bash scripts/setup.sh`, the CPU build of torch)"
        write_record("setup.disk", what, gb(total), command, "../getting-started.md#install", f"({parts}{inside})")
        if ".venv-blender" in sizes:
            what = "Blender as a module (`.venv-blender`)"
            write_record("setup.blender", what, gb(sizes[".venv-blender"]), command, "../getting-started.md#install")
        print("wrote the records; python -m benchmarks.records --write puts them into the pages")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
