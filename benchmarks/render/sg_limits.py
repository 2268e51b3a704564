"""What TANGO's SG model cannot represent, measured against Mitsuba on the held-out metric views.

For each mesh and material: Mitsuba's full path-traced target, the same scene with direct light
only (no interreflection), direct light without visibility (no shadows), and our SG renderer
with the *true* material and normals under the SG light fitted to the target through it (the
best a perfect optimisation of the model could reach). Prints the error budget in mean squared
sRGB error over fully covered object pixels, Mitsuba's own noise taken out (see
``stages/reference/limits.py``).

    python -m benchmarks.render.sg_limits                       # built-in meshes
    python -m benchmarks.render.sg_limits --shared bunny horse  # also meshes of ../shared/meshes
    python -m benchmarks.render.sg_limits --builtin candle:metal --brdf tango,gltf   # both BRDFs (default)
    python -m benchmarks.render.sg_limits --builtin knot:wood --visibility off,on    # our renderer's shadows
    python -m benchmarks.render.sg_limits --builtin --shared horse --faces full,0.1,5000   # decimated levels

With ``--visibility on`` our renderer casts shadows (1024 stored directions, shadow rays for
lobes too sharp for them), and each line adds how closely like agrees with like: ours shadowed
against Mitsuba's direct light, ours unshadowed against its unshadowed light.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import SHARED_MESHES


def main() -> None:
    from stages.config.sections import NormalizeSettings, RaycacheSettings, TargetSettings
    from stages.geometry.normalization import normalize_mesh
    from stages.geometry.raycache import RayCache, metric_views, trace_views
    from stages.geometry.tracing import EmbreeTracer
    from stages.reference.limits import measure_limits
    from stages.reference.targets import TargetRenderer

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--builtin", nargs="*", default=["vase:wood", "candle:plaster", "knot:wood", "vase:metal"])
    parser.add_argument("--shared", nargs="*", default=[], help="names in ../shared/meshes (wood)")
    parser.add_argument("--spp", type=int, default=128)
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--lobes", type=int, nargs="*", default=[32])
    parser.add_argument("--brdf", default="tango,gltf", help="the model's BRDFs, comma-separated (tango, gltf)")
    parser.add_argument("--visibility", default="off", help="our renderer's shadows, comma-separated (off, on)")
    parser.add_argument("--directions", type=int, default=1024, help="stored visibility directions (shadows cast)")
    parser.add_argument("--shadow-samples", type=int, default=64, help="shadow rays per lobe too sharp for the directions")
    parser.add_argument(
        "--faces",
        default="full",
        help="levels of each mesh, comma-separated: full, a fraction of its faces (0.1) or a face count (5000), "
        "each decimated by the decimate stage's collapse from the normalised mesh",
    )
    parser.add_argument("--normals", default="smooth", help="the truth's and our shading normals: smooth or flat")
    args = parser.parse_args()
    shadowed = [v == "on" for v in args.visibility.split(",") if v]
    brdfs = [b for b in args.brdf.split(",") if b]
    cases = [(f"builtin:{c.split(':')[0]}", c.split(":")[1]) for c in args.builtin]
    cases += [(str(SHARED_MESHES / f"{n}.obj"), "wood") for n in args.shared]
    rc = RaycacheSettings(metrics_resolution=args.resolution)
    print(f"metric views: {len(metric_views(rc))} at {args.resolution} px; Mitsuba at {args.spp} spp per render")
    levels = [f for f in args.faces.split(",") if f]
    for (source, material), level in ((c, f) for c in cases for f in levels):
        t0 = time.perf_counter()
        mesh, quality = mesh_level(normalize_mesh(source, NormalizeSettings()).mesh, level)
        arrays, _ = trace_views(mesh, metric_views(rc), EmbreeTracer(mesh))
        with tempfile.TemporaryDirectory() as d:
            np.savez(Path(d) / "m.npz", **arrays)
            cache = RayCache(Path(d) / "m.npz")
            renderer = TargetRenderer(mesh, material, TargetSettings(texture_size=1024, shading_normals=args.normals))
            for brdf, vis in ((b, v) for b in brdfs for v in shadowed):
                r = measure_limits(
                    renderer,
                    cache,
                    args.spp,
                    tuple(args.lobes),
                    brdf=brdf,
                    visibility=vis,
                    directions=args.directions,
                    shadow_samples=args.shadow_samples,
                )
                stem = Path(source).stem if "/" in source else source[8:]
                name = f"{stem} ({len(mesh.faces)} faces{quality}), {material}, {brdf} BRDF"
                name += ", shadows cast" if vis else ""
                parts = []
                for k in args.lobes:
                    lk = r[f"lobes_{k}"]
                    sh = lk["share"]
                    parts.append(
                        f"{k} lobes: {lk['psnr_db']['target']:.2f} dB (error {lk['error_mse']['target']:.2e} = "
                        f"interreflection {100 * sh['interreflection']:.0f}% + shadows {100 * sh['shadows']:.0f}% + "
                        f"BRDF/light/closed form {100 * sh['brdf_light_and_closed_form']:.0f}%)"
                    )
                    if vis:
                        ag = lk["agreement_db"]
                        parts[-1] += f", like with like: shadowed {ag['shadowed']:.2f} dB, unshadowed {ag['unshadowed']:.2f} dB"
                if vis:
                    so = r["self_occlusion"]
                    parts.append(
                        f"self-occlusion mean {so['mean']:.3f}, median {so['median']:.3f}, p95 {so['p95']:.3f}; "
                        f"visibility ({args.directions} directions, {args.shadow_samples} rays per sharp lobe) "
                        f"traced in {r['visibility']['seconds']:.1f} s"
                    )
                print(
                    f"{name}: noise {r['noise_mse']:.1e}, interreflection {r['interreflection_mse']:.2e}, "
                    f"shadows {r['shadows_mse']:.2e}; " + "; ".join(parts) + f"; {time.perf_counter() - t0:.0f} s",
                    flush=True,
                )


def mesh_level(mesh, level: str):
    """``mesh`` at ``level`` (``full``, a fraction of its faces or a face count), and a text of the
    decimation's quality: Hausdorff distance both ways (normalised frame) and the shares of
    slivers and folds (:func:`stages.geometry.decimation.shape_quality`)."""
    from stages.config.sections import DecimateSettings
    from stages.geometry.decimation import decimate_mesh, shape_quality

    def text(q: dict) -> str:
        return f"slivers {100 * q['slivers']:.1f}%, folds {100 * q['folds']:.2f}%"

    if level == "full":
        return mesh, f"; {text(shape_quality(mesh))}"
    target = round(float(level) * len(mesh.faces)) if float(level) < 1 else int(level)
    result = decimate_mesh(mesh, DecimateSettings(target_faces=target))
    return result.mesh, f", Hausdorff {result.stats['hausdorff_max']:.4f}; {text(result.stats['shape_after'])}"


if __name__ == "__main__":
    main()
