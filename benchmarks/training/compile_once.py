"""A compiled run's first steps from an empty inductor cache: one compilation, or two.

An optimisation with the renderer compiled (``compile_shading: on``; ``--networks``: the networks
in its graph, ``compile_networks: on``) is set up in a fresh process with an empty inductor cache
(a temporary folder), as a machine's first compiled run is, and stepped ``--steps`` times: it
prints the setup's seconds (the ray cache read, CLIP loaded, the graph compiled on its first
pass), each step's seconds, and the graphs dynamo compiled at the setup and in each step. A step
that compiles again (its points on the other side of a size the first pass's code guards on)
takes as long as the setup's compilation; none should.

``--preset paper``: the paper's step (1 view from a 512x512 ray cache of 8 views, 1 global
image and 4 crops, width 256, 32 lobes); ``--preset fast``: the ``fast`` preset's settings
(no crops, width 64, 16 lobes). The mesh is ``../shared/meshes/person.obj`` when present (a tall,
thin figure: its views' points differ most from front to side), else the built-in vase; CLIP
ViT-B-32 at 224 with random weights (timing does not depend on them).

    python -m benchmarks.training.compile_once [--preset paper|fast] [--steps 8] [--networks] [--threads 2]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--preset", choices=("paper", "fast"), default="paper")
    parser.add_argument("--steps", type=int, default=8)
    parser.add_argument("--networks", action="store_true", help="compile_networks: on (one graph)")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as d:
        os.environ["TORCHINDUCTOR_CACHE_DIR"] = str(Path(d) / "inductor")  # empty: before torch is imported
        run(Path(d), args)


def run(tmp: Path, args: argparse.Namespace) -> None:
    import torch
    from torch._dynamo.utils import counters

    from benchmarks.common import build_cache, vit_b32_random
    from stages.config.presets import PRESETS
    from stages.config.sections import OptimizeSettings
    from stages.core.provenance import Timer
    from stages.geometry.raycache import RayCache
    from stages.training.optimizer import Optimizer

    torch.set_num_threads(args.threads)
    train, mesh = build_cache(tmp)
    preset = {k: v for k, v in PRESETS["fast"].items() if k != "iterations"} if args.preset == "fast" else {}
    networks = "on" if args.networks else "off"
    settings = OptimizeSettings(**{**preset, "iterations": 1500, "compile_shading": "on", "compile_networks": networks})
    guide = vit_b32_random(bf16=settings.bf16, tower=settings.clip_tower)
    print(f"# mesh {mesh}; preset {args.preset}; compile_networks {networks}; empty inductor cache", flush=True)
    graphs = counters["stats"]["unique_graphs"]
    t0 = time.perf_counter()
    opt = Optimizer(settings, RayCache(train), "a person made of wood", "cpu", guide=guide)
    setup = time.perf_counter() - t0
    setup_graphs, graphs = counters["stats"]["unique_graphs"] - graphs, counters["stats"]["unique_graphs"]
    print(f"setup {setup:.1f} s, {setup_graphs} graph(s) compiled; {opt.shading_path}", flush=True)
    print(f"# a step's typical points (the anchor view's global image): {opt.compiled.typical_points}", flush=True)
    steps, step_graphs = [], 0
    for i in range(args.steps):
        t0 = time.perf_counter()
        opt.step(Timer())
        steps.append(time.perf_counter() - t0)
        new, graphs = counters["stats"]["unique_graphs"] - graphs, counters["stats"]["unique_graphs"]
        step_graphs += new
        print(f"step {i}: {steps[-1]:.2f} s, {opt.points_last} points, {new} graph(s) compiled", flush=True)
    print(
        f"setup_s={setup:.1f} setup_graphs={setup_graphs} steps_s={sum(steps):.1f} step_graphs={step_graphs} "
        f"slowest_step_s={max(steps):.2f} preset={args.preset} networks={networks}"
    )


if __name__ == "__main__":
    main()
