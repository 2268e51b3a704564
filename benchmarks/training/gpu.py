"""The paper's optimisation on one GPU, in one command: wall time, seconds per iteration, peak
GPU memory and where the time goes.

At the paper's defaults (a 512x512 ray cache of 8 views, CLIP ViT-B-32 at 224 with random weights:
no weights can be downloaded on the lent machines and timing does not depend on them, networks of
width 256, 32 light lobes, 1 view with 1 global image and 4 crops per step) it runs
``--iterations`` (1,500) real training steps (``Optimizer.step``) on CUDA and prints:

* the wall time of the whole loop and its seconds per iteration (after ``--warmup`` steps, which
  load kernels and fill caches), against the target of 60 s for 1,500 iterations;
* the peak GPU memory allocated by torch (``torch.cuda.max_memory_allocated``) against 4 GiB;
* a profile of ``--profile-steps`` steps: the top CUDA kernels by device time, host-to-device and
  device-to-host copies per step, and the share of the step the GPU was busy (low: the Python
  overhead of small kernels dominates);
* the levers side by side (``--levers``, or ``--levers "float32,one graph"`` for some):
  bfloat16 for CLIP and the networks, TF32 products, the renderer compiled by torch.compile
  (``compile_shading: on``, Triton), the networks compiled into the renderer's graph
  (``compile_networks: on``; fewer launches), and that graph captured as CUDA graphs
  (``compile_static: on``: the points padded to the largest view's, one launch per graph); a
  compilation is paid in the lever's setup, not in its timed iterations, and printed apart, with
  the warm-up's seconds and the graphs dynamo compiled in the setup, the warm-up and the timed
  iterations (a graph compiled after the setup is a second compilation that a real run pays).

The mesh is ``../shared/meshes/person.obj`` when present, else the built-in vase. Without CUDA it
stops with a message (tests/gpu holds the GPU tests; both skip or stop on a CPU machine).

    python -m benchmarks.training.gpu [--iterations 1500] [--levers [NAMES]] [--lever-iterations 200] [--bf16] [--tf32]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import torch

from benchmarks.common import build_cache, vit_b32_random
from stages.config.sections import OptimizeSettings
from stages.core.provenance import Timer
from stages.geometry.raycache import RayCache
from stages.training.optimizer import Optimizer

TARGET_S = 60.0
TARGET_GIB = 4.0


def run(train: Path, iterations: int, warmup: int, bf16: bool, tf32: bool, compiled: str = "") -> dict:
    """``compiled``: "" eager, "renderer" the renderer compiled, "one graph" the networks and the
    renderer compiled together (``compile_networks``), "cuda graphs" that graph captured as CUDA
    graphs (``compile_static``)."""
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = tf32
    s = OptimizeSettings(
        iterations=iterations,
        bf16=bf16,
        bf16_networks=bf16,
        compile_shading="on" if compiled else "off",
        compile_networks="on" if compiled in ("one graph", "cuda graphs") else "off",
        compile_static="on" if compiled == "cuda graphs" else "off",
    )
    guide = vit_b32_random(bf16=s.bf16, tower=s.clip_tower, device="cuda")
    graphs = [compiled_graphs()]
    t0 = time.perf_counter()
    opt = Optimizer(s, RayCache(train), "a person made of wood", "cuda", guide=guide)  # compiles the renderer
    setup = time.perf_counter() - t0
    graphs.append(compiled_graphs())
    t0 = time.perf_counter()
    for _ in range(warmup):
        opt.step(Timer())
    torch.cuda.synchronize()
    warm = time.perf_counter() - t0
    graphs.append(compiled_graphs())
    torch.cuda.reset_peak_memory_stats()
    t0 = time.perf_counter()
    for _ in range(iterations):
        opt.step(Timer())
    torch.cuda.synchronize()
    wall = time.perf_counter() - t0
    graphs.append(compiled_graphs())
    return {
        "wall_s": wall,
        "s_per_iter": wall / iterations,
        "peak_gib": torch.cuda.max_memory_allocated() / 2**30,
        "precision": f"clip {guide.precision}; networks {opt.network_precision}; tf32 {tf32}; shading {opt.shading_path}",
        "setup_s": setup,
        "warmup_s": warm,
        # graphs dynamo compiled in the setup, the warm-up and the timed iterations
        "graphs": "/".join(str(b - a) for a, b in zip(graphs, graphs[1:], strict=False)),
        "opt": opt,
    }


def compiled_graphs() -> int:
    """Graphs dynamo has compiled in this process so far."""
    from torch._dynamo.utils import counters

    return counters["stats"]["unique_graphs"]


def profile(opt: Optimizer, steps: int) -> None:
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as torch_profile

    torch.cuda.synchronize()
    t0 = time.perf_counter()
    with torch_profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        for _ in range(steps):
            opt.step(Timer())
        torch.cuda.synchronize()
    wall = time.perf_counter() - t0
    events = prof.key_averages()
    device_us = sum(e.self_device_time_total for e in events if e.device_type == torch.autograd.DeviceType.CUDA)
    copies = {k: 0 for k in ("HtoD", "DtoH")}
    for e in events:
        for k in copies:
            if f"Memcpy {k}" in e.key:
                copies[k] += e.count
    print(f"# profile of {steps} steps: GPU busy {device_us / 1e6 / wall:.0%} of the wall time")
    print(f"# copies per step: host->device {copies['HtoD'] / steps:.1f}, device->host {copies['DtoH'] / steps:.1f}")
    print(events.table(sort_by="self_cuda_time_total", row_limit=15))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--iterations", type=int, default=1500)
    parser.add_argument("--warmup", type=int, default=10)
    parser.add_argument("--profile-steps", type=int, default=20)
    parser.add_argument("--bf16", action="store_true", help="bfloat16 autocast for CLIP and the networks")
    parser.add_argument("--tf32", action="store_true", help="TF32 matrix products for the float32 parts")
    parser.add_argument(
        "--levers",
        nargs="?",
        const=",".join(LEVERS),
        help=f"also time --lever-iterations under each lever (comma-separated, of: {', '.join(LEVERS)}; all when bare)",
    )
    parser.add_argument("--lever-iterations", type=int, default=200, help="iterations timed under each lever")
    args = parser.parse_args()
    if not torch.cuda.is_available():
        raise SystemExit(
            "benchmarks.training.gpu needs a CUDA device (torch sees none); on a CPU use python -m benchmarks.training.optimize"
        )
    name = torch.cuda.get_device_name()
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        train, mesh = build_cache(Path(d))
        took = time.perf_counter() - t0
        print(f"# {name}; torch {torch.__version__}; mesh {mesh}; ray cache 512x512 in {took:.1f} s", flush=True)
        main_run = run(train, args.iterations, args.warmup, args.bf16, args.tf32)
        print(f"# {main_run['precision']}", flush=True)
        # the summary first: a lever that fails below must not cost the main run's figures
        pts = statistics.mean(row["points"] for row in main_run["opt"].history[-args.iterations :])
        print(
            f"iterations={args.iterations} wall_s={main_run['wall_s']:.1f} target_s={TARGET_S * args.iterations / 1500:.1f} "
            f"s_per_iter={main_run['s_per_iter']:.4f} peak_gib={main_run['peak_gib']:.2f} target_gib={TARGET_GIB} "
            f"points_per_iter={pts:.0f} device={name.replace(' ', '_')}",
            flush=True,
        )
        profile(main_run["opt"], args.profile_steps)
        if args.levers:
            names = [n.strip() for n in args.levers.split(",") if n.strip()]
            unknown = [n for n in names if n not in LEVERS]
            if unknown:
                raise SystemExit(f"--levers: unknown {', '.join(unknown)}; choose from {', '.join(LEVERS)}")
            levers(train, args.warmup, names, args.lever_iterations)


#: the levers ``--levers`` times, by name: (bf16, tf32, compiled)
LEVERS = {
    "float32": (False, False, ""),
    "tf32": (False, True, ""),
    "bf16": (True, False, ""),
    "compiled renderer": (False, False, "renderer"),
    "one graph": (False, False, "one graph"),
    "cuda graphs": (False, False, "cuda graphs"),
}


def levers(train: Path, warmup: int, names: list[str], iterations: int = 200) -> None:
    """``iterations`` under each lever of ``names`` (:data:`LEVERS`), side by side, the first the
    ratios' base; a lever whose run fails (a non-finite loss, as TF32 products gave on an H100
    before the SG product's cosine was held in [-1, 1]) is reported as such. A compiled lever
    pays its compilation in its setup (printed apart), not in its timed iterations; ``graphs``:
    those dynamo compiled in the setup, the warm-up and the timed iterations (``1/0/0``: once)."""
    print(f"{'lever':<22}{'s/iter':>9}{'x first':>9}{'peak GiB':>10}{'setup s':>9}{'warm-up s':>10}{'graphs':>9}", flush=True)
    base = None
    for name in names:
        bf16, tf32, compiled = LEVERS[name]
        try:
            r = run(train, iterations, warmup, bf16, tf32, compiled)
        except (FloatingPointError, RuntimeError) as exc:
            print(f"{name:<22} failed: {type(exc).__name__}: {str(exc).splitlines()[0][:120]}", flush=True)
            continue
        base = base or r["s_per_iter"]
        row = (
            f"{name:<22}{r['s_per_iter']:>9.4f}{base / r['s_per_iter']:>9.2f}{r['peak_gib']:>10.2f}{r['setup_s']:>9.1f}"
            f"{r['warmup_s']:>10.1f}{r['graphs']:>9}"
        )
        print(row + ("" if not compiled else f"  ({r['precision'].split('; ')[-1]})"), flush=True)


if __name__ == "__main__":
    main()
