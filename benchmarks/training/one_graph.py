"""The networks compiled into the renderer's graph (``compile_networks: on``) against the renderer
compiled alone, or that graph with static shapes (``compile_static: on``) against it with free
ones, on the real paper step, paired.

Two optimisations of the paper's step (1 view from a 512x512 ray cache, 1 global image and 4
crops, CLIP ViT-B-32 at 224 with random weights, width 256, 32 lobes), the same seed, so the same
views and crops step by step, compiled two ways (``--ways``, of :data:`WAYS`: by default
``compile_networks: off`` and ``on``, both ``compile_shading: on``), are stepped in turns (the
order alternating) in one process, so the machine's drift from minute to minute falls on both
alike. It prints each one's setup (the compilation, read from inductor's cache where it can be),
the mean seconds per step and the median, lowest and highest of the paired ratios (the first way
over the second: above 1, the second is faster), and the last losses (the same function: they
agree to rounding).

``--precision bf16`` runs CLIP and the networks in bfloat16 where the CPU has it natively (the
defaults there); ``fp32`` both in float32. The mesh is ``../shared/meshes/person.obj`` when
present, else the built-in vase. On a CUDA machine ``--device cuda`` runs the same pairing there.

    python -m benchmarks.training.one_graph [--steps 20] [--precision bf16|fp32] [--threads 2] [--device cpu]
        [--ways "renderer alone,one graph" | --ways "one graph,static shapes"]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import torch

from benchmarks.common import build_cache, paired_ratios, vit_b32_random
from stages.config.sections import OptimizeSettings
from stages.core.provenance import Timer
from stages.geometry.raycache import RayCache
from stages.training.optimizer import Optimizer

#: the ways compared, by name: the key of their figures and their settings (beside ``compile_shading: on``)
WAYS = {
    "renderer alone": ("alone", {"compile_networks": "off"}),
    "one graph": ("one_graph", {"compile_networks": "on"}),
    "static shapes": ("static", {"compile_networks": "on", "compile_static": "on"}),
}


def paired(train: Path, steps: int, precision: str, device: str, ways: list[str]) -> dict[str, list[float]]:
    """Seconds of each step of each of the two ``ways``, stepped in turns."""
    fp32 = {"bf16": "off", "bf16_networks": "off"} if precision == "fp32" else {}
    opts = {}
    for name in ways:
        s = OptimizeSettings(iterations=1500, compile_shading="on", **WAYS[name][1], **fp32)
        guide = vit_b32_random(bf16=s.bf16, tower=s.clip_tower, device=device)
        t0 = time.perf_counter()
        opts[name] = Optimizer(s, RayCache(train), "a person made of wood", device, guide=guide)
        padded = opts[name].compiled.static_points
        pad = f"; points padded to {padded} (the largest view's)" if padded else ""
        print(f"# {name}: setup {time.perf_counter() - t0:.1f} s; {opts[name].shading_path}{pad}", flush=True)
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
        points = [row["points"] for row in o.history[1:]]
        print(f"# {name}: {statistics.mean(points):.0f} points per step ({min(points)}-{max(points)})", flush=True)
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--precision", choices=("bf16", "fp32"), default="bf16")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--ways", default="renderer alone,one graph", help=f"two of: {', '.join(WAYS)}")
    args = parser.parse_args()
    ways = [w.strip() for w in args.ways.split(",")]
    if len(ways) != 2 or any(w not in WAYS for w in ways):
        raise SystemExit(f"--ways: two of {', '.join(WAYS)}, comma-separated; got {args.ways!r}")
    torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as d:
        train, mesh = build_cache(Path(d))
        print(f"# mesh {mesh}; {args.steps} paired steps; precision {args.precision}; device {args.device}", flush=True)
        times = paired(train, args.steps, args.precision, args.device, ways)
    (first, a), (second, b) = ((WAYS[w][0], times[w]) for w in ways)
    ratios = paired_ratios(a, b)
    print(
        f"{first}_s={statistics.mean(a):.4f} {second}_s={statistics.mean(b):.4f} "
        f"ratio_median={statistics.median(ratios):.3f} ratio_min={min(ratios):.3f} ratio_max={max(ratios):.3f} "
        f"loss_{first}={times[ways[0] + ' loss'][0]:.5f} loss_{second}={times[ways[1] + ' loss'][0]:.5f} "
        f"precision={args.precision} device={args.device}"
    )


if __name__ == "__main__":
    main()
