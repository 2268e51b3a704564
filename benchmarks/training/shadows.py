"""What shadows cost: the raycache stage's visibility (seconds, bytes) and the optimisation's step
with shadows against without, measured side by side on the same cache (issue 32's aim: at most
15% more per step at the paper's counts).

Per mesh: normalise, the raycache stage with ``visibility: on`` (``--directions``), then the real
training step (``Optimizer.step``) at the paper's counts (one view, a 224-pixel global image and
four local crops, CLIP ViT-B/32 with random weights, networks of width 256, 32 light lobes; or a
preset's) with ``shadows: false`` and ``shadows: true`` on that cache, alternating ``--repeats``
times; printed: the visibility's seconds and bytes per hit, seconds per step of each, and the ratio.

    python -m benchmarks.training.shadows                         # the knot, the paper's counts
    python -m benchmarks.training.shadows --meshes knot,vase --preset fast --directions 256,512
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

from benchmarks.common import make_optimizer, step_time, vit_b32_random


def step_seconds(train: Path, settings: dict, shadows: bool, steps: int) -> float:
    """Mean seconds of the real step (``benchmarks.common.step_time``, CLIP ViT-B/32 with random
    weights at 224 pixels) with ``optimize.shadows`` = ``shadows``."""
    from stages.config.sections import OptimizeSettings

    s = OptimizeSettings(**{**settings, "shadows": shadows})
    opt = make_optimizer(s, train, vit_b32_random(bf16=s.bf16, tower=s.clip_tower))
    assert (opt.views[0].shadows is not None) == shadows
    return step_time(opt, steps)[0]


def main() -> None:
    from stages import raycache
    from stages.config.presets import PRESETS
    from stages.config.sections import NormalizeSettings, RaycacheSettings
    from stages.geometry.meshio import save_ply
    from stages.geometry.normalization import normalize_mesh

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", default="knot", help="built-in meshes or paths, comma-separated")
    parser.add_argument("--preset", default="paper", help="paper (the schema's defaults) or a preset's name")
    parser.add_argument("--directions", default="512", help="visibility directions, comma-separated")
    parser.add_argument("--views", type=int, default=8, help="training views in the cache")
    parser.add_argument("--resolution", type=int, default=512, help="the cache's pixels (TANGO: 512)")
    parser.add_argument("--steps", type=int, default=6, help="timed steps per run (after a warm-up)")
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    import torch

    torch.set_num_threads(2)
    settings = {} if args.preset == "paper" else dict(PRESETS[args.preset])
    settings = {"crops": 4, "width": 256, "light_lobes": 32, **settings} if args.preset == "paper" else settings
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
                for _ in range(args.repeats):
                    for shadows in (False, True):
                        seconds[shadows].append(step_seconds(d / "train.npz", settings, shadows, args.steps))
                off, on = statistics.median(seconds[False]), statistics.median(seconds[True])
                runs = f"{[round(x, 3) for x in seconds[False]]} / {[round(x, 3) for x in seconds[True]]}"
                print(
                    f"  {args.preset}: {off:.3f} s per step without shadows, {on:.3f} s with (x{on / off:.2f}; runs {runs})",
                    flush=True,
                )


if __name__ == "__main__":
    main()
