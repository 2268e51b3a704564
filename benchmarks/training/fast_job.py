"""The ``fast`` preset's whole optimize job on a built-in mesh, under CLIP ViT-B-32 at 224, per
CPU lever, side by side: the job's wall time as a user sees it (``python -m stages.optimize`` in
a fresh process: start-up, CLIP loading, 300 iterations, the evaluation renders and the outputs)
against the target of 90 seconds, and its parts: the process's start (imports) before the stage's
clock, the setup (the ray cache and CLIP loaded, the renderer compiled), the loop and the outputs.
``defaults`` is what a user gets (the bfloat16 levers on ``auto``: bfloat16 where the CPU has it
natively); ``float32`` turns both off.

``defaults`` compiles the renderer where the same renderer has been compiled on this machine
before (``compile_shading: auto``; a first compilation pays from 1,000 iterations, a cached one
from 100), so it depends on the machine's history: ``eager`` runs the same with the renderer
eager; ``defaults+compiled`` compiles whatever the cache holds (cold on a fresh machine: the run
pays the first compilation) and leaves the cache warm for ``defaults`` and for
``defaults+compiled (warm)`` after it. The ray cache is the
default one (64 views at 512x512) of ``--mesh`` (built-in vase). No CLIP
weights reach our machines, so ViT-B-32 runs with random weights saved once as a local
checkpoint (``optimize.clip_checkpoint``): timing does not depend on the weights. Quality under
bfloat16 is measured where it can be, on image targets (``python -m benchmarks.quality.recovery
--precision``) and as the cosines of CLIP's outputs (``python -m benchmarks.training.optimize --clip-only``). ``defaults AVX2
only`` runs the defaults with torch held to AVX2 (``stages.core.device.AVX2_ONLY_ENV``: no native
bfloat16, inductor's code for AVX2 in that CPU's own cache folder, cold on its first run), this
CPU standing in for one without AVX-512. ``allocator as it is`` runs the defaults with the C
allocator left to give freed memory back (``keep_freed_memory: off``). The float32 linear layers
run by oneDNN where it measured faster (``onednn_products: auto``, ``stages.render.products``);
``float32 with ATen's products`` and ``AVX2 only with ATen's products`` keep ATen's (MKL's).

Each lever's loop is set against its FLOP floor: the ``fast`` step's FLOPs counted on three real
steps in this process (``benchmarks.common.step_flops``: CLIP's forward and backward to its image, the
networks' products and the pointwise, per point shaded), times the job's iterations and its points
per iteration, at the peak matrix-multiply rates of the lever's precisions, measured in a fresh
process under the lever's environment (``x floor``; NaN where bfloat16 is emulated).

    python -m benchmarks.training.fast_job [--mesh vase] [--levers float32,defaults] [--threads 2]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import (
    REPO,
    at_points,
    lever_floor,
    make_optimizer,
    module_command,
    peak_matmul_rate,
    step_flops,
    vit_b32_random,
)
from stages.core.device import AVX2_ONLY_ENV

#: issue 34's target for the fast job (the whole job, as a user sees it)
TARGET_S = 90.0
#: lever name -> optimize settings on top of the fast preset
#: (names without commas: ``--levers`` is a comma-separated list of them)
LEVERS = {
    "float32": {"bf16": "off", "bf16_networks": "off"},
    "eager": {"compile_shading": "off"},
    "defaults": {},
    "bf16 CLIP only": {"bf16": "on", "bf16_networks": "off"},
    "defaults+compiled": {"compile_shading": True},
    "defaults+compiled (warm)": {"compile_shading": True},
    "float32 open_clip tower": {"clip_tower": "open_clip", "bf16": "off", "bf16_networks": "off"},
    "defaults AVX2 only": {},
    "AVX2 only with ATen's products": {"onednn_products": "off"},
    "float32 with ATen's products": {"bf16": "off", "bf16_networks": "off", "onednn_products": "off"},
    "allocator as it is": {"keep_freed_memory": "off"},
}
#: lever name -> the environment its job runs under (on top of this one's)
ENVIRONMENTS = {"defaults AVX2 only": AVX2_ONLY_ENV, "AVX2 only with ATen's products": AVX2_ONLY_ENV}


def prepare(work: Path, mesh: str) -> Path:
    """Normalised mesh, the default ray cache and a random ViT-B-32 checkpoint in ``work``."""
    import torch

    from stages.config.sections import NormalizeSettings, RaycacheSettings
    from stages.geometry.meshio import save_ply
    from stages.geometry.normalization import normalize_mesh
    from stages.guidance.compat import import_open_clip
    from stages.raycache import run as raycache_run

    save_ply(work / "mesh.ply", normalize_mesh(f"builtin:{mesh}", NormalizeSettings()).mesh)
    raycache_run(work / "mesh.ply", work / "train.npz", work / "eval.npz", work / "rc.json", RaycacheSettings())
    open_clip = import_open_clip()
    torch.manual_seed(0)
    torch.save(open_clip.create_model("ViT-B-32", pretrained=None).state_dict(), work / "vit-b-32-random.pt")
    return work / "vit-b-32-random.pt"


def peak_rates() -> dict:
    """This process's peak matrix-multiply rates (``benchmarks.common.peak_matmul_rate``) in float32
    and, where the CPU runs it natively, bfloat16 (else None: an emulated rate is no ceiling)."""
    import torch

    from stages.core.device import bf16_support

    native = bf16_support(torch.device("cpu"))[0]
    return {"fp32": peak_matmul_rate(torch.float32), "bf16": peak_matmul_rate(torch.bfloat16) if native else None}


def peaks_under(name: str, threads: int) -> dict:
    """:func:`peak_rates` in a fresh process under lever ``name``'s environment (its instruction set)."""
    cmd = module_command(__spec__.name, "--peaks", "--threads", str(threads))
    env = {**os.environ, **ENVIRONMENTS.get(name, {})}
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, env=env, check=True)
    return json.loads(proc.stdout.splitlines()[-1])


def step_counts(work: Path) -> dict:
    """The ``fast`` preset's step FLOPs (``benchmarks.common.step_flops``: CLIP's to its images,
    the networks' products and the pointwise, and the points shaded), counted on 3 real steps in
    this process on the jobs' ray cache; the precision does not change the count."""
    from stages.config.presets import PRESETS
    from stages.config.sections import OptimizeSettings

    settings = OptimizeSettings(**{**PRESETS["fast"], "bf16": "off", "bf16_networks": "off", "compile_shading": "off"})
    guide = vit_b32_random()
    opt = make_optimizer(settings, work / "train.npz", guide)
    return step_flops(opt, guide, 3, settings.views_per_step * (1 + settings.crops))


def loop_floor(counts: dict, row: dict, rates: dict) -> float:
    """The FLOP floor of a job's loop: its iterations times the floor of a step of its mean points
    (``benchmarks.common.lever_floor`` of ``counts``, :func:`step_counts`, at those points) at the
    ``rates`` of its precisions; NaN where a part ran bfloat16 without a native rate."""
    clip_bf16, networks_bf16 = row["precision"].startswith("clip bfloat16"), "networks bfloat16" in row["precision"]
    step = lever_floor(at_points(counts, row["points"]), clip_bf16, networks_bf16, rates, rates["bf16"] is not None)
    return row["iterations"] * step


def job(work: Path, checkpoint: Path, name: str, overrides: dict, threads: int) -> dict:
    from stages.config.presets import PRESETS
    from stages.config.sections import OptimizeSettings

    settings = OptimizeSettings(**{**PRESETS["fast"], "clip_checkpoint": str(checkpoint), "checkpoint_every": 1000, **overrides})
    out = work / name.replace(" ", "_").replace("(", "").replace(")", "")
    cmd = [sys.executable, "-m", "stages.optimize", "--train", str(work / "train.npz"), "--eval", str(work / "eval.npz")]
    cmd += ["--prompt", "a vase made of wood", "--out-dir", str(out), "--settings", json.dumps(settings.to_dict())]
    cmd += ["--threads", str(threads), "--device", "cpu"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, env={**os.environ, **ENVIRONMENTS.get(name, {})})
    wall = time.perf_counter() - t0
    if proc.returncode:
        raise SystemExit(f"{name}: the optimize job failed:\n{proc.stderr[-3000:]}")
    meta = json.loads((out / "meta.json").read_text())
    return {
        "wall_s": wall,
        "loop_s": meta["timings_s"]["loop"],
        "timings_s": meta["timings_s"],
        "s_per_iter": meta["seconds_per_iteration"],
        "points": meta["points_per_iteration"],
        "iterations": settings.iterations,
        "cpu": meta["cpu"],
        "precision": f"clip {meta['clip_precision'].split(' (')[0]}, networks {meta['network_precision'].split(' (')[0]}, "
        f"float32 by {meta['float32_products'].split(' (')[0]}, shading {meta['shading_path']}",
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--mesh", default="vase")
    parser.add_argument("--levers", default=",".join(LEVERS), help=f"comma-separated, of: {', '.join(LEVERS)}")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--peaks", action="store_true", help=argparse.SUPPRESS)  # peak_rates() as JSON (peaks_under)
    args = parser.parse_args()
    if args.peaks:
        import torch

        torch.set_num_threads(args.threads)
        print(json.dumps(peak_rates()))
        return
    names = [n.strip() for n in args.levers.split(",") if n.strip()]
    with tempfile.TemporaryDirectory() as d:
        work = Path(d)
        t0 = time.perf_counter()
        ckpt = prepare(work, args.mesh)
        print(f"# built-in {args.mesh}: default ray cache and a random ViT-B-32 checkpoint in {time.perf_counter() - t0:.0f} s")
        counts = step_counts(work)
        print(
            f"# the fast step counted: CLIP {counts['clip'] / 1e9:.2f} GFLOP, networks {counts['mlp'] / 1e9:.2f} GFLOP "
            f"and pointwise {counts['pointwise'] / 1e9:.3f} GFLOP at {counts['points']:.0f} points; the loop's floor: "
            "them at the peak rates of each lever's precisions and instruction set (nan: bfloat16 emulated)"
        )
        print(
            f"{'lever':<26}{'job s':>8}{'start s':>8}{'setup s':>8}{'loop s':>8}{'floor s':>8}{'x floor':>8}{'output s':>9}"
            f"{'s/iter':>8}{'points':>8}  precision; cpu",
            flush=True,
        )
        rows = {}
        for name in names:
            r = rows[name] = job(work, ckpt, name, LEVERS[name], args.threads)
            rates = peaks_under(name, args.threads)
            r["floor_s"] = loop_floor(counts, r, rates)
            peaks = ", ".join(f"{k} {v / 1e9:.0f}" for k, v in rates.items() if v is not None)
            print(
                f"{name:<26}{r['wall_s']:>8.1f}{r['wall_s'] - r['timings_s']['total']:>8.1f}{r['timings_s']['setup']:>8.1f}"
                f"{r['loop_s']:>8.1f}{r['floor_s']:>8.1f}{r['loop_s'] / r['floor_s']:>8.1f}{r['timings_s']['outputs']:>9.1f}"
                f"{r['s_per_iter']:>8.3f}{r['points']:>8.0f}  {r['precision']}; {r['cpu']}; peaks GFLOP/s {peaks}",
                flush=True,
            )
    best = min(rows, key=lambda k: rows[k]["wall_s"])
    shown = "defaults" if "defaults" in rows else best
    print(
        f"fast_job_s={rows[shown]['wall_s']:.1f} target_s={TARGET_S:.0f} of={shown} best={best.replace(' ', '_')} "
        f"loop_ratio_to_floor={rows[shown]['loop_s'] / rows[shown]['floor_s']:.1f} "
        + " ".join(f"{k.replace(' ', '_')}_s={v['wall_s']:.1f}" for k, v in rows.items())
    )


if __name__ == "__main__":
    main()
