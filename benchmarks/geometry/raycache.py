"""Ray-cache throughput: primary rays per second at 224x224 and 512x512, and bytes per view.

Meshes: a generated torus-knot tube of 81,920 faces and ../shared/meshes/person.obj (48,918
faces; skipped when ../shared is absent). For each mesh and resolution, the training pool of
``--views`` views (TANGO's sampler, anchor 1.96/0.63, std 8, radius 2, fov 60) is traced twice:
the first pass warms up, the second is timed. Two rates are printed:

* ``trace``: rays / seconds spent inside Embree (embreex ``run``);
* ``total``: rays / wall time of the whole cache build (ray generation, tracing, compaction).

The last line is ``key=value`` pairs; ``rays_per_s_224`` and ``rays_per_s_512`` are the *total*
rates, the slower of the two meshes; ``bytes_per_view`` is at 512 on the generated mesh.

Then the shadow rays, side by side on each mesh: the bake's ambient occlusion samples (32,768
points, both sides, the default 512 directions: about 17 M rays) traced as the visibility bits are,
with Embree's first-hit query in one thread (how they were traced before 2026-11-25), its any-hit
query in one thread, the any-hit query over every CPU in batches of 2^20 rays (the batch size
before 2026-11-29, traced the current way: each batch whole on one thread), and the same in
batches of ``RAYS_PER_BATCH`` (the default); the bits must be equal. ``vis_speedup`` is the first
against the last, ``vis_batch_speedup`` the last two (the batch size alone).

    python -m benchmarks.geometry.raycache [--views 24] [--visibility-only]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from benchmarks.common import SHARED_MESHES, knot_mesh
from stages.config.sections import NormalizeSettings, RaycacheSettings
from stages.core.threads import cpu_threads, set_cpu_threads
from stages.geometry import visibility
from stages.geometry.meshio import TriMesh
from stages.geometry.normalization import normalize_mesh
from stages.geometry.raycache import trace_views, training_views
from stages.geometry.tracing import EmbreeTracer
from stages.geometry.visibility import OcclusionSamples, fibonacci_directions


def measure(mesh: TriMesh, width: int, views: int) -> dict:
    settings = RaycacheSettings(views=views, resolution=width)
    vs = training_views(settings)
    t0 = time.perf_counter()
    tracer = EmbreeTracer(mesh)
    bvh = time.perf_counter() - t0
    trace_views(mesh, vs, tracer)  # warm-up
    t0 = time.perf_counter()
    arrays, st = trace_views(mesh, vs, tracer)
    wall = time.perf_counter() - t0
    per_hit = sum(arrays[k].nbytes for k in ("pixel", "face", "bary"))
    return {
        "faces": len(mesh.faces),
        "rays": st.rays,
        "bvh_s": bvh,
        "trace_rate": st.rays / st.trace_seconds,
        "total_rate": st.rays / wall,
        "coverage": st.hits / st.rays,
        "bytes_per_view": per_hit / views,
    }


class FirstHit:
    """A tracer whose any-hit answer comes from the first-hit query (the earlier way)."""

    def __init__(self, tracer: EmbreeTracer) -> None:
        self.tracer = tracer

    def occluded(self, origins, directions, threads=None):
        return self.tracer.trace(origins, directions).face >= 0


def visibility_side_by_side(meshes: dict[str, TriMesh], samples: int = 32768, directions: int = 512) -> dict:
    """The occlusion samples of each mesh traced four ways (see the module docstring)."""
    dirs = fibonacci_directions(directions)
    cpus = cpu_threads()
    out = {}
    print(f"shadow rays: {samples} points x 2 sides x {directions} directions (those above each side)")
    for name, mesh in meshes.items():
        tracer = EmbreeTracer(mesh)
        ways = (
            ("first-hit, 1 thread", FirstHit(tracer), 1, visibility.RAYS_PER_BATCH),
            ("any-hit, 1 thread", tracer, 1, visibility.RAYS_PER_BATCH),
            (f"any-hit, {cpus} threads, 2^20", tracer, cpus, 1 << 20),
            (f"any-hit, {cpus} threads", tracer, cpus, visibility.RAYS_PER_BATCH),
        )
        times, values = [], []
        default = visibility.RAYS_PER_BATCH
        for label, t, count, batch in ways:
            set_cpu_threads(count)
            visibility.RAYS_PER_BATCH = batch
            t0 = time.perf_counter()
            occ = OcclusionSamples(mesh, t, dirs, samples)
            times.append(time.perf_counter() - t0)
            values.append(occ.values)
            print(f"  {name:<10}{label:<32}{times[-1]:>8.2f} s")
        visibility.RAYS_PER_BATCH = default
        set_cpu_threads(None)
        assert all(np.array_equal(values[0], v) for v in values[1:]), "the four ways disagree"
        out[f"vis_s_first_hit_{name}"] = times[0]
        out[f"vis_s_any_hit_{name}"] = times[1]
        out[f"vis_s_threads_2_20_{name}"] = times[2]
        out[f"vis_s_threads_{name}"] = times[3]
        out[f"vis_speedup_{name}"] = times[0] / times[3]
        out[f"vis_batch_speedup_{name}"] = times[2] / times[3]
    out["vis_threads"] = cpus
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--views", type=int, default=24)
    parser.add_argument("--visibility-only", action="store_true", help="only the shadow rays, side by side")
    args = parser.parse_args()
    meshes = {"knot80k": knot_mesh(), "vase": normalize_mesh("builtin:vase", NormalizeSettings()).mesh}
    person = SHARED_MESHES / "person.obj"
    if person.is_file():
        meshes["person"] = normalize_mesh(person, NormalizeSettings()).mesh
    else:
        print(f"# {person} absent: measuring the generated meshes only")
    vis = visibility_side_by_side(meshes)
    if args.visibility_only:
        print(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in vis.items()))
        return
    meshes.pop("vase")  # the primary rays' table keeps its two meshes
    rows = {}
    header = ("mesh", "faces", "width", "coverage", "trace Mray/s", "total Mray/s", "bytes/view")
    print(f"{header[0]:<10}" + "".join(f"{h:>{w}}" for h, w in zip(header[1:], (8, 7, 10, 14, 14, 12), strict=True)))
    for name, mesh in meshes.items():
        for width in (224, 512):
            r = measure(mesh, width, args.views)
            rows[(name, width)] = r
            print(
                f"{name:<10}{r['faces']:>8}{width:>7}{r['coverage']:>10.3f}{r['trace_rate'] / 1e6:>14.2f}"
                f"{r['total_rate'] / 1e6:>14.2f}{r['bytes_per_view']:>12.0f}"
            )
    kv = {
        "views": args.views,
        "rays_per_s_224": min(r["total_rate"] for (n, w), r in rows.items() if w == 224),
        "rays_per_s_512": min(r["total_rate"] for (n, w), r in rows.items() if w == 512),
        "trace_rays_per_s_512": min(r["trace_rate"] for (n, w), r in rows.items() if w == 512),
        "bytes_per_view": rows[("knot80k", 512)]["bytes_per_view"],
        "bytes_per_hit": 12,
    }
    for (name, width), r in rows.items():
        kv[f"rays_per_s_{width}_{name}"] = r["total_rate"]
    if ("person", 512) in rows:
        kv["bytes_per_view_person"] = rows[("person", 512)]["bytes_per_view"]
    kv.update(vis)
    print(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in kv.items()))


if __name__ == "__main__":
    with np.errstate(all="raise"):  # (scoped: the docs' tests run this script in-process)
        main()
