"""What shadows cost: the raycache stage's visibility (seconds, bytes) and the optimisation's step
with shadows against without, measured side by side on the same cache (issue 32's aim: at most
15% more per step at the paper's counts).

Per mesh: normalise, the raycache stage with ``visibility: on`` (``--directions``), then the
optimize stage twice on that cache, ``shadows: false`` and ``shadows: true``, alternating
``--repeats`` times, with the tiny test CLIP (the step's guidance cost is CLIP's, the same in both:
see ``benchmarks/optimize.py`` for the real tower) and the preset's settings; printed: the
visibility's seconds and bytes per hit, each run's seconds per iteration, and the ratio.

    python benchmarks/shadows.py                                  # the knot, the paper's counts
    python benchmarks/shadows.py --meshes knot,vase --preset fast --directions 256,512
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main() -> None:
    from stages import optimize, raycache
    from stages.config.presets import PRESETS
    from stages.config.sections import NormalizeSettings, OptimizeSettings, RaycacheSettings
    from stages.geometry.meshio import save_ply
    from stages.geometry.normalization import normalize_mesh

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", default="knot", help="built-in meshes or paths, comma-separated")
    parser.add_argument("--preset", default="paper", help="paper (the schema's defaults) or a preset's name")
    parser.add_argument("--directions", default="512", help="visibility directions, comma-separated")
    parser.add_argument("--views", type=int, default=16, help="training views in the cache")
    parser.add_argument("--resolution", type=int, default=512, help="the cache's pixels (TANGO: 512)")
    parser.add_argument("--iterations", type=int, default=12)
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    preset = {} if args.preset == "paper" else dict(PRESETS[args.preset])
    base = {**preset, "iterations": args.iterations, "clip_tiny_test": True, "image_size": 64, "checkpoint_every": 10**6}
    for name in args.meshes.split(","):
        source = f"builtin:{name}" if "/" not in name and "." not in name else name
        with tempfile.TemporaryDirectory() as tmp:
            d = Path(tmp)
            save_ply(d / "mesh.ply", normalize_mesh(source, NormalizeSettings()).mesh)
            for directions in (int(x) for x in args.directions.split(",")):
                rc = RaycacheSettings(
                    views=args.views, resolution=args.resolution, visibility="on", visibility_directions=directions
                )
                t0 = time.perf_counter()
                raycache.run(d / "mesh.ply", d / "train.npz", d / "eval.npz", d / "rc.json", rc)
                meta = json.loads((d / "rc.json").read_text())
                hits = meta["stats"]["train"]["hits"]
                per_hit = meta["stats"]["train"]["visibility_bytes"] / hits
                print(
                    f"{name}: {args.views} views at {args.resolution} px, {hits} hits; visibility of {directions} "
                    f"directions in {meta['timings_s']['visibility']:.1f} s ({per_hit:.0f} bytes per hit; "
                    f"the raycache stage {time.perf_counter() - t0:.1f} s in all)",
                    flush=True,
                )
                seconds = {False: [], True: []}
                for r in range(args.repeats):
                    for shadows in (False, True):
                        s = OptimizeSettings(**{**base, "shadows": shadows})
                        out = d / f"opt-{directions}-{shadows}-{r}"
                        optimize.run(d / "train.npz", d / "eval.npz", f"a {name} made of wood", out, s, "cpu")
                        seconds[shadows].append(json.loads((out / "meta.json").read_text())["seconds_per_iteration"])
                off, on = statistics.median(seconds[False]), statistics.median(seconds[True])
                print(
                    f"  {args.preset}: {off:.3f} s per iteration without shadows, {on:.3f} s with "
                    f"(x{on / off:.2f}; runs {seconds[False]} / {seconds[True]})",
                    flush=True,
                )


if __name__ == "__main__":
    main()
