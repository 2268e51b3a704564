"""Kernel launches per paper step, counted on the CPU: what a GPU step pays for.

On a GPU the paper's step is bound by kernel launches, not arithmetic (``benchmarks/gpu.py``: the
GPU busy 5-10% of a step). Each operation torch runs on a tensor's data is one kernel launch there,
so the count of such operations in a real step (``Optimizer.step``, forward and backward), taken on
the CPU with a dispatch mode, is the GPU's launch count without a GPU: view and metadata
operations (``view``, ``slice``, ``t``, ``expand``, ``empty``, ...) launch nothing and are not
counted. The paper's step (1 view of a 512x512 ray cache, 1 global image and 4 crops, CLIP
ViT-B-32 at 224 with random weights, width 256, 32 lobes) in float32 with the eager renderer, as a
GPU runs it by default (AdamW's multi-tensor form, as on a GPU: 73 launches a step against 312 in its
per-parameter form, which a CPU runs), is counted twice, side by side: with the shadows' shares in the CPU's
blocks of points, and in the GPU's (:func:`stages.render.visibility.visibility_block`: one block
for a step's points). It prints the launches per step of each and the operations launched most.

    python benchmarks/launches.py [--steps 3] [--top 12]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from collections import Counter
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode

sys.path.insert(0, str(Path(__file__).resolve().parent))
from optimize import build_cache, make_optimizer, vit_b32_random  # noqa: E402

from stages.config.sections import OptimizeSettings  # noqa: E402
from stages.core.provenance import Timer  # noqa: E402
from stages.render import visibility  # noqa: E402

#: operations that allocate without writing, or view without the view tag: no kernel
NO_LAUNCH = {"empty", "empty_like", "empty_strided", "new_empty", "new_empty_strided", "detach", "lift_fresh", "_unsafe_view"}


class Launches(TorchDispatchMode):
    """Counts the operations that would each be a kernel launch on a GPU, by name."""

    def __init__(self) -> None:
        super().__init__()
        self.counts: Counter[str] = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = func.overloadpacket.__name__
        if not func.is_view and name not in NO_LAUNCH:
            self.counts[name] += 1
        return func(*args, **(kwargs or {}))


def count(train: Path, steps: int, gpu_blocks: bool) -> Counter[str]:
    """Launches per step (mean of ``steps`` after a warm-up), the shares in the GPU's blocks
    where ``gpu_blocks``."""
    s = OptimizeSettings(crops=4, width=256, light_lobes=32, bf16="off", bf16_networks="off", compile_shading="off")
    opt = make_optimizer(s, train, vit_b32_random(tower=s.clip_tower))
    for group in opt.adamw.param_groups:  # AdamW as on a GPU: a few multi-tensor launches, not ones per parameter
        group["foreach"] = True
    real = visibility.visibility_block
    if gpu_blocks:
        visibility.visibility_block = lambda device, directions, products: real(torch.device("cuda"), directions, products)
    try:
        opt.step(Timer())
        with Launches() as mode:
            for _ in range(steps):
                opt.step(Timer())
    finally:
        visibility.visibility_block = real
    return Counter({k: v / steps for k, v in mode.counts.items()})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=3)
    parser.add_argument("--top", type=int, default=12)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as d:
        train, mesh = build_cache(Path(d))
        print(f"# mesh {mesh}; the paper step, float32, eager renderer; launches per step (mean of {args.steps})", flush=True)
        ways = {"CPU blocks": count(train, args.steps, False), "GPU blocks": count(train, args.steps, True)}
    names = sorted(set().union(*ways.values()), key=lambda k: -max(w[k] for w in ways.values()))[: args.top]
    print(f"{'operation':<28}" + "".join(f"{w:>12}" for w in ways))
    for name in names:
        print(f"{name:<28}" + "".join(f"{w[name]:>12.0f}" for w in ways.values()))
    totals = {w: sum(c.values()) for w, c in ways.items()}
    print(
        f"launches_cpu_blocks={totals['CPU blocks']:.0f} launches_gpu_blocks={totals['GPU blocks']:.0f} "
        f"ratio={totals['CPU blocks'] / totals['GPU blocks']:.2f}"
    )


if __name__ == "__main__":
    main()
