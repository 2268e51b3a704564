"""Ray-cache throughput: primary rays per second at 224x224 and 512x512, and bytes per view.

Meshes: a generated torus-knot tube of 81,920 faces and ../shared/meshes/person.obj (48,918
faces; skipped when ../shared is absent). For each mesh and resolution, the training pool of
``--views`` views (TANGO's sampler, anchor 1.96/0.63, std 8, radius 2, fov 60) is traced twice:
the first pass warms up, the second is timed. Two rates are printed:

* ``trace``: rays / seconds spent inside Embree (embreex ``run``);
* ``total``: rays / wall time of the whole cache build (ray generation, tracing, compaction).

The last line is ``key=value`` pairs; ``rays_per_s_224`` and ``rays_per_s_512`` are the *total*
rates, the slower of the two meshes; ``bytes_per_view`` is at 512 on the generated mesh.

    python benchmarks/raycache.py [--views 24]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from stages.config.sections import NormalizeSettings, RaycacheSettings
from stages.geometry.meshio import TriMesh
from stages.geometry.normalization import normalize_mesh
from stages.geometry.raycache import trace_views, training_views
from stages.geometry.shapes import knot
from stages.geometry.tracing import EmbreeTracer

SHARED = Path(__file__).resolve().parents[2] / "shared" / "meshes"


def generated_80k() -> TriMesh:
    v, f = knot(samples=2048, sides=20)  # 2048 * 20 * 2 = 81,920 faces
    from stages.geometry.normalization import normalization_transform

    tf = normalization_transform(v)
    return TriMesh(tf.forward(v), f)


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--views", type=int, default=24)
    args = parser.parse_args()
    meshes = {"knot80k": generated_80k()}
    person = SHARED / "person.obj"
    if person.is_file():
        meshes["person"] = normalize_mesh(person, NormalizeSettings()).mesh
    else:
        print(f"# {person} absent: measuring the generated mesh only")
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
    print(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in kv.items()))


if __name__ == "__main__":
    np.seterr(all="raise")
    main()
