"""Threads per optimisation job on a CPU: one thread against two, and two one-thread jobs at once.

What the optimize rule's ``threads`` follow (a guidance mode's ``cpu_threads``,
:mod:`stages.config.guidance_modes`). Each figure is a child process timing ``--steps`` steps
after a warm-up, eager (as a run of a few hundred steps trains without a warm compilation cache):

* ``image``: the demo's image-guided step (``config/demo.yaml``'s optimisation: 2 views of 128
  pixels, width 64, the normal network, 16 lobes; its own SG-rendered targets, so Mitsuba is not
  needed) on a ray cache of the built-in vase (32 views of 128 pixels, the default visibility);
* ``clip``: the ``fast`` preset's CLIP step (ViT-B-32 with random weights at 224) on the paper's
  ray cache (``benchmarks.common.build_cache``).

For each: seconds per step alone on 1 thread and alone on 2 (``speedup_2_threads``: the second
thread's gain), and two 1-thread children at once (``step_s_pair``, each child's mean);
``pair_throughput = 2 * step_s_2 / step_s_pair`` is the work of two one-thread jobs side by side
against one two-thread job at a time: above 1, a job of that guidance should take one thread.

    python -m benchmarks.training.threads [--steps 30] [--only image|clip]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import tempfile
from pathlib import Path

from benchmarks.common import EAGER, REPO, build_cache, step_time

#: the demo's optimisation settings (config/demo.yaml), on its own SG-rendered targets
DEMO = REPO / "config" / "demo.yaml"


def child(kind: str, threads: int, steps: int, work: Path) -> dict:
    """One timing in this process (``--child``): ``kind``'s step on ``threads`` threads."""
    import torch

    torch.set_num_threads(threads)
    from stages.config.workflow import load_config_files
    from stages.core.threads import set_cpu_threads
    from stages.geometry.raycache import RayCache
    from stages.training.optimizer import Optimizer

    set_cpu_threads(threads)
    if kind == "image":
        cfg = load_config_files([DEMO])
        settings = dataclasses.replace(cfg.optimize_settings("wood", "base"), target_renderer="sg", **EAGER)
        opt = Optimizer(settings, RayCache(work / "image" / "train.npz"), "a vase made of wood", "cpu")
    else:
        from benchmarks.common import make_optimizer, vit_b32_random
        from stages.config.presets import PRESETS
        from stages.config.sections import OptimizeSettings

        settings = OptimizeSettings(**{**PRESETS["fast"], **EAGER})
        opt = make_optimizer(settings, work / "clip" / "train.npz", vit_b32_random(bf16=settings.bf16, tower=settings.clip_tower))
    seconds, points = step_time(opt, steps)
    return {"step_s": seconds, "points": points}


def prepare(work: Path, kinds: list[str]) -> None:
    """The ray caches the children read."""
    from stages.config.sections import NormalizeSettings, RaycacheSettings
    from stages.geometry.meshio import save_ply
    from stages.geometry.normalization import normalize_mesh
    from stages.raycache import run as raycache_run

    if "image" in kinds:
        folder = work / "image"
        folder.mkdir(parents=True)
        save_ply(folder / "mesh.ply", normalize_mesh("builtin:vase", NormalizeSettings()).mesh)
        rc = RaycacheSettings(views=32, resolution=128, std=3.0, eval_azimuths=1, eval_elevations_deg=(0.0,))
        raycache_run(folder / "mesh.ply", folder / "train.npz", folder / "eval.npz", folder / "rc.json", rc)
    if "clip" in kinds:
        (work / "clip").mkdir(parents=True)
        build_cache(work / "clip")


def spawn(kind: str, threads: int, steps: int, work: Path) -> subprocess.Popen:
    args = ["--child", kind, "--threads", str(threads), "--steps", str(steps), "--work", str(work)]
    return subprocess.Popen(
        [sys.executable, "-m", "benchmarks.training.threads", *args], cwd=REPO, stdout=subprocess.PIPE, text=True
    )


def collect(*procs: subprocess.Popen) -> list[dict]:
    out = []
    for p in procs:
        stdout, _ = p.communicate()
        if p.returncode != 0:
            raise SystemExit(f"a timing child failed (exit {p.returncode})")
        out.append(json.loads(stdout.strip().splitlines()[-1]))
    return out


def measure(kind: str, steps: int, work: Path) -> dict:
    """``kind``'s step alone on 1 and 2 threads, then two 1-thread children at once."""
    (one,) = collect(spawn(kind, 1, steps, work))
    (two,) = collect(spawn(kind, 2, steps, work))
    pair = collect(spawn(kind, 1, steps, work), spawn(kind, 1, steps, work))
    pair_s = sum(p["step_s"] for p in pair) / len(pair)
    return {
        "points": one["points"],
        "step_s_1": one["step_s"],
        "step_s_2": two["step_s"],
        "step_s_pair": pair_s,
        "speedup_2_threads": one["step_s"] / two["step_s"],
        "pair_throughput": 2 * two["step_s"] / pair_s,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--only", choices=("image", "clip"))
    parser.add_argument("--child", choices=("image", "clip"), help=argparse.SUPPRESS)
    parser.add_argument("--threads", type=int, default=1, help=argparse.SUPPRESS)
    parser.add_argument("--work", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(args.child, args.threads, args.steps, args.work)))
        return
    kinds = [args.only] if args.only else ["image", "clip"]
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        prepare(work, kinds)
        rows = {kind: measure(kind, args.steps, work) for kind in kinds}
    header = ("guidance", "points", "1 thread s", "2 threads s", "pair s", "2-thread gain", "pair throughput")
    print(f"{header[0]:<10}" + "".join(f"{h:>16}" for h in header[1:]))
    for kind, r in rows.items():
        print(
            f"{kind:<10}{r['points']:>16.0f}{r['step_s_1']:>16.3f}{r['step_s_2']:>16.3f}{r['step_s_pair']:>16.3f}"
            f"{r['speedup_2_threads']:>16.2f}{r['pair_throughput']:>16.2f}"
        )
    print(" ".join(f"{k}_{kind}={v:.4g}" for kind, r in rows.items() for k, v in r.items()))


if __name__ == "__main__":
    main()
