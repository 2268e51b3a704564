"""Image-target recovery: held-out object-pixel PSNR/SSIM and the recovered material's error.

Two kinds of targets, one fit (300 iterations, the sweep's base settings: the protocol of
``stages.testing.recovery``, which ``tests/training/test_optimize.py`` also imports, so the
measured figures and the tests' floors come from one definition):

* **Mitsuba ground truth** (the default ``target_renderer``): the target stage path-traces the
  mesh in a principled material with textures and a normal map under a sun and sky; graded on the
  held-out metric views over fully covered object pixels, with the material's error;
* **our own SG renders** (``target_renderer: sg``), kept as a regression check of the optimiser:
  a procedural material under an SG light, graded on the evaluation views (the renderer grades
  itself, so these figures say nothing about the renderer).

    python -m benchmarks.quality.image_targets            # every case
    python -m benchmarks.quality.image_targets --mitsuba  # the Mitsuba cases only
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from stages.testing.recovery import MITSUBA_TARGET, recover_mitsuba, recover_sg

#: (name, mesh, material, optimize overrides); the target settings are the test's
MITSUBA_CASES = (
    ("vase, wood, normal network on", "builtin:vase", "wood", {"normal_network": True}),
    ("vase, wood, no normal network", "builtin:vase", "wood", {}),
    ("vase, metal, normal network on", "builtin:vase", "metal", {"normal_network": True}),
    ("candle, plaster, normal network on", "builtin:candle", "plaster", {"normal_network": True}),
    ("knot, wood, normal network on", "builtin:knot", "wood", {"normal_network": True}),
)
SG_CASES = (
    ("studio light (4 lobes, representable), no normal network", {}),
    ("sky light (97 lobes), normal network on", {"target_light": "sky", "normal_network": True}),
)


def _scaled(mat: dict) -> str:
    """The albedo error after its scale, or why there is none (a black, metallic truth)."""
    if mat["albedo_rmse_scaled"] is None:
        return "no scale: the true albedo is black"
    return f"{mat['albedo_rmse_scaled']:.3f} after scale {mat['albedo_scale']:.2f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mitsuba", action="store_true", help="only the Mitsuba cases")
    parser.add_argument("--cases", default="", help="comma-separated indices of the Mitsuba cases to run")
    args = parser.parse_args()
    picks = [int(i) for i in args.cases.split(",") if i] or range(len(MITSUBA_CASES))
    for k in picks:
        name, mesh, material, overrides = MITSUBA_CASES[k]
        with tempfile.TemporaryDirectory() as d:
            t0 = time.perf_counter()
            r = recover_mitsuba(Path(d), mesh, material, MITSUBA_TARGET, **overrides)
            it, mat = r["metrics"], r["metrics"]["material"]
            print(
                f"Mitsuba targets, {name}: PSNR {it['psnr_db']:.2f} dB, SSIM {it['ssim']:.3f} "
                f"(target noise {it['target_noise_psnr_db']:.1f} dB); albedo RMSE {mat['albedo_rmse']:.3f} "
                f"({_scaled(mat)}), roughness MAE "
                f"{mat.get('roughness_mae', float('nan')):.3f}, specular RMSE {mat.get('specular_rmse', float('nan')):.3f}, "
                f"normal {mat['normal_angle_deg_mean']:.1f} deg, light energy ratio "
                f"{'/'.join(f'{x:.2f}' for x in mat['light_energy_ratio'])}; {time.perf_counter() - t0:.0f} s",
                flush=True,
            )
    if args.mitsuba:
        return
    for name, overrides in SG_CASES:
        with tempfile.TemporaryDirectory() as d:
            t0 = time.perf_counter()
            meta = recover_sg(Path(d), **overrides)
            print(
                f"SG self-check, {name}: {meta['eval_psnr_db']:.2f} dB object-pixel PSNR, {time.perf_counter() - t0:.0f} s",
                flush=True,
            )


if __name__ == "__main__":
    main()
