"""The networks compiled into the renderer's graph (``compile_networks: on``) against the renderer
compiled alone, on the real paper step, paired.

Two optimisations of the paper's step (1 view from a 512x512 ray cache, 1 global image and 4
crops, CLIP ViT-B-32 at 224 with random weights, width 256, 32 lobes), the same seed, so the same
views and crops step by step, one with ``compile_networks: off`` and one with ``on`` (both
``compile_shading: on``), are stepped in turns (the order alternating) in one process, so the
machine's drift from minute to minute falls on both alike. It prints each one's setup (the
compilation, read from inductor's cache where it can be), the mean seconds per step and the
median, lowest and highest of the paired ratios (the renderer alone over one graph: above 1, one
graph is faster), and the last losses (the same function: they agree to rounding).

``--precision bf16`` runs CLIP and the networks in bfloat16 where the CPU has it natively (the
defaults there); ``fp32`` both in float32. The mesh is ``../shared/meshes/person.obj`` when
present, else the built-in vase. On a CUDA machine ``--device cuda`` runs the same pairing there.

    python benchmarks/one_graph.py [--steps 20] [--precision bf16|fp32] [--threads 2] [--device cpu]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from optimize import build_cache, vit_b32_random  # noqa: E402

from stages.config.sections import OptimizeSettings  # noqa: E402
from stages.core.provenance import Timer  # noqa: E402
from stages.geometry.raycache import RayCache  # noqa: E402
from stages.training.optimizer import Optimizer  # noqa: E402

WAYS = {"renderer alone": "off", "one graph": "on"}


def paired(train: Path, steps: int, precision: str, device: str) -> dict[str, list[float]]:
    """Seconds of each step of each way, the ways stepped in turns."""
    fp32 = {"bf16": "off", "bf16_networks": "off"} if precision == "fp32" else {}
    opts = {}
    for name, networks in WAYS.items():
        s = OptimizeSettings(iterations=1500, compile_shading="on", compile_networks=networks, **fp32)
        guide = vit_b32_random(bf16=s.bf16, tower=s.clip_tower, device=device)
        t0 = time.perf_counter()
        opts[name] = Optimizer(s, RayCache(train), "a person made of wood", device, guide=guide)
        print(f"# {name}: setup {time.perf_counter() - t0:.1f} s; {opts[name].shading_path}", flush=True)
        opts[name].step(Timer())  # warm-up
    times = {name: [] for name in opts}
    for i in range(steps):
        for name in list(opts) if i % 2 == 0 else reversed(list(opts)):
            t0 = time.perf_counter()
            opts[name].step(Timer())
            if device == "cuda":
                torch.cuda.synchronize()
            times[name].append(time.perf_counter() - t0)
    for name, o in opts.items():
        times[name + " loss"] = [o.history[-1]["loss"]]
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--precision", choices=("bf16", "fp32"), default="bf16")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as d:
        train, mesh = build_cache(Path(d))
        print(f"# mesh {mesh}; {args.steps} paired steps; precision {args.precision}; device {args.device}", flush=True)
        times = paired(train, args.steps, args.precision, args.device)
    alone, one = times["renderer alone"], times["one graph"]
    ratios = [a / b for a, b in zip(alone, one, strict=True)]
    print(
        f"alone_s={statistics.mean(alone):.4f} one_graph_s={statistics.mean(one):.4f} "
        f"ratio_median={statistics.median(ratios):.3f} ratio_min={min(ratios):.3f} ratio_max={max(ratios):.3f} "
        f"loss_alone={times['renderer alone loss'][0]:.5f} loss_one_graph={times['one graph loss'][0]:.5f} "
        f"precision={args.precision} device={args.device}"
    )


if __name__ == "__main__":
    main()
