"""Our closed-form SG shading against Mitsuba on the same scene, split into diffuse and specular,
as a function of n . v and roughness.

The scene: a unit icosphere (flat faces, 81,920 of them) seen through one of our cameras; a given
SG light (the procedural ``studio`` light, four lobes) written as an equirectangular map for
Mitsuba's ``envmap``; a white Lambertian surface (Mitsuba's ``diffuse``) for the diffuse term and
TANGO's microfacet BRDF evaluated exactly per direction (``stages/reference/tango_bsdf.py``) for
the specular term, for each roughness and ``F0``. Mitsuba path-traces one bounce (a convex
sphere neither shadows nor lights itself); we evaluate ``diffuse_radiance`` and
``specular_radiance`` (and the ``split_sum`` and ``fitted`` options' ``specular_radiance_split_sum``
and ``specular_radiance_fitted``, printed under each row) at the ray cache's hits, the very pixels Mitsuba rendered.

Per bin of ``n . v`` it prints ``sum(ours) / sum(Mitsuba) - 1`` over fully covered pixels, with
Mitsuba's Monte Carlo standard error of that ratio (from two independent halves), and saves a
plot. This is the reference the anisotropic-lobe work is judged by.

    python -m benchmarks.render.shading_vs_mitsuba --out docs/figures/shading_vs_mitsuba.png
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from benchmarks.common import RESULTS

ROUGHNESS = (0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 1.0)
F0 = (0.04, 0.9)
NV_EDGES = (0.02, 0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 0.9, 1.0)


def main() -> None:
    import torch

    from stages.geometry.raycache import RayCache, ViewSet, trace_views
    from stages.geometry.tracing import EmbreeTracer
    from stages.model.procedural import procedural_light
    from stages.reference import tango_bsdf
    from stages.reference.mitsuba import choose_variant, import_mitsuba, sensor
    from stages.reference.targets import ENV_TO_WORLD, _mesh, mitsuba_rows
    from stages.render.brdf.tango import TANGO
    from stages.render.envmap import equirect_directions
    from stages.render.fitted_lobe import specular_radiance_fitted
    from stages.render.isotropic_lobe import specular_radiance
    from stages.render.shading import diffuse_radiance
    from stages.render.split_sum import specular_radiance_split_sum

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=256)
    parser.add_argument("--spp", type=int, default=256)
    parser.add_argument("--env-height", type=int, default=512)
    parser.add_argument("--out", type=Path, default=RESULTS / "shading_vs_mitsuba.png")
    args = parser.parse_args()
    t_start = time.perf_counter()

    import trimesh

    from stages.geometry.meshio import TriMesh

    s = trimesh.creation.icosphere(subdivisions=6, radius=1.0)
    mesh = TriMesh(np.asarray(s.vertices, np.float64), np.asarray(s.faces, np.int64))
    views = ViewSet(np.array([0.3]), np.array([0.2]), np.array([3.0]), 45.0, args.width, 0.3, 0.2)
    c2w = views.c2w[0]
    import tempfile

    arrays, _ = trace_views(mesh, views, EmbreeTracer(mesh))
    with tempfile.TemporaryDirectory() as d:
        np.savez(Path(d) / "c.npz", **arrays)
        hits = RayCache(Path(d) / "c.npz").view(0)
    n = hits.normal.astype(np.float64)
    v = -hits.direction.astype(np.float64)
    flip = (n * v).sum(1) < 0
    n[flip] = -n[flip]
    nv = (n * v).sum(1)

    light = procedural_light("studio", dtype=torch.float64)
    h = args.env_height
    env = light.radiance(equirect_directions(h, 2 * h).double().reshape(-1, 3)).reshape(h, 2 * h, 3).numpy()

    variant = choose_variant("auto")
    mi = import_mitsuba(variant)
    plugin = tango_bsdf.register(mi)
    emitter = {
        "type": "envmap",
        "bitmap": mi.Bitmap(np.ascontiguousarray(mitsuba_rows(env))),
        "to_world": mi.ScalarTransform4f(ENV_TO_WORLD.tolist()),
    }
    integrator = mi.load_dict({"type": "path", "max_depth": 2, "hide_emitters": True})
    cam = mi.load_dict(sensor(c2w, 45.0, args.width, args.spp // 2, centred=False, alpha=True, mi=mi))

    def render(bsdf: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        scene = mi.load_dict(
            {"type": "scene", "object": _mesh(mi, mesh, np.zeros((len(mesh.faces), 3, 2)), mi.load_dict(bsdf)), "light": emitter}
        )
        halves = []
        for seed in (0, 1):
            img = np.array(mi.render(scene, sensor=cam, integrator=integrator, seed=seed, spp=args.spp // 2), np.float64)
            halves.append(img.reshape(-1, 4)[hits.pixel])
        alpha = halves[0][:, 3]
        return halves[0][:, :3], halves[1][:, :3], alpha

    def table(ours: np.ndarray, a: np.ndarray, b: np.ndarray, full: np.ndarray) -> list[tuple[float, float, int]]:
        rows = []
        ref = 0.5 * (a + b)
        for lo, hi in zip(NV_EDGES[:-1], NV_EDGES[1:], strict=True):
            m = full & (nv >= lo) & (nv < hi)
            if m.sum() < 20:
                rows.append((np.nan, np.nan, int(m.sum())))
                continue
            ratio = ours[m].sum() / ref[m].sum() - 1.0
            # the halves' ratio spread estimates the Monte Carlo error of the mean's ratio
            se = abs(a[m].sum() - b[m].sum()) / (2.0 * ref[m].sum())
            rows.append((float(ratio), float(se), int(m.sum())))
        return rows

    def show(title: str, rows) -> None:
        cells = " ".join(f"{100 * r:+6.1f}%(±{100 * e:.1f})" if np.isfinite(r) else "     n/a      " for r, e, _ in rows)
        print(f"{title:<28} {cells}", flush=True)

    header = " ".join(f"[{lo:.2f},{hi:.2f})".center(14) for lo, hi in zip(NV_EDGES[:-1], NV_EDGES[1:], strict=True))
    print(f"Mitsuba {mi.__version__} ({variant}), {args.spp} spp, {args.width}x{args.width}; n.v bins: pixels")
    print(f"{'':<28} {header}")
    tn, tv = torch.from_numpy(n), torch.from_numpy(v)
    a, b, alpha = render({"type": "diffuse", "reflectance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}})
    full = alpha > 0.999
    ours_d = diffuse_radiance(tn, torch.ones_like(tn), light).numpy()
    results = {"diffuse": table(ours_d, a, b, full)}
    show("diffuse", results["diffuse"])
    for f0 in F0:
        for r in ROUGHNESS:
            a, b, _ = render({"type": plugin, "f0": f0, "roughness": r})
            spec = torch.full_like(tn, f0)
            rough = torch.full((len(tn), 1), r, dtype=torch.float64)
            ours_s = specular_radiance(tn, tv, spec, rough, light).numpy()
            key = f"specular F0 {f0} r {r}"
            results[key] = table(ours_s, a, b, full)
            show(key, results[key])
            # the split-sum option (exact energy, the isotropic lobe's shape) on the same render
            ours_ss = specular_radiance_split_sum(tn, tv, spec, rough, light, TANGO).numpy()
            show(f"  split sum F0 {f0} r {r}", table(ours_ss, a, b, full))
            # the fitted option (exact energy, moment-fitted lobe corrected by the BRDF per light lobe)
            ours_fit = specular_radiance_fitted(tn, tv, spec, rough, light, TANGO).numpy()
            show(f"  fitted    F0 {f0} r {r}", table(ours_fit, a, b, full))
    print(f"pixels per bin: {[c for _, _, c in results['diffuse']]}; {time.perf_counter() - t_start:.0f} s")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    centres = [0.5 * (lo + hi) for lo, hi in zip(NV_EDGES[:-1], NV_EDGES[1:], strict=True)]
    fig, axes = plt.subplots(1, 1 + len(F0), figsize=(5 * (1 + len(F0)), 3.8), sharey=True)
    axes[0].errorbar(
        centres, [100 * r for r, _, _ in results["diffuse"]], [100 * e for _, e, _ in results["diffuse"]], marker="o"
    )
    axes[0].set_title("diffuse (any roughness)")
    for ax, f0 in zip(axes[1:], F0, strict=True):
        for r in ROUGHNESS:
            rows = results[f"specular F0 {f0} r {r}"]
            ax.errorbar(centres, [100 * x for x, _, _ in rows], [100 * e for _, e, _ in rows], marker=".", label=f"r {r}")
        ax.set_title(f"specular, F0 = {f0}")
        ax.legend(fontsize=7)
    for ax in axes:
        ax.axhline(0, color="k", lw=0.6)
        ax.set_xscale("log")
        ax.set_xlabel("n . v")
    axes[0].set_ylabel("ours / Mitsuba - 1 (%)")
    fig.suptitle("closed-form SG shading vs Mitsuba (TANGO's BRDF evaluated exactly), studio SG light", fontsize=9)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"plot: {args.out}")


if __name__ == "__main__":
    main()
