"""The C allocator keeping the memory a step frees (``optimize.keep_freed_memory``) against the
allocator as it is, on the paper's training step, or another process-wide lever's off against on
(``--lever onednn_products``: the float32 linear layers by ATen's kernels against oneDNN's): the
setting holds for a whole process, so the two are compared in child processes taken in turns
(off, on, off, on, ...), each timing
``--steps`` real steps (``Optimizer.step``) after 3 untimed ones. Each prints its seconds per
step, minor page faults per step and peak resident memory; the last line gives the median of the
paired ratios (off over on).

The mesh is ``../shared/meshes/person.obj`` when present, else the built-in vase; the paper's
settings (a 512 x 512 ray cache of 8 views, CLIP ViT-B-32 with random weights, width 256, 32 lobes,
1 global image and 4 crops per step) and the defaults' levers, as ``benchmarks.training.optimize``'s
measured step, whose last line also gives the step's FLOP floor. ``--isa avx2`` holds torch to AVX2;
``--precision float32`` turns both bfloat16 levers off.

    python -m benchmarks.training.allocator [--rounds 3] [--steps 8] [--isa native|avx2]
        [--lever keep_freed_memory|onednn_products] [--precision defaults|float32]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

from benchmarks.common import REPO, build_cache, make_optimizer, module_command, paired_ratios, vit_b32_random
from stages.core.device import AVX2_ONLY_ENV, cpu_isa

#: the process-wide levers this benchmark compares, and what the optimiser records of each
LEVERS = {"keep_freed_memory": "allocator", "onednn_products": "float32_products"}


def child(train: Path, lever: str, setting: str, steps: int, float32: bool) -> dict:
    """``steps`` paper steps under ``lever: setting`` in this process (``float32``: both bfloat16
    levers off)."""
    import torch

    from stages.config.sections import OptimizeSettings
    from stages.core.provenance import Timer

    torch.manual_seed(0)
    precision = {"bf16": "off", "bf16_networks": "off"} if float32 else {}
    s = OptimizeSettings(iterations=1500, **{lever: setting}, **precision)
    opt = make_optimizer(s, train, vit_b32_random(bf16=s.bf16))
    for _ in range(3):
        opt.step(Timer())
    faults0, t0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt, time.perf_counter()
    for _ in range(steps):
        opt.step(Timer())
    wall = time.perf_counter() - t0
    return {
        "setting": setting,
        "s_per_step": wall / steps,
        "faults_per_step": (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults0) / steps,
        "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9,
        "allocator": getattr(opt, LEVERS[lever]),
        "step": f"{opt.shading_path}; networks {opt.network_precision}",
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=3, help="pairs of processes (off, then on)")
    parser.add_argument("--steps", type=int, default=8, help="timed steps per process")
    parser.add_argument("--isa", choices=("native", "avx2"), default="native", help="avx2: torch held to AVX2")
    parser.add_argument("--lever", choices=tuple(LEVERS), default="keep_freed_memory", help="the lever taken off and on")
    parser.add_argument("--precision", choices=("defaults", "float32"), default="defaults")
    parser.add_argument("--child", nargs=2, metavar=("TRAIN", "SETTING"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        row = child(Path(args.child[0]), args.lever, args.child[1], args.steps, args.precision == "float32")
        print(json.dumps(row), flush=True)
        return
    env = {**os.environ, **(AVX2_ONLY_ENV if args.isa == "avx2" else {})}
    with tempfile.TemporaryDirectory() as d:
        train, mesh = build_cache(Path(d))
        print(
            f"# mesh {mesh}; the paper step ({args.precision}); {args.lever} off and on; {args.steps} steps per process; "
            f"torch held to {args.isa}",
            flush=True,
        )
        print(f"{'round':>5} {'setting':<8}{'s/step':>8}{'faults/step':>13}{'peak GB':>9}  {LEVERS[args.lever]}", flush=True)
        rows: dict[str, list[dict]] = {"off": [], "on": []}
        for r in range(args.rounds):
            for setting in ("off", "on"):
                cmd = module_command(__spec__.name, "--steps", str(args.steps), "--lever", args.lever)
                cmd += ["--precision", args.precision, "--child", str(train), setting]
                out = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, check=True).stdout
                row = json.loads(out.strip().splitlines()[-1])
                rows[setting].append(row)
                print(
                    f"{r + 1:>5} {setting:<8}{row['s_per_step']:>8.3f}{row['faults_per_step']:>13.0f}"
                    f"{row['peak_rss_gb']:>9.2f}  {row['allocator']}",
                    flush=True,
                )
    step = rows["on"][-1]["step"]
    ratios = paired_ratios([r["s_per_step"] for r in rows["off"]], [r["s_per_step"] for r in rows["on"]])
    med = {k: statistics.median(r["s_per_step"] for r in v) for k, v in rows.items()}
    faults = {k: statistics.median(r["faults_per_step"] for r in v) for k, v in rows.items()}
    rss = {k: max(r["peak_rss_gb"] for r in v) for k, v in rows.items()}
    print(f"# the step: {step}; CPU {cpu_isa() if args.isa == 'native' else 'held to AVX2'}")
    print(
        f"s_per_step_off={med['off']:.4g} s_per_step_on={med['on']:.4g} paired_ratio={statistics.median(ratios):.3f} "
        f"faults_off={faults['off']:.0f} faults_on={faults['on']:.0f} "
        f"peak_rss_gb_off={rss['off']:.2f} peak_rss_gb_on={rss['on']:.2f}"
    )


if __name__ == "__main__":
    main()
