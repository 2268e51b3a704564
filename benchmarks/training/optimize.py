"""Optimisation step cost on this machine, split by component, against its two ceilings.

At the paper's per-step counts (1 view from a 512x512 ray cache, 1 global image and 4 local crops,
CLIP ViT-B-32 at 224x224, networks of width 256, 32 light lobes) it measures:

* ``s_per_iter``: wall time of the real training step (``stages.training.optimizer.Optimizer.step``);
* the split of one step into ray-cache gather, encodings+MLPs (forward+backward), shading
  (forward+backward), CLIP forward+backward and the optimizer step, by running the same
  functions with the autograd graph cut between the parts;
* ``points_per_iter``: the cached hits the networks evaluated (only those the images need);
* the soft floor, as before: CLIP's own forward+backward time for those 5 images plus the MLPs'
  FLOPs at the machine's matrix-multiply rate at their shapes (``soft_floor_s``);
* the true floor: the FLOPs of a step counted on real steps (matrix products by torch's
  ``FlopCounterMode``: CLIP forward and backward to the images, the MLPs forward and backward;
  pointwise FLOPs, one per output element of every op tagged pointwise: shading, activations,
  the optimizer) divided by the machine's peak matrix-multiply rate measured in float32 and in
  bfloat16 (``floor_fp32_s``, ``floor_bf16_s``), and ``ratio_to_floor = s_per_iter`` over the
  floor of what the machine runs (``floor_s``, ``floor_of``: bfloat16 only where it is native).
  The last line prints these with the precision that ran and the target (``target_s``: 0.6 s where
  the CPU runs bfloat16 natively, 1.2 s where it does not).

First, CLIP alone along its paths (open_clip's modules or the batched tower, float32 or
bfloat16 autocast): seconds and the cosines of embeddings and image gradients against open_clip
in float32. It then shows the trade between MLP width and step time, the cost of local crops, the
cost and benefit of supersampling (error of 1 and 2 samples per pixel against 4, same field), and
the CPU levers (``LEVERS``: CLIP's tower, bfloat16 for CLIP and for the networks, the compiled
renderer alone or in one graph with the networks (``compile_networks``, of free or static shapes:
``compile_static``), hash-grid encodings with
width-64 networks) on the real step, side by side, each against its own FLOP floor (its FLOPs
counted on two of its steps, at the peak rates of its precisions; ``--lever``
picks some by name; the reference always runs). ``--precision float32`` measures the main step with
both bfloat16 levers off (the defaults: ``auto``, bfloat16 where the CPU has it natively). The
floor printed last is of what this machine can run: the bfloat16 floor only where bfloat16 is
native (an emulated rate would make a floor slower than the float32 one); ``floor_of`` says which.
CLIP has random weights here (timing does not depend on them). The mesh is
``../shared/meshes/person.obj`` when present, else the built-in vase.

``--isa avx2`` runs all of it with torch held to AVX2 (``stages.core.device.AVX2_ONLY_ENV``, in a
new process: no native bfloat16, so float32 and the 1.2 s target), this CPU standing in for one
without AVX-512; the last line's ``cpu`` names what ran.

    python -m benchmarks.training.optimize [--steps 8] [--threads 2] [--precision defaults|float32] [--clip-only]
        [--no-levers] [--lever hash ...] [--isa native|avx2]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import (
    FP32,
    PARTS,
    best_of,
    build_cache,
    clip_backward,
    eager_flops,
    lever_floor,
    make_optimizer,
    matmul_rate,
    mlp_flops_per_point,
    module_command,
    paired_ratios,
    peak_matmul_rate,
    step_time,
    timed_split,
    vit_b32_random,
)
from stages.config.sections import OptimizeSettings
from stages.core.device import AVX2_ONLY_ENV, bf16_support, cpu_isa
from stages.core.provenance import Timer
from stages.guidance.clip import ClipGuide
from stages.imaging.images import compose, gather_points, global_spec
from stages.render.color import linear_to_srgb
from stages.render.products import linear, onednn_available, onednn_choice, onednn_products
from stages.training.optimizer import Optimizer

#: the target for the paper's step (width 256, 1 global image and 4 crops) on a 2-core CPU that runs
#: bfloat16 natively (AMX or AVX-512 BF16), and on one that does not (AVX2 only); the last line
#: names the one this machine is held to, decided at run time
TARGET_NATIVE_BF16_S = 0.6
TARGET_AVX2_S = 1.2


def clip_time(guide: ClipGuide, images: int, steps: int) -> float:
    text = guide.embed_text("a person")
    ts = []
    for _ in range(steps + 1):
        x = torch.rand(images, 3, 224, 224, requires_grad=True)
        t0 = time.perf_counter()
        clip_backward(guide, x, text)
        ts.append(time.perf_counter() - t0)
    return statistics.mean(ts[1:])


def clip_batching(steps: int) -> list[dict]:
    """CLIP's part of the step (the batched tower; float32, and bfloat16 where the CPU runs it
    natively) with the global image and the 4 crops through the tower apart (two calls of
    ``ClipGuide.similarity``, 50 and 200 rows per product) and as one batch (``similarities``,
    250 rows, what the step runs), measured alternately on the same images: median seconds each
    and the median of the paired ratios, and the relative difference of the image gradients."""
    x0 = torch.rand(5, 3, 224, 224, generator=torch.Generator().manual_seed(3))
    rows = []
    for bf16 in (False, True) if bf16_support(torch.device("cpu"))[0] else (False,):
        guide = vit_b32_random(bf16=bf16)
        text = guide.embed_text("a person")

        def apart(x, guide=guide, text=text):
            guide.similarity(x[:1], text).add(guide.similarity(x[1:], text)).backward()

        def together(x, guide=guide, text=text):
            clip_backward(guide, x, text)

        times, grads = {"apart": [], "together": []}, {}
        for i in range(steps + 1):
            for name, fn in (("apart", apart), ("together", together)):
                x = x0.clone().requires_grad_()
                t0 = time.perf_counter()
                fn(x)
                if i:
                    times[name].append(time.perf_counter() - t0)
                grads[name] = x.grad
        ratios = paired_ratios(times["apart"], times["together"])
        diff = float((grads["apart"] - grads["together"]).norm() / grads["apart"].norm())
        rows.append(
            {
                "precision": "bf16" if bf16 else "fp32",
                "apart_s": statistics.median(times["apart"]),
                "together_s": statistics.median(times["together"]),
                "ratio": statistics.median(ratios),
                "grad_rel_diff": diff,
            }
        )
    return rows


#: CLIP's paths compared side by side: (tower, bfloat16); the first is the reference
CLIP_PATHS = (("open_clip", False), ("batched", False), ("open_clip", True), ("batched", True))


def clip_paths(steps: int) -> list[dict]:
    """CLIP ViT-B-32 (the same random weights) along each of :data:`CLIP_PATHS`, side by side:
    forward+backward seconds for 5 images at 224 (the paper's 1 + 4 split), and the cosines of its
    image embeddings and image gradients against open_clip's own modules in float32."""
    guides = [vit_b32_random(bf16=bf16, tower=tower) for tower, bf16 in CLIP_PATHS]
    text = guides[0].embed_text("a person")
    x0 = torch.rand(5, 3, 224, 224, generator=torch.Generator().manual_seed(1))
    rows, ref = [], None
    for (tower, bf16), guide in zip(CLIP_PATHS, guides, strict=True):
        x = x0.clone().requires_grad_()
        emb = guide.embed_images(x).detach().flatten()
        clip_backward(guide, x, text)
        ref = ref or (emb, x.grad.flatten())
        cos = torch.nn.functional.cosine_similarity
        rows.append(
            {
                "tower": tower,
                "precision": guide.precision,
                "bf16": bf16,
                "s": clip_time(guide, 5, steps),
                "cos_embedding": float(cos(emb.double(), ref[0].double(), dim=0)),
                "cos_gradient": float(cos(x.grad.flatten().double(), ref[1].double(), dim=0)),
            }
        )
    return rows


#: the CPU levers measured on the real step at the paper's counts: name -> settings overrides
LEVERS = {
    "reference (open_clip tower, float32)": {"clip_tower": "open_clip", **FP32},
    "batched CLIP tower, float32": FP32,
    "float32, ATen's products (onednn_products: off)": {**FP32, "onednn_products": "off"},
    "+ bf16 CLIP": {"bf16": "on", "bf16_networks": "off"},
    "+ bf16 networks": {"bf16": "off", "bf16_networks": "on"},
    "+ bf16 CLIP and networks": {"bf16": "on", "bf16_networks": "on"},
    "defaults (bf16 auto)": {},
    "+ bf16 and compiled shading": {"bf16": "on", "bf16_networks": "on", "compile_shading": True, "compile_networks": "off"},
    "+ bf16, networks and shading in one graph": {
        "bf16": "on",
        "bf16_networks": "on",
        "compile_shading": True,
        "compile_networks": "on",
    },
    "+ bf16, one graph of static shapes": {
        "bf16": "on",
        "bf16_networks": "on",
        "compile_shading": True,
        "compile_networks": "on",
        "compile_static": "on",
    },
    "float32, compiled shading": {**FP32, "compile_shading": True, "compile_networks": "off"},
    "float32, networks and shading in one graph": {**FP32, "compile_shading": True, "compile_networks": "on"},
    "NeRF encodings, width 64": {"width": 64, **FP32},
    "hash grids, width 64": {"material_encoding": "hashgrid", "normal_encoding": "hashgrid", "width": 64, **FP32},
    "hash grids, width 64, + bf16 CLIP and networks": {
        "material_encoding": "hashgrid",
        "normal_encoding": "hashgrid",
        "width": 64,
        "bf16": "on",
        "bf16_networks": "on",
    },
    "hash grids, width 64, + bf16 and compiled shading": {
        "material_encoding": "hashgrid",
        "normal_encoding": "hashgrid",
        "width": 64,
        "bf16": "on",
        "bf16_networks": "on",
        "compile_shading": True,
        "compile_networks": "off",
    },
}


def lever_steps(train: Path, steps: int, only: list[str] | None, peak: dict[str, float], native: bool) -> dict[str, dict]:
    """The real step (``Optimizer.step``) and its split under each of :data:`LEVERS` (those whose
    name contains one of ``only``, and the reference), side by side, each with its FLOP floor
    (:func:`lever_floor`, from FLOPs counted on two of its own steps)."""
    out = {}
    for i, (name, over) in enumerate(LEVERS.items()):
        if i and only and not any(o in name for o in only):
            continue
        s = OptimizeSettings(**{"crops": 4, "width": 256, "light_lobes": 32, **over})
        guide = vit_b32_random(bf16=s.bf16, tower=s.clip_tower)
        opt = make_optimizer(s, train, guide)
        t0 = time.perf_counter()
        opt.step(Timer())  # the first step compiles (compile_shading)
        first = time.perf_counter() - t0
        t, points = step_time(opt, steps)
        split = timed_split(opt, max(2, steps // 2))
        short = {True: "bf16", False: "fp32"}
        kernels = opt.float32_products.split(" (")[0]
        path = f"clip {short[guide.bf16]}, networks {short[opt.field.bf16]}, float32 by {kernels}, shading {opt.shading_path}"
        floor = lever_floor(eager_flops(s, train, guide, 2, points), guide.bf16, opt.field.bf16, peak, native)
        out[name] = {"s": t, "first_s": first, **split, "precision": path, "floor_s": floor}
    return out


def supersampling_error(opt: Optimizer) -> dict[int, float]:
    """RMSE of the global image at 1 and 2 samples per pixel against 4 (same field, view 0)."""
    v = opt.views[0]
    out = {}
    with torch.no_grad():
        ref = None
        for spp in (4, 2, 1):
            spec = global_spec(opt.views.width, 224, spp)
            needed, (lk,) = gather_points([spec], v.index)
            sel = torch.from_numpy(needed)
            col = linear_to_srgb(opt.field(v.points[sel], v.normals[sel], v.view[sel]).shading.rgb)
            img = compose(col, lk, spec, torch.zeros(3, 224, 224))
            if ref is None:
                ref = img
            else:
                out[spp] = float(torch.sqrt(((img - ref) ** 2).mean()))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=8)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--clip-only", action="store_true", help="only CLIP's towers and precisions")
    parser.add_argument(
        "--precision",
        choices=("defaults", "float32"),
        default="defaults",
        help="the measured step (last line): the defaults (bf16 auto: bfloat16 where native) or float32",
    )
    parser.add_argument("--no-levers", action="store_true", help="skip the table of CPU levers")
    parser.add_argument("--lever", action="append", help="only the levers whose name contains this (repeatable)")
    parser.add_argument("--isa", choices=("native", "avx2"), default="native", help="avx2: torch held to AVX2 (a new process)")
    args = parser.parse_args()
    if args.isa == "avx2" and any(os.environ.get(k) != v for k, v in AVX2_ONLY_ENV.items()):
        # the same command in a new process (torch reads the variables when it loads)
        command = module_command(__spec__.name, *sys.argv[1:])
        os.execve(sys.executable, command, {**os.environ, **AVX2_ONLY_ENV})
    torch.set_num_threads(args.threads)
    print(f"# CPU {cpu_isa()}", flush=True)
    # CLIP measured alone below routes its float32 linear layers as a training step does
    routed, products = onednn_choice(OptimizeSettings().onednn_products, torch.device("cpu"))
    print(f"# float32 linear layers: {products}", flush=True)
    print("# float32 products at the step's shapes, GFLOP/s by kernel (the forward, and the two gradients' products)")
    print(f"{'product':<58}{'ATen':>8}{'oneDNN':>8}{'ratio':>7}")
    for name, rates in product_rates().items():
        ratio = rates["onednn"] / rates["aten"] if rates.get("onednn") else float("nan")
        print(f"{name:<58}{rates['aten'] / 1e9:>8.0f}{rates.get('onednn', float('nan')) / 1e9:>8.0f}{ratio:>7.2f}", flush=True)
    with onednn_products(routed):
        measure(args)


#: the float32 products of a paper step, ``name -> (rows, inner, columns)`` of ``(rows x inner) @
#: (inner x columns)``: CLIP's MLP (250 tokens) forward and its input gradient, the networks'
#: width-256 layer (24,500 points) forward and its weight gradient (the sum over the points)
STEP_PRODUCTS = {
    "CLIP MLP in, forward (250 x 768 by 768 x 3072)": (250, 768, 3072),
    "CLIP MLP in, input gradient (250 x 3072 by 3072 x 768)": (250, 3072, 768),
    "networks, forward (24500 x 256 by 256 x 256)": (24500, 256, 256),
}


def product_rates() -> dict[str, dict[str, float]]:
    """:data:`STEP_PRODUCTS` and the networks' weight gradient, FLOP/s by ATen's and by oneDNN's
    kernels (oneDNN's where this torch has it; the weight gradient by ``torch.mm`` of the
    transposed operand, as ATen runs it, and by oneDNN on the same views)."""
    out = {}
    for name, shape in STEP_PRODUCTS.items():
        out[name] = {k: matmul_rate(*shape, kernels=k) for k in ("aten", "onednn")[: 2 if onednn_available() else 1]}
    g, x = torch.randn(24500, 256), torch.randn(24500, 256)
    flops = 2.0 * 24500 * 256 * 256
    rates = {"aten": flops / best_of(lambda: g.t() @ x)}
    if onednn_available():
        with onednn_products(True):
            rates["onednn"] = flops / best_of(lambda: linear(g.t(), x.t()))
    out["networks, weight gradient (256 x 24500 by 24500 x 256)"] = rates
    return out


def measure(args: argparse.Namespace) -> None:
    """Everything :func:`main` prints after the CPU's line."""
    clip_rows = clip_paths(args.steps)
    print("# CLIP ViT-B-32 forward+backward to 5 images at 224; cosines against open_clip's modules in float32")
    print(f"{'tower':<11}{'precision':<58}{'s':>8}{'speed-up':>9}{'cos emb':>10}{'cos grad':>10}")
    for r in clip_rows:
        print(
            f"{r['tower']:<11}{r['precision'][:57]:<58}{r['s']:>8.3f}{clip_rows[0]['s'] / r['s']:>9.2f}"
            f"{r['cos_embedding']:>10.5f}{r['cos_gradient']:>10.5f}",
            flush=True,
        )
    batching = clip_batching(args.steps)
    print("# a step's 1 global image and 4 crops through CLIP's tower apart (50 + 200 rows) or as one batch (250 rows)")
    print(f"{'precision':<10}{'apart s':>9}{'one batch s':>12}{'ratio':>7}{'grad diff':>11}")
    for r in batching:
        print(f"{r['precision']:<10}{r['apart_s']:>9.3f}{r['together_s']:>12.3f}{r['ratio']:>7.2f}{r['grad_rel_diff']:>11.1e}")
    print(" ".join(f"clip_one_batch_ratio_{r['precision']}={r['ratio']:.3f}" for r in batching), flush=True)
    if args.clip_only:
        return
    with tempfile.TemporaryDirectory() as d:
        train, mesh_name = build_cache(Path(d))
        paper = OptimizeSettings(crops=4, width=256, light_lobes=32, **(FP32 if args.precision == "float32" else {}))
        guide = vit_b32_random(bf16=paper.bf16, tower=paper.clip_tower)
        opt = make_optimizer(paper, train, guide)
        f = opt.field
        c = opt.compiled
        renderer = "compiled" if c.shade_graph is not None else "eager"
        renderer = ("static graph" if c.static_points else "one graph") if c.field_graph is not None else renderer
        precision = f"clip:{'bf16' if guide.bf16 else 'fp32'},networks:{'bf16' if f.bf16 else 'fp32'},renderer:{renderer}"
        s_per_iter, points = step_time(opt, args.steps)
        split = timed_split(opt, args.steps)
        clip_s = clip_time(guide, 5, args.steps)
        rate = matmul_rate(65536, 256, 256)  # the MLPs' shapes
        flops = mlp_flops_per_point(opt.field)
        mlp_floor = flops * points / rate
        floor_s = clip_s + mlp_floor
        print(f"# mesh {mesh_name}, ray cache 512x512, torch threads {args.threads}, CLIP ViT-B-32 (random weights)")
        print(
            f"# the measured step: CLIP {guide.precision}, {guide.tower} tower; networks {opt.network_precision}; "
            f"renderer {opt.shading_path}; float32 linear layers {opt.float32_products}"
        )
        print("# paper counts: 1 view, 1 global + 4 crops at 224, width 256, 32 lobes")
        print(f"{'part':<22}{'s/iter':>10}")
        for k in ("gather", "mlp", "shading", "clip", "optimizer"):
            print(f"{k:<22}{split[k]:>10.3f}")
        print(f"{'sum of parts':<22}{sum(split[k] for k in PARTS if split[k] == split[k]):>10.3f}")  # NaN: not cut
        print(f"{'real step':<22}{s_per_iter:>10.3f}")
        print(
            f"# ceilings: CLIP fwd+bwd (5 images) {clip_s:.3f} s; "
            f"matmul {rate / 1e9:.1f} GFLOP/s at width 256; "
            f"MLPs {flops / 1e6:.2f} MFLOP/point fwd+bwd x {points:.0f} points = {mlp_floor:.3f} s"
        )
        print(f"# soft floor (CLIP's own time + MLP FLOPs at that rate) {floor_s:.3f} s; ratio {s_per_iter / floor_s:.2f}")
        # the true floor: every FLOP of a step, counted, at the machine's peak matrix-multiply rate
        counts = eager_flops(paper, train, guide, max(2, args.steps // 2), points)
        # the floor of what this machine can run: bfloat16 only where it is native (emulated
        # bfloat16 is slower than float32, and its "floor" would mean nothing; measured on a small
        # product there: 0.3 GFLOP/s, a minute for one at 2048)
        native, why = bf16_support(torch.device("cpu"))
        fp32 = {k: peak_matmul_rate(torch.float32, kernels=k) for k in ("aten", "onednn")[: 2 if onednn_available() else 1]}
        peak = {"fp32": max(fp32.values()), "bf16": peak_matmul_rate(torch.bfloat16, 2048 if native else 256)}
        floors = {k: counts["total"] / r for k, r in peak.items()}
        floor_of = "bf16" if native and floors["bf16"] < floors["fp32"] else "fp32"
        best = floors[floor_of]
        print(
            f"# counted per step: CLIP {counts['clip'] / 1e9:.2f} GFLOP (fwd+bwd to the images), MLPs "
            f"{counts['mlp'] / 1e9:.2f} GFLOP (fwd+bwd), pointwise {counts['pointwise'] / 1e9:.3f} GFLOP; "
            f"total {counts['total'] / 1e9:.2f} GFLOP"
        )
        print(
            f"# peak matmul (2048^2; bfloat16 256^2 where emulated; {args.threads} threads): "
            f"fp32 {peak['fp32'] / 1e9:.0f} GFLOP/s ({', '.join(f'{k} {v / 1e9:.0f}' for k, v in fp32.items())}), "
            f"bf16 {peak['bf16'] / 1e9:.0f} GFLOP/s ({'native' if native else 'emulated: not a floor'}); "
            f"floor fp32 {floors['fp32']:.3f} s, bf16 {floors['bf16']:.3f} s; the floor here: {floor_of} ({why}); "
            f"ratio to it {s_per_iter / best:.1f}"
        )
        # trades: width, crops, supersampling
        print(f"{'width':>6}{'crops':>6}{'spp':>5}{'points':>9}{'s/iter':>9}{'MFLOP/pt':>10}")
        rows = {}
        for width, crops, spp in ((64, 4, 1), (128, 4, 1), (256, 4, 1), (256, 0, 1), (256, 0, 2)):
            s = OptimizeSettings(crops=crops, width=width, light_lobes=32, supersample=spp)
            o = make_optimizer(s, train, guide)
            t, p = step_time(o, max(2, args.steps // 2))
            rows[(width, crops, spp)] = t
            print(f"{width:>6}{crops:>6}{spp:>5}{p:>9.0f}{t:>9.3f}{mlp_flops_per_point(o.field) / 1e6:>10.2f}")
        err = supersampling_error(opt)
        print(f"# supersampling benefit: RMSE vs 4 spp: 1 spp {err[1]:.4f}, 2 spp {err[2]:.4f}")
        if not args.no_levers:
            levers = lever_steps(train, max(3, args.steps // 2), args.lever, peak, native)
            print("# CPU levers on the real step (paper counts), side by side in this run; floor: its FLOPs at the peak")
            print("# rates above for its precisions (nan: bfloat16 emulated here, no floor)")
            head = f"{'lever':<48}{'s/iter':>8}{'x ref':>7}{'floor':>7}{'x floor':>8}{'mlp':>7}{'shading':>8}{'clip':>7}"
            print(f"{head}{'1st s':>7}  precision")
            ref_s = next(iter(levers.values()))["s"]
            for name, r in levers.items():
                print(
                    f"{name:<48}{r['s']:>8.3f}{ref_s / r['s']:>7.2f}{r['floor_s']:>7.3f}{r['s'] / r['floor_s']:>8.2f}"
                    f"{r['mlp']:>7.3f}{r['shading']:>8.3f}{r['clip']:>7.3f}{r['first_s']:>7.1f}"
                    f"  {r['precision']}",
                    flush=True,
                )
    kv = {
        "s_per_iter": s_per_iter,
        "clip_s": clip_s,
        "points_per_iter": points,
        "mlp_s": split["mlp"],
        "shading_s": split["shading"],
        "gather_s": split["gather"],
        "optimizer_s": split["optimizer"],
        "matmul_gflops": rate / 1e9,
        "mlp_mflop_per_point": flops / 1e6,
        "soft_floor_s": floor_s,
        "clip_gflop": counts["clip"] / 1e9,
        "mlp_gflop": counts["mlp"] / 1e9,
        "pointwise_gflop": counts["pointwise"] / 1e9,
        "peak_fp32_gflops": peak["fp32"] / 1e9,
        **{f"peak_fp32_{k}_gflops": v / 1e9 for k, v in fp32.items()},
        "peak_bf16_gflops": peak["bf16"] / 1e9,
        "s_per_iter_width64": rows[(64, 4, 1)],
        "s_per_iter_nocrops": rows[(256, 0, 1)],
        "s_per_iter_nocrops_spp2": rows[(256, 0, 2)],
        "rmse_spp1_vs_spp4": err[1],
        "rmse_spp2_vs_spp4": err[2],
        **{f"clip_{r['tower']}_{'bf16' if r['bf16'] else 'fp32'}_s": r["s"] for r in clip_rows},
        "clip_cos_embedding_bf16": clip_rows[-1]["cos_embedding"],
        "clip_cos_gradient_bf16": clip_rows[-1]["cos_gradient"],
    }
    print(" ".join(f"{k}={v:.4g}" for k, v in kv.items()))
    # the last line: the figures the speed issue asks for, and the precision that ran
    last = {
        "s_per_iter": s_per_iter,
        "target_s": TARGET_NATIVE_BF16_S if bf16_support(torch.device("cpu"))[0] else TARGET_AVX2_S,
        "floor_s": best,
        "ratio_to_floor": s_per_iter / best,
        "floor_fp32_s": floors["fp32"],
    }
    if native:
        last["floor_bf16_s"] = floors["bf16"]
    print(" ".join(f"{k}={v:.4g}" for k, v in last.items()) + f" floor_of={floor_of} precision={precision} cpu={cpu_isa()}")


if __name__ == "__main__":
    with np.errstate(all="ignore"):  # (scoped: the docs' tests run this script in-process)
        main()
