"""How often ``normalize.up_axis: auto`` guesses right: every built-in mesh and (in a developer
checkout) every mesh of ``../shared/meshes``, all modelled +Y up, written with each of the six
up axes (rotated so that the named axis is up), guessed from an OBJ's point of view (no format
convention). Prints the guess per mesh and orientation, the margin of each guess, and the count
right, overall and for the files as they come (+Y up).

    python -m benchmarks.geometry.up_axis
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from benchmarks.common import SHARED_MESHES


def main() -> None:
    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args()
    from stages.geometry.meshio import TriMesh, load_mesh
    from stages.geometry.normalization import UP_AXIS_ROTATIONS, guess_up_axis
    from stages.geometry.shapes import BUILTIN_NAMES

    sources = [f"builtin:{n}" for n in BUILTIN_NAMES] + sorted(str(p) for p in SHARED_MESHES.glob("*.obj"))
    right = total = upright = 0
    t0 = time.perf_counter()
    for src in sources:
        mesh = load_mesh(src)
        cells = []
        for axis, rot in UP_AXIS_ROTATIONS.items():
            guess, ev = guess_up_axis(TriMesh(mesh.vertices @ rot, mesh.faces))  # rot turns it back to +y up
            ok = guess == axis
            right += ok
            total += 1
            upright += ok and axis == "+y"
            cells.append(f"{axis}->{guess}{'' if ok else ' WRONG'} ({ev['margin']})")
        print(f"{Path(src).name:16s} " + "  ".join(cells), flush=True)
    took = time.perf_counter() - t0
    print(f"right: {right} of {total} orientations; the files as they come (+y up): {upright} of {len(sources)}; {took:.1f} s")


if __name__ == "__main__":
    main()
