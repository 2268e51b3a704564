"""The ``fast`` preset's step with shadows, split, and the shadows' visible shares both ways.

On the built-in vase (a ray cache of ``--views`` views at 512 pixels with the default visibility:
512 directions per hit), CLIP ViT-B-32 at 224 with random weights, the ``fast`` preset under the
defaults (``bf16: auto``) and in float32:

* ``step_s``: the real training step (``Optimizer.step``), mean of ``--steps`` after a warm-up;
* its split (``benchmarks.common.timed_split``: gather, networks, shading with the
  shadows' shares, CLIP, optimiser) with the graph cut between the parts;
* the renderer alone at 17,000 points and 16 lobes, eager and compiled (``compile_shading``),
  with the compilation's seconds and the steps that repay it (``--shading-only``: this alone);
* the shadows' shares at the paper's step size (24,500 points, 32 lobes, the default 512 stored
  directions), float32 products against
  bfloat16 products (the training's under ``bf16_networks``): seconds and agreement (also with
  ``--shading-only``);
* the shadows' shares at the step's points, forward and forward+backward, by the fused blocks
  (``lobe_visibility_bits``, the training's path; float32 and bfloat16 products) and by the matrix
  form (``lobe_visibility``, the plain reference), side by side.

    python -m benchmarks.training.fast_step [--views 8] [--steps 6] [--threads 2] [--shading-only]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from benchmarks.common import PARTS, best_of, make_optimizer, step_time, timed_split, vit_b32_random


def shares_side_by_side(opt) -> dict[str, float]:
    """Seconds of the shadows' shares at view 0's first 17,000 hits (about a fast step's points)."""
    import torch

    from stages.render.visibility import lobe_visibility, lobe_visibility_bits, unpack_bits

    shadows = opt.views[0].shadows
    idx = torch.arange(min(17_000, len(shadows)))
    bits, normal = shadows._bits[idx], shadows._normals[idx]
    dirs = shadows._dirs
    out = {"points": float(len(idx)), "directions": float(len(dirs))}
    for name, fn, bf16 in (
        ("fused", lambda a, s: lobe_visibility_bits(normal, bits, dirs, a, s), False),
        ("fused_bf16", lambda a, s: lobe_visibility_bits(normal, bits, dirs, a, s), True),
        ("matrix", lambda a, s: lobe_visibility(normal, unpack_bits(bits, len(dirs)), dirs, a, s), False),
    ):

        def forward(fn=fn, bf16=bf16):
            with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
                light = opt.field.light.sg()
                fn(light.axis, light.sharpness)

        def both(fn=fn, bf16=bf16):
            light = opt.field.light.sg()
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
                share = fn(light.axis, light.sharpness)
            share.sum().backward()

        out[f"{name}_fwd_s"], out[f"{name}_fwd_bwd_s"] = best_of(forward), best_of(both)
    return out


def shares_precision_side_by_side(points: int, lobes: int) -> dict[str, float]:
    """The shadows' shares (``lobe_visibility_bits``, the ray cache's default number of stored
    directions, ``raycache.visibility_directions``) at ``points`` random points,
    each beside a random wall (a half-space of directions blocked), and ``lobes`` lobes of
    sharpness 1 to 1,000, forward and backward: float32 products against bfloat16 products (the
    training's under ``bf16_networks``), seconds and agreement (largest share difference, cosine
    of the gradients to the lobes' axes and sharpnesses), side by side."""
    import math

    import numpy as np
    import torch

    from stages.config.sections import RaycacheSettings
    from stages.geometry.visibility import fibonacci_directions
    from stages.render.visibility import lobe_visibility_bits

    gen = torch.Generator().manual_seed(0)
    dirs = torch.from_numpy(fibonacci_directions(RaycacheSettings().visibility_directions)).float()
    normal = torch.nn.functional.normalize(torch.randn(points, 3, generator=gen), dim=-1)
    wall = torch.nn.functional.normalize(torch.randn(points, 3, generator=gen), dim=-1)
    bits = torch.from_numpy(np.packbits(((wall @ dirs.T) > 0.2).numpy(), axis=1))
    axis = torch.nn.functional.normalize(torch.randn(lobes, 3, generator=gen), dim=-1)
    lam = torch.exp(torch.rand(lobes, 1, generator=gen) * math.log(1e3))
    weight = torch.rand(points, lobes, generator=gen)
    results = {}

    def once(bf16: bool):
        a, s_ = axis.clone().requires_grad_(), lam.clone().requires_grad_()
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            share = lobe_visibility_bits(normal, bits, dirs, a, s_)
        (share * weight).sum().backward()
        results[bf16] = (share.detach(), a.grad.flatten(), s_.grad.flatten())

    out = {"fp32_s": best_of(lambda: once(False)), "bf16_s": best_of(lambda: once(True))}
    (v32, *g32), (v16, *g16) = results[False], results[True]
    cosines = [float(torch.nn.functional.cosine_similarity(a, b, dim=0)) for a, b in zip(g32, g16, strict=True)]
    return out | {"max_diff": float((v32 - v16).abs().max()), "grad_cos": min(cosines), "directions": len(dirs)}


def shading_side_by_side(points: int, lobes: int) -> dict[str, float]:
    """The renderer the training runs (glTF's BRDF, the fitted lobe, each lobe's visible share),
    forward and backward at ``points`` random points and ``lobes`` lobes: eager, and compiled
    (``compile_shading``: the first call's seconds are the compilation, from inductor's disk cache
    when it is warm), side by side in this process."""
    import torch

    from stages.model.field import shade_material
    from stages.model.lights.sg import SGLightModule
    from stages.model.networks import Material
    from stages.render.light import Light

    gen = torch.Generator().manual_seed(0)
    normal = torch.nn.functional.normalize(torch.randn(points, 3, generator=gen), dim=-1)
    view = torch.nn.functional.normalize(normal + torch.randn(points, 3, generator=gen), dim=-1)
    view = torch.where((view * normal).sum(-1, keepdim=True) < 0, -view, view)
    inputs = [normal, view, torch.rand(points, 3, generator=gen), torch.rand(points, 1, generator=gen)]
    inputs += [torch.rand(points, 1, generator=gen) * 0.9 + 0.1, torch.rand(points, lobes, generator=gen)]
    light = SGLightModule(lobes)

    def once(fn) -> None:
        n, v, base, metallic, rough, shares = (t.detach().requires_grad_() for t in inputs)
        out = fn(n, v, Material.gltf(base, metallic, rough), Light.of(light()), "fitted", (shares,))
        (out.diffuse.sum() + out.specular.sum()).backward()

    from stages.core.device import use_inductor_cache
    from stages.model.compiled import compiled_shade_material

    use_inductor_cache()  # the training's own cache folder
    compiled = compiled_shade_material("gltf", torch.device("cpu"))  # as training compiles it
    t0 = time.perf_counter()
    once(compiled)
    first = time.perf_counter() - t0
    return {"eager_s": best_of(lambda: once(shade_material)), "compiled_s": best_of(lambda: once(compiled)), "compile_s": first}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--views", type=int, default=8)
    parser.add_argument("--steps", type=int, default=6)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--shading-only", action="store_true", help="only the renderer, eager against compiled")
    args = parser.parse_args()
    import torch

    from stages.config.presets import PRESETS
    from stages.config.sections import NormalizeSettings, OptimizeSettings, RaycacheSettings
    from stages.geometry.meshio import save_ply
    from stages.geometry.normalization import normalize_mesh
    from stages.raycache import run as raycache_run

    torch.set_num_threads(args.threads)
    rd = shading_side_by_side(17_000, 16)
    renderer = (
        f"shading_eager_s={rd['eager_s']:.4g} shading_compiled_s={rd['compiled_s']:.4g} compile_s={rd['compile_s']:.3g} "
        f"repaid_after_steps={rd['compile_s'] / max(rd['eager_s'] - rd['compiled_s'], 1e-9):.0f}"
    )
    print(
        f"# the renderer at 17,000 points and 16 lobes (glTF, fitted lobe, shadows' shares), forward and backward: "
        f"eager {rd['eager_s']:.3f} s, compiled {rd['compiled_s']:.3f} s ({rd['eager_s'] / rd['compiled_s']:.2f}x) "
        f"after a compilation of {rd['compile_s']:.1f} s",
        flush=True,
    )
    sp = shares_precision_side_by_side(24_500, 32)
    shares = (
        f"shares_fp32_s={sp['fp32_s']:.4g} shares_bf16_s={sp['bf16_s']:.4g} shares_bf16_max_diff={sp['max_diff']:.3g} "
        f"shares_bf16_grad_cos={sp['grad_cos']:.6f}"
    )
    print(
        f"# the shadows' shares at the paper's step size (24,500 points, 32 lobes, {sp['directions']} directions), forward and "
        f"backward: float32 products {sp['fp32_s']:.3f} s, bfloat16 products {sp['bf16_s']:.3f} s "
        f"({sp['fp32_s'] / sp['bf16_s']:.2f}x); largest share difference {sp['max_diff']:.4f}, gradients' cosine "
        f"{sp['grad_cos']:.6f}",
        flush=True,
    )
    if args.shading_only:
        print(renderer, shares)
        return
    with tempfile.TemporaryDirectory() as d:
        work = Path(d)
        t0 = time.perf_counter()
        save_ply(work / "mesh.ply", normalize_mesh("builtin:vase", NormalizeSettings()).mesh)
        cache = RaycacheSettings(views=args.views)
        raycache_run(work / "mesh.ply", work / "train.npz", work / "eval.npz", work / "rc.json", cache)
        print(f"# built-in vase, {args.views} views at 512 with visibility: {time.perf_counter() - t0:.0f} s", flush=True)
        rows = {}
        for label, over in (("defaults", {}), ("float32", {"bf16": "off", "bf16_networks": "off"})):
            s = OptimizeSettings(**{**PRESETS["fast"], **over})
            guide = vit_b32_random(bf16=s.bf16, tower=s.clip_tower)
            opt = make_optimizer(s, work / "train.npz", guide)
            step, points = step_time(opt, args.steps)
            split = timed_split(opt, args.steps)
            rows[label] = {"step_s": step, "points": points, **{k: split[k] for k in PARTS}}
            print(
                f"{label:<9} step {step:.3f} s at {points:.0f} points; "
                + ", ".join(f"{k} {split[k]:.3f}" for k in PARTS)
                + f"  (clip {guide.precision.split(' (')[0]}, networks {opt.network_precision.split(' (')[0]})",
                flush=True,
            )
        sh = shares_side_by_side(opt)
        print(
            f"# shadows' shares at {sh['points']:.0f} points, 16 lobes, {sh['directions']:.0f} directions: fused blocks "
            f"{sh['fused_fwd_s']:.3f} s forward, {sh['fused_fwd_bwd_s']:.3f} s with the backward (bfloat16 products "
            f"{sh['fused_bf16_fwd_s']:.3f} s, {sh['fused_bf16_fwd_bwd_s']:.3f} s); matrix form "
            f"{sh['matrix_fwd_s']:.3f} s, {sh['matrix_fwd_bwd_s']:.3f} s"
        )
    d_, f_ = rows["defaults"], rows["float32"]
    print(
        f"step_s={d_['step_s']:.4g} step_float32_s={f_['step_s']:.4g} shading_s={d_['shading']:.4g} "
        f"clip_s={d_['clip']:.4g} shares_fused_s={sh['fused_fwd_bwd_s']:.4g} shares_matrix_s={sh['matrix_fwd_bwd_s']:.4g} "
        f"shares_speedup={sh['matrix_fwd_bwd_s'] / sh['fused_fwd_bwd_s']:.3g} {renderer} {shares}"
    )


if __name__ == "__main__":
    main()
