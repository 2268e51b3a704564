"""Mitsuba's two CPU variants side by side on the target stage's own scene: what a machine without
libLLVM 16+ (``scalar_rgb``) pays against one with it (``llvm_ad_rgb``).

The built-in mesh is normalised, its metric views traced, and the target scene (principled BSDF
with textures and a normal map, ``builtin:sun_sky``, path tracer) rendered through the same views
in each variant, in one process; prints seconds, samples per second (whole images, as the target
stage counts them), the ratio, and the doctor's probe rate for each variant (what its estimate
uses). Needs libLLVM 16+ for the second variant: a system one (Debian: apt-get install
libllvm19) or the ``karellen-llvm-core`` wheel the ``reference`` extra installs; it prints which.
To measure the wheel's on a machine that also has a system one, hide the system folders:

    python -m benchmarks.render.mitsuba_variants [--mesh vase] [--views 4] [--resolution 128] [--spp 64]
    TANGO_LIBLLVM_DIRS= python -m benchmarks.render.mitsuba_variants    # the wheel's libLLVM
"""

from __future__ import annotations

import argparse
import platform
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np


def main() -> None:
    from stages.config.sections import NormalizeSettings, RaycacheSettings, TargetSettings
    from stages.geometry.normalization import normalize_mesh
    from stages.geometry.raycache import RayCache, metric_views, trace_views
    from stages.geometry.tracing import EmbreeTracer
    from stages.reference.mitsuba import locate_libllvm
    from stages.reference.targets import TargetRenderer, probe

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", default="vase", help="a built-in mesh")
    parser.add_argument("--views", type=int, default=4, help="metric views rendered (azimuths at elevation 0)")
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--spp", type=int, default=64)
    args = parser.parse_args()
    lib = locate_libllvm()
    if lib is None:
        raise SystemExit("no libLLVM 16+ for llvm_ad_rgb (pip install karellen-llvm-core); nothing to compare")
    mesh = normalize_mesh(f"builtin:{args.mesh}", NormalizeSettings()).mesh
    rc = RaycacheSettings(metrics_azimuths=args.views, metrics_elevations_deg=(0.0,), metrics_resolution=args.resolution)
    arrays, _ = trace_views(mesh, metric_views(rc), EmbreeTracer(mesh))
    print(
        f"{datetime.now(UTC):%Y-%m-%d %H:%M} UTC, {platform.processor() or platform.machine()}, "
        f"{args.mesh} ({len(mesh.faces)} faces): {args.views} views at {args.resolution} px, {args.spp} spp; "
        f"llvm_ad_rgb with {lib.describe()}"
    )
    rates = {}
    with tempfile.TemporaryDirectory() as d:
        np.savez(Path(d) / "m.npz", **arrays)
        cache = RayCache(Path(d) / "m.npz")
        for variant in ("scalar_rgb", "llvm_ad_rgb"):
            settings = TargetSettings(variant=variant, texture_size=512)
            renderer = TargetRenderer(mesh, "wood", settings)
            renderer.render_cache(cache, 2, 0)  # warm-up: scene upload and, for LLVM, kernel compilation
            t0 = time.perf_counter()
            renderer.render_cache(cache, args.spp, 1)
            seconds = time.perf_counter() - t0
            rates[variant] = 2 * args.views * args.resolution**2 * (args.spp // 2) / seconds
            probed = probe(settings)
            print(
                f"  {variant:<12} {seconds:7.2f} s  {rates[variant] / 1e6:6.2f} M samples/s  "
                f"(the doctor's probe: {probed.samples_per_second / 1e6:.2f} M samples/s)"
            )
    print(f"  llvm_ad_rgb / scalar_rgb: {rates['llvm_ad_rgb'] / rates['scalar_rgb']:.2f}x the samples per second")


if __name__ == "__main__":
    main()
