"""What a sun costs a training step: the ``fast`` preset's step on the built-in vase (a ray cache
of ``--views`` views at 512 pixels with the default visibility, 512 directions per hit; CLIP
ViT-B-32 at 224 with random weights) with no sun and with ``--suns`` suns (``sun_samples``
directions each, a shadow ray per point and direction), taken in turns: ``--rounds`` rounds of
``--steps`` steps each way, the ratio the median of the rounds' ratios (the machine's speed drifts
between rounds, not within one). Also the shadow rays the suns traced per step (a learned sun
moves every step, so its points are traced again).

    python -m benchmarks.training.suns_step [--views 8] [--steps 4] [--rounds 3] [--suns 1] [--threads 2]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from benchmarks.common import make_optimizer, step_time, vit_b32_random


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--views", type=int, default=8)
    parser.add_argument("--steps", type=int, default=4)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--suns", type=int, default=1)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    import torch

    from stages.config.presets import PRESETS
    from stages.config.sections import NormalizeSettings, OptimizeSettings, RaycacheSettings
    from stages.geometry.meshio import save_ply
    from stages.geometry.normalization import normalize_mesh
    from stages.raycache import run as raycache_run

    torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as d:
        work = Path(d)
        t0 = time.perf_counter()
        save_ply(work / "mesh.ply", normalize_mesh("builtin:vase", NormalizeSettings()).mesh)
        raycache_run(
            work / "mesh.ply", work / "train.npz", work / "eval.npz", work / "rc.json", RaycacheSettings(views=args.views)
        )
        print(f"# built-in vase, {args.views} views at 512 with visibility: {time.perf_counter() - t0:.0f} s", flush=True)
        runs = {}
        for suns in (0, args.suns):
            s = OptimizeSettings(**{**PRESETS["fast"], "suns": suns})
            runs[suns] = make_optimizer(s, work / "train.npz", vit_b32_random(bf16=s.bf16, tower=s.clip_tower))
        times: dict[int, list[float]] = {k: [] for k in runs}
        for r in range(args.rounds):
            for suns, opt in runs.items():
                step, points = step_time(opt, args.steps)
                times[suns].append(step)
                print(f"round {r + 1}: suns {suns}: {step:.3f} s per step at {points:.0f} points", flush=True)
        sun_opt = runs[args.suns]
        rays = sum(v.shadows._sun.traces for v in sun_opt.views._views.values() if v.shadows and v.shadows._sun)
        steps = sun_opt.steps_taken
        ratios = [b / a for a, b in zip(times[0], times[args.suns], strict=True)]
        print(
            f"step_s={statistics.median(times[0]):.4g} step_suns_s={statistics.median(times[args.suns]):.4g} "
            f"ratio={statistics.median(ratios):.3f} suns={args.suns} sun_samples={sun_opt.settings.sun_samples} "
            f"points_traced_per_step={rays / max(steps, 1):.0f}"
        )


if __name__ == "__main__":
    main()
