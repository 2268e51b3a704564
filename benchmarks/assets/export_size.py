"""Welded against faceted exports: file sizes, validators and the Blender round trip, side by side.

Per built-in mesh: normalise, a small ray cache, a short image-guided fit (SG-rendered targets:
the asset's content, not its quality, is what is compared here) with flat and with smooth shading
normals, the bake (texture size from the texel density, as the workflow does), then the export
stage twice on the same bake: as before 2026-11-22 (``export.weld: false``: one vertex per face
corner; ``usdz_root: usda``: the USDZ carries the text layer) and as now (the defaults: vertices
shared where position, normal, UV and tangent agree; the USDZ carries a binary crate layer).
Printed per row: vertices, GLB and USDZ bytes and their ratio to the faceted file of the same
bake (and the GLB's without its embedded textures, which welding does not touch), the
validators' errors and warnings (usd-core on the .usdz, Khronos on the .glb), and, unless
``--no-blender``, the roundtrip stage's Cycles-vs-field PSNR for both files with the import
checks' tangent error (Blender's own MikkTSpace against the frame the normal map was baked in).

    python -m benchmarks.assets.export_size                  # vase, candle, knot; flat and smooth
    python -m benchmarks.assets.export_size --meshes vase --normals smooth --no-blender
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

from benchmarks.common import RESULTS


def prepare(work: Path, name: str) -> None:
    from stages.config.sections import NormalizeSettings, RaycacheSettings
    from stages.geometry.meshio import save_ply
    from stages.geometry.normalization import normalize_mesh
    from stages.raycache import run as raycache_run

    res = normalize_mesh(f"builtin:{name}", NormalizeSettings())
    save_ply(work / "mesh.ply", res.mesh)
    (work / "transform.json").write_text(json.dumps(res.transform.to_json()))
    rc = RaycacheSettings(views=16, resolution=96, eval_azimuths=8, eval_elevations_deg=(0.0, 30.0), eval_resolution=96)
    raycache_run(work / "mesh.ply", work / "train.npz", work / "eval.npz", work / "rc.json", rc)


def cell(work: Path, normals: str, iterations: int, blender: bool) -> list[dict]:
    from stages import bake, export, optimize, roundtrip
    from stages.config.sections import BakeSettings, ExportSettings, OptimizeSettings, RoundtripSettings

    out = work / normals
    s = OptimizeSettings(
        iterations=iterations,
        guidance="image",
        target_renderer="sg",
        image_size=96,
        eval_width=96,
        width=128,
        lr=5e-3,
        crops=0,
        shading_normals=normals,
        checkpoint_every=100_000,
    )
    optimize.run(work / "train.npz", work / "eval.npz", "", out / "opt", s, "cpu")
    bake.run(work / "mesh.ply", out / "opt" / "field.pt", work / "eval.npz", out / "bake", BakeSettings())
    rows = []
    for weld in (False, True):
        exp = out / f"export-{'welded' if weld else 'faceted'}"
        t0 = time.perf_counter()
        stats = export.run(
            work / "mesh.ply",
            work / "transform.json",
            out / "bake",
            out / "bake" / "preview.png",
            exp,
            ExportSettings(weld=weld, usdz_root="usdc" if weld else "usda"),
            "x",
        )
        row = {
            "normals": normals,
            "layout": "welded" if weld else "faceted",
            "faces": stats["faces"],
            "vertices": stats["vertices_exported"],
            "glb_bytes": stats["file_bytes"]["model.glb"],
            "usdz_bytes": stats["file_bytes"]["model.usdz"],
            "texture_bytes": sum(p.stat().st_size for p in (exp / "textures").glob("*.png")),
            "usd_errors": stats["usd_validation_errors"],
            "usd_warnings": stats["usd_validation_warnings"],
            "gltf_errors": stats["gltf_validation_errors"],
            "gltf_warnings": stats["gltf_validation_warnings"],
            "export_s": time.perf_counter() - t0,
        }
        if blender:
            rt = roundtrip.run(
                work / "mesh.ply",
                work / "transform.json",
                out / "opt" / "field.pt",
                work / "eval.npz",
                out / "bake",
                exp,
                out / f"roundtrip-{row['layout']}",
                RoundtripSettings(enabled=True),
            )
            for fmt in ("glb", "usdz"):
                row[f"{fmt}_roundtrip_psnr_db"] = rt["formats"][fmt]["psnr_db"]
                row[f"{fmt}_tangent_p99_deg"] = rt["formats"][fmt]["import"].get("tangent_error_deg_p99")
                row[f"{fmt}_import_problems"] = len(rt["formats"][fmt]["import"]["problems"])
        rows.append(row)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", default="vase,candle,knot", help="comma-separated built-in meshes")
    parser.add_argument("--normals", default="flat,smooth", help="comma-separated shading normals")
    parser.add_argument("--iterations", type=int, default=150, help="iterations of the short fit")
    parser.add_argument("--no-blender", action="store_true", help="skip the Blender round trip")
    parser.add_argument("--out", type=Path, default=RESULTS / "export_size.json")
    args = parser.parse_args()
    import torch

    torch.set_num_threads(int(os.environ.get("TANGO_THREADS", "2")))
    rows = []
    for name in args.meshes.split(","):
        with tempfile.TemporaryDirectory() as d:
            work = Path(d)
            prepare(work, name)
            for normals in args.normals.split(","):
                pair = cell(work, normals, args.iterations, not args.no_blender)
                base = pair[0]
                for r in pair:
                    r["mesh"] = name
                    r["glb_ratio"] = r["glb_bytes"] / base["glb_bytes"]
                    r["usdz_ratio"] = r["usdz_bytes"] / base["usdz_bytes"]
                    # what the geometry takes: the GLB without its embedded PNGs
                    r["glb_geometry_ratio"] = (r["glb_bytes"] - r["texture_bytes"]) / (base["glb_bytes"] - base["texture_bytes"])
                    rt = ""
                    if "glb_roundtrip_psnr_db" in r:
                        problems = r["glb_import_problems"] + r["usdz_import_problems"]
                        rt = (
                            f"  Blender GLB {r['glb_roundtrip_psnr_db']:.2f} dB "
                            f"(tangents p99 {r['glb_tangent_p99_deg']:.3f} deg), "
                            f"USDZ {r['usdz_roundtrip_psnr_db']:.2f} dB, import problems {problems}"
                        )
                    print(
                        f"{name:7s} {normals:6s} {r['layout']:8s} faces {r['faces']:6d} vertices {r['vertices']:6d}  "
                        f"GLB {r['glb_bytes'] / 1e6:6.3f} MB (x{r['glb_ratio']:.3f}; geometry x{r['glb_geometry_ratio']:.3f}, "
                        f"textures {r['texture_bytes'] / 1e6:.3f} MB)  USDZ {r['usdz_bytes'] / 1e6:6.3f} MB "
                        f"(x{r['usdz_ratio']:.3f})  validators: USD {r['usd_errors']} errors {r['usd_warnings']} warnings, "
                        f"glTF {r['gltf_errors']} errors {r['gltf_warnings']} warnings{rt}",
                        flush=True,
                    )
                rows += pair
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(".json.part")
    tmp.write_text(json.dumps(rows, indent=1))
    tmp.replace(args.out)
    print(f"wrote {args.out}", flush=True)


if __name__ == "__main__":
    main()
