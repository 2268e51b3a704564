"""Kernel launches per paper step, counted on the CPU and split by part: what a GPU step pays for.

On a GPU the paper's step is bound by kernel launches, not arithmetic (``benchmarks.training.gpu``: the
GPU busy 5-10% of a step). Each operation torch runs on a tensor's data is one kernel launch there,
so the count of such operations in a real step (``Optimizer.step``, forward and backward), taken on
the CPU with a dispatch mode, is the GPU's launch count without a GPU: view and metadata
operations (``view``, ``slice``, ``t``, ``expand``, ``empty``, ...) launch nothing and are not
counted. The paper's step (1 view of a 512x512 ray cache, 1 global image and 4 crops, CLIP
ViT-B-32 at 224 with random weights, width 256, 32 lobes) in float32 with the eager renderer is
counted twice, side by side: on the CPU's paths, and on the GPU's where they differ (the shadows'
shares in one block for a step's points, :func:`stages.render.visibility.visibility_block`, where
a CPU takes blocks of 512; CLIP's attention by torch's fused kernel,
:func:`stages.guidance.vit.fused_attention`, where a CPU takes plain products).

Each launch is put down to the part of the step that made it: the forward's by the function that
ran it (the renderer's ``shade_material``, the networks, the light, the shadows' shares, CLIP's
loss, the images' compositing, the priors, the finiteness check, the optimiser), the backward's by
the part whose forward made the autograd node that runs it. On a GPU the paper's run compiles the
renderer (``compile_shading: auto`` from 1,400 iterations), so its forward and backward become a
few fused kernels there, and what the other parts launch is what is left to a step eager: the last
line's ``launches_outside_renderer``.

    python -m benchmarks.training.launches [--steps 3] [--top 12] [--part CLIP ...]
"""

from __future__ import annotations

import argparse
import contextlib
import tempfile
from collections import Counter
from pathlib import Path

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten

import stages.model.field as field_module
import stages.training.optimizer as optimizer_module
from benchmarks.common import build_cache, make_optimizer, vit_b32_random
from stages.config.sections import OptimizeSettings
from stages.core.provenance import Timer
from stages.guidance import vit
from stages.render import visibility

#: operations that allocate without writing, or view without the view tag: no kernel
NO_LAUNCH = {"empty", "empty_like", "empty_strided", "new_empty", "new_empty_strided", "detach", "lift_fresh", "_unsafe_view"}
#: the parts, in the order printed
PARTS = ("renderer", "networks", "light", "shadows' shares", "CLIP", "images", "priors", "finiteness check", "optimiser", "other")


class Parts:
    """Which part of the step runs now (forward), and which part made each autograd node (backward)."""

    def __init__(self) -> None:
        self.now = "other"
        self.nodes: dict[int, tuple[str, object]] = {}  # id(node) -> (part, node: kept alive so ids stay unique)

    @contextlib.contextmanager
    def part(self, name: str):
        before, self.now = self.now, name
        try:
            yield
        finally:
            self.now = before

    def wrap(self, owner, attr: str, name: str) -> None:
        """``owner.attr`` (a function or bound method) run as part ``name``."""
        fn = getattr(owner, attr)

        def run(*args, **kwargs):
            with self.part(name):
                out = fn(*args, **kwargs)
                for t in tree_flatten(out)[0]:  # (an autograd.Function's output is not seen by the Tagger)
                    if isinstance(t, torch.Tensor) and t.grad_fn is not None:
                        self.tag(t.grad_fn)
                return out

        setattr(owner, attr, run)

    def tag(self, node) -> None:
        """``node`` and the untagged nodes behind it (made inside the same call: a composite
        operation's) as the current part's."""
        stack = [node]
        while stack:
            n = stack.pop()
            if n is None or id(n) in self.nodes:
                continue
            self.nodes[id(n)] = (self.now, n)
            stack.extend(next_fn for next_fn, _ in n.next_functions)

    def of_node(self, node) -> str:
        return self.nodes.get(id(node), ("other",))[0]


class Tagger(TorchFunctionMode):
    """Tags the autograd nodes a forward operation makes with the part running it."""

    def __init__(self, parts: Parts) -> None:
        super().__init__()
        self.parts = parts

    def __torch_function__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        if torch._C._current_autograd_node() is None:
            for t in tree_flatten(out)[0]:
                if isinstance(t, torch.Tensor) and t.grad_fn is not None:
                    self.parts.tag(t.grad_fn)
        return out


class Launches(TorchDispatchMode):
    """Counts the operations that would each be a kernel launch on a GPU, by name and by part."""

    def __init__(self, parts: Parts) -> None:
        super().__init__()
        self.parts = parts
        self.counts: Counter[str] = Counter()
        self.by_part: Counter[str] = Counter()
        self.in_part: Counter[tuple[str, str]] = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = func.overloadpacket.__name__
        if not func.is_view and name not in NO_LAUNCH:
            node = torch._C._current_autograd_node()
            part = self.parts.now if node is None else self.parts.of_node(node)
            self.counts[name] += 1
            self.by_part[part] += 1
            self.in_part[part, ("backward " if node is not None else "") + name] += 1
        return func(*args, **(kwargs or {}))


class PartTimer(Timer):
    """The step's own sections, the optimiser's among them, as parts."""

    def __init__(self, parts: Parts) -> None:
        super().__init__()
        self.parts = parts

    @contextlib.contextmanager
    def __call__(self, name: str):
        with super().__call__(name), self.parts.part("optimiser" if name == "optimizer" else self.parts.now):
            yield


def count(train: Path, steps: int, gpu_paths: bool) -> tuple[Counter, Counter, Counter]:
    """Launches per step by operation, by part and by (part, operation) (means of ``steps``
    after a warm-up), on the GPU's paths where ``gpu_paths``."""
    s = OptimizeSettings(crops=4, width=256, light_lobes=32, bf16="off", bf16_networks="off", compile_shading="off")
    opt = make_optimizer(s, train, vit_b32_random(tower=s.clip_tower))
    parts = Parts()
    field = opt.field
    modules = [(field_module, "shade_material"), (optimizer_module, "compose"), (optimizer_module, "linear_to_srgb")]
    originals = [getattr(m, attr) for m, attr in modules]  # (put back after: the next count wraps its own)
    for owner, attr, name in (
        (field_module, "shade_material", "renderer"),
        (field, "surface", "networks"),
        (field.light, "forward", "light"),
        (field, "shares", "shadows' shares"),
        (opt.guidance, "loss", "CLIP"),
        (optimizer_module, "compose", "images"),
        (optimizer_module, "linear_to_srgb", "images"),
        (opt, "priors", "priors"),
        (opt, "check_finite", "finiteness check"),
    ):
        parts.wrap(owner, attr, name)
    block, fused = visibility.visibility_block, vit.fused_attention
    if gpu_paths:
        visibility.visibility_block = lambda device, directions, products: block(torch.device("cuda"), directions, products)
        vit.fused_attention = lambda device: fused(torch.device("cuda"))
    try:
        opt.step(Timer())
        with Tagger(parts), Launches(parts) as mode:
            for _ in range(steps):
                parts.nodes.clear()  # the last step's graph: its nodes are done
                opt.step(PartTimer(parts))
    finally:
        visibility.visibility_block, vit.fused_attention = block, fused
        for (module, attr), fn in zip(modules, originals, strict=True):
            setattr(module, attr, fn)
    return tuple(Counter({k: v / steps for k, v in c.items()}) for c in (mode.counts, mode.by_part, mode.in_part))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=3)
    parser.add_argument("--top", type=int, default=12)
    parser.add_argument("--part", choices=PARTS, action="append", help="also list this part's operations (repeatable)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as d:
        train, mesh = build_cache(Path(d))
        print(f"# mesh {mesh}; the paper step, float32, eager renderer; launches per step (mean of {args.steps})", flush=True)
        ways = {"CPU paths": count(train, args.steps, False), "GPU paths": count(train, args.steps, True)}
    ops = {w: c[0] for w, c in ways.items()}
    parts = {w: c[1] for w, c in ways.items()}
    print(f"{'part':<28}" + "".join(f"{w:>12}" for w in ways))
    for name in PARTS:
        print(f"{name:<28}" + "".join(f"{p[name]:>12.0f}" for p in parts.values()))
    names = sorted(set().union(*ops.values()), key=lambda k: -max(w[k] for w in ops.values()))[: args.top]
    print(f"{'operation':<28}" + "".join(f"{w:>12}" for w in ways))
    for name in names:
        print(f"{name:<28}" + "".join(f"{w[name]:>12.0f}" for w in ops.values()))
    for part in args.part or []:
        within = ways["GPU paths"][2]
        print(f"# {part} (GPU paths): " + ", ".join(f"{op} {n:.0f}" for (p, op), n in within.most_common() if p == part))
    totals = {w: sum(c.values()) for w, c in ops.items()}
    outside = sum(v for k, v in parts["GPU paths"].items() if k != "renderer")
    print(
        f"launches_cpu_paths={totals['CPU paths']:.0f} launches_gpu_paths={totals['GPU paths']:.0f} "
        f"ratio={totals['CPU paths'] / totals['GPU paths']:.2f} launches_outside_renderer={outside:.0f}"
    )


if __name__ == "__main__":
    main()
