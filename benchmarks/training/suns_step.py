"""What a sun and a bounce cost a training step: the ``fast`` preset's step on a built-in mesh
(``--mesh``, the vase by default; a ray cache of ``--views`` views at 512 pixels with the default
visibility, 512 directions per hit; CLIP ViT-B-32 at 224 with random weights) with direct light
alone, with ``--suns`` suns (``sun_samples`` directions each, a shadow ray per point and direction)
and, with ``--bounces``, with one bounce (``bounce_samples`` first hits per point, traced once),
taken in turns: ``--rounds`` rounds of ``--steps`` steps each way, each ratio the median of the
rounds' ratios (the machine's speed drifts between rounds, not within one). Also the shadow rays
the suns traced per step (a learned sun moves every step, so its points are traced again) and a
refresh of the bounce's table, timed apart and spread over ``bounce_every`` steps.

    python -m benchmarks.training.suns_step [--views 8] [--steps 4] [--rounds 3] [--suns 1] [--threads 2]
    python -m benchmarks.training.suns_step --mesh builtin:knot --bounces
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
    parser.add_argument("--mesh", default="builtin:vase")
    parser.add_argument("--bounces", action="store_true", help="also measure one bounce (optimize.bounces: 1)")
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
        save_ply(work / "mesh.ply", normalize_mesh(args.mesh, NormalizeSettings()).mesh)
        raycache_run(
            work / "mesh.ply", work / "train.npz", work / "eval.npz", work / "rc.json", RaycacheSettings(views=args.views)
        )
        print(f"# {args.mesh}, {args.views} views at 512 with visibility: {time.perf_counter() - t0:.0f} s", flush=True)
        configs = {"direct": {}, "suns": {"suns": args.suns}, **({"bounce": {"bounces": 1}} if args.bounces else {})}
        runs = {}
        for name, extra in configs.items():
            s = OptimizeSettings(**{**PRESETS["fast"], **extra})
            runs[name] = make_optimizer(s, work / "train.npz", vit_b32_random(bf16=s.bf16, tower=s.clip_tower))
        times: dict[str, list[float]] = {k: [] for k in runs}
        for r in range(args.rounds):
            for name, opt in runs.items():
                step, points = step_time(opt, args.steps)
                times[name].append(step)
                print(f"round {r + 1}: {name}: {step:.3f} s per step at {points:.0f} points", flush=True)
        sun_opt = runs["suns"]
        rays = sum(v.shadows._sun.traces for v in sun_opt.views._views.values() if v.shadows and v.shadows._sun)
        steps = sun_opt.steps_taken

        def ratio(name: str) -> float:
            return statistics.median(b / a for a, b in zip(times["direct"], times[name], strict=True))

        line = (
            f"step_s={statistics.median(times['direct']):.4g} step_suns_s={statistics.median(times['suns']):.4g} "
            f"ratio={ratio('suns'):.3f} suns={args.suns} sun_samples={sun_opt.settings.sun_samples} "
            f"points_traced_per_step={rays / max(steps, 1):.0f}"
        )
        if args.bounces:
            bounce = runs["bounce"]
            refresh = []
            for _ in range(3):
                t0 = time.perf_counter()
                bounce.refresh_bounce()
                refresh.append(time.perf_counter() - t0)
            every = bounce.settings.bounce_every
            line += (
                f" step_bounce_s={statistics.median(times['bounce']):.4g} ratio_bounce={ratio('bounce'):.3f}"
                f" refresh_s={statistics.median(refresh):.3g} refresh_per_step_s={statistics.median(refresh) / every:.3g}"
                f" face_sides={len(bounce.senders)} senders_visibility_s={bounce.senders.seconds:.3g}"
            )
        print(line)


if __name__ == "__main__":
    main()
