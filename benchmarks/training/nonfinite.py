"""Which operation first turns finite inputs into a non-finite (or float32-overflowing) result in
real training steps: the op's name, its shapes and the lines of stages/ that called it.

At the paper's settings (the ray cache and random-weight ViT-B-32 of benchmarks.training.gpu) it runs
``--steps`` training steps under a dispatch mode that checks every op's floating outputs, forward and
backward, and prints the first op whose inputs were all finite and whose output was not, together
with the largest finite magnitude seen per op (the ops that come near float32's range). With
``--tf32`` the float32 matrix products run in TF32 (on CUDA, where the loss turned non-finite near
step 45 on an H100).

    python -m benchmarks.training.nonfinite [--device cuda] [--tf32] [--steps 80]
"""

from __future__ import annotations

import argparse
import tempfile
import traceback
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten

from benchmarks.common import build_cache, vit_b32_random
from stages.config.sections import OptimizeSettings
from stages.core.provenance import Timer
from stages.geometry.raycache import RayCache
from stages.training.optimizer import Optimizer


def _floats(tree) -> list[torch.Tensor]:
    leaves, _ = tree_flatten(tree)
    return [t for t in leaves if isinstance(t, torch.Tensor) and t.is_floating_point() and t.numel()]


def _where() -> str:
    frames = [f for f in traceback.extract_stack() if "/stages/" in f.filename]
    return " <- ".join(f"{Path(f.filename).name}:{f.lineno} {f.name}" for f in reversed(frames[-4:])) or "(outside stages/)"


class NonFiniteSites(TorchDispatchMode):
    """Every call site (op and stages/ lines) whose finite inputs gave a non-finite output, with the
    step it first did so and how often; sites a ``where`` masks later show from the first step."""

    def __init__(self) -> None:
        super().__init__()
        self.step = 0
        self.sites: dict[str, list[int]] = {}
        self.largest: dict[str, tuple[float, str]] = {}

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        name = str(func.overloadpacket.__name__)
        ins = _floats((args, kwargs))
        if not ins:  # creation ops (empty, zeros, ...): nothing to propagate
            return out
        for t in _floats(out):
            if not bool(torch.isfinite(t).all()):
                if all(bool(torch.isfinite(i).all()) for i in ins):
                    site = f"{name} {[tuple(i.shape) for i in ins]} {t.dtype}: {_where()}"
                    self.sites.setdefault(site, [self.step, 0])[1] += 1
                continue
            big = float(t.detach().abs().max())
            if big > self.largest.get(name, (-1.0, ""))[0]:
                self.largest[name] = (big, _where())
        return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--tf32", action="store_true")
    parser.add_argument("--steps", type=int, default=80)
    args = parser.parse_args()
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = args.tf32
    with tempfile.TemporaryDirectory() as d:
        train, mesh = build_cache(Path(d))
        s = OptimizeSettings(iterations=args.steps)
        guide = vit_b32_random(tower=s.clip_tower, device=args.device)
        opt = Optimizer(s, RayCache(train), "a person made of wood", args.device, guide=guide)
        mode = NonFiniteSites()
        try:
            with mode:
                for mode.step in range(args.steps):
                    opt.step(Timer())
        except FloatingPointError as exc:
            print(f"# step {mode.step}: {str(exc).splitlines()[0]}")
        print(f"# mesh {mesh}; device {args.device}; tf32 {args.tf32}; steps run {mode.step + 1}")
        print("sites whose finite inputs gave non-finite outputs (first step, count):")
        for site, (first, count) in sorted(mode.sites.items(), key=lambda kv: kv[1][0]):
            print(f"  step {first:>4} x{count:<5} {site}")
        print("largest finite magnitude per op:")
        for name, (big, where) in sorted(mode.largest.items(), key=lambda kv: -kv[1][0])[:12]:
            print(f"{name:<28}{big:>12.3e}  {where}")


if __name__ == "__main__":
    main()
