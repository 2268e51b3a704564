"""What the gate costs (stages/core/safefiles.py): a read of a results folder's file through the
gate (the components below ``results/`` checked for links, opened without following one, the
handle checked, the size bounded) against a plain ``Path.read_bytes`` of the same file, side by
side in one run, at the depth of a cell's files (``results/<exp>/<mesh>/<prompt>/<variant>/<stage>/``).

    python -m benchmarks.workflow.gate [--files 2000] [--bytes 4096] [--repeats 5]

Prints microseconds per read of each, the gate's extra time per read and the ratio; the floor is
the plain read. Last line: ``gate_us``, ``plain_us``, ``extra_us``, ``ratio``.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from stages.core.safefiles import RECORD_LIMIT, read_bytes


def make_tree(root: Path, files: int, size: int) -> list[Path]:
    """``files`` records of ``size`` bytes, one per cell, as a results folder holds them."""
    paths = []
    for i in range(files):
        folder = root / "results" / "exp" / f"mesh{i % 50}" / f"prompt{i // 50}" / "base" / "optimize"
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / "meta.json"
        path.write_bytes(b"x" * size)
        paths.append(path)
    return paths


def per_read_us(read, paths: list[Path], repeats: int) -> float:
    """The median over ``repeats`` passes of microseconds per read of every path."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for p in paths:
            read(p)
        times.append((time.perf_counter() - t0) / len(paths) * 1e6)
    return statistics.median(times)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--files", type=int, default=2000)
    parser.add_argument("--bytes", type=int, default=4096)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as d:
        paths = make_tree(Path(d), args.files, args.bytes)
        per_read_us(Path.read_bytes, paths, 1)  # warm the file system's caches
        # in turns, so that a busy moment of the machine falls on both
        plain, gate = [], []
        for _ in range(3):
            plain.append(per_read_us(Path.read_bytes, paths, args.repeats))
            gate.append(per_read_us(lambda p: read_bytes(p, RECORD_LIMIT), paths, args.repeats))
    p, g = statistics.median(plain), statistics.median(gate)
    print(f"{args.files} files of {args.bytes} bytes, 6 folders deep under results/")
    print(f"{'read':<28}{'us per read':>12}")
    print(f"{'Path.read_bytes (the floor)':<28}{p:>12.1f}")
    print(f"{'the gate (read_bytes)':<28}{g:>12.1f}")
    print(f"gate_us={g:.1f} plain_us={p:.1f} extra_us={g - p:.1f} ratio={g / p:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
