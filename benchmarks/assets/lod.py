"""Levels of detail: per level, faces, file sizes, bake time and fidelity against the full-resolution
neural render, in our renderer and through Blender.

Per mesh: the recovery benchmark's preparation (normalise, the recovery cache at 96 pixels,
Mitsuba's targets of a procedural material with a bump map, so the field has surface detail to
carry) and a ``fast`` fit under image guidance; the bake and export stages (lod0), then the lod stage
(``--levels``, default the schema's 50%, 10%, 2%; textures at the full bake's size unless
``--texture-size``). Printed per level: faces, GLB and USDZ bytes, decimation and bake seconds,
the fraction of texels that found the traced surface, our renderer's PSNR of the level's textures
against the trained field on the traced mesh (object pixels both cover, sRGB) with the silhouettes'
IoU and, unless ``--no-blender``, the roundtrip stage on the level's GLB: Cycles renders of the
imported level against the same neural render (fully covered object pixels), with the import
checks' problem count.

    python -m benchmarks.assets.lod                                   # vase, candle, knot
    python -m benchmarks.assets.lod --meshes shared:lamp --levels 0.25,0.05 --no-blender
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

from benchmarks.common import RESULTS, fit_recovery, mesh_sources, prepare_recovery, recovery_folder


def levels_of(work: Path, name: str, args) -> list[dict]:
    import torch

    from stages import bake, export, lod, roundtrip
    from stages.config.sections import BakeSettings, ExportSettings, LodSettings, NormalizeSettings, RoundtripSettings
    from stages.geometry.normalization import normalize_mesh

    prepare_recovery(work, args.source, args.material)
    (work / "transform.json").write_text(json.dumps(normalize_mesh(args.source, NormalizeSettings()).transform.to_json()))
    row = fit_recovery(work, args.material, "fast")
    field = recovery_folder(work, "fast") / "field.pt"
    torch.set_num_threads(int(os.environ.get("TANGO_THREADS", "2")))
    bake.run(work / "mesh.ply", field, work / "eval.npz", work / "bake", BakeSettings())
    preview = work / "bake" / "preview.png"
    export.run(work / "mesh.ply", work / "transform.json", work / "bake", preview, work / "export", ExportSettings())
    settings = LodSettings(enabled=True, texture_size=args.texture_size, **({"levels": args.levels} if args.levels else {}))
    t0 = time.perf_counter()
    files = lod.CellFiles(
        work / "mesh.ply", field, work / "eval.npz", work / "transform.json", work / "bake", work / "export" / "meta.json"
    )
    stats = lod.run(
        files,
        work / "lod",
        settings,
        BakeSettings(),
        ExportSettings(),
        name,
    )
    lod_s = time.perf_counter() - t0
    rows = []
    for r in stats["levels"]:
        out = {
            "mesh": name,
            "fit_psnr_db": row["psnr_db"],
            **{k: r.get(k) for k in ("level", "fraction", "faces", "texture_size", "bake_seconds", "decimate_seconds")},
            "glb_bytes": r["file_bytes"]["model.glb"],
            "usdz_bytes": r["file_bytes"]["model.usdz"],
            "texels_on_traced_surface": r.get("texels_on_traced_surface", 1.0),
            "ours_psnr_db": r["fidelity_psnr_db"],
            "silhouette_iou": r["silhouette_iou"],
            "lod_stage_s": lod_s,
        }
        if not args.no_blender:
            folder = work / "export" if r["level"] == "lod0" else work / "lod" / r["level"]
            mesh = work / "mesh.ply" if r["level"] == "lod0" else folder / "mesh.ply"
            atlas_dir = work / "bake" if r["level"] == "lod0" else folder
            rt = roundtrip.run(
                mesh,
                work / "transform.json",
                field,
                work / "eval.npz",
                atlas_dir,
                folder,
                work / f"roundtrip-{r['level']}",
                RoundtripSettings(enabled=True, formats=("glb",)),
            )
            out["blender_glb_psnr_db"] = rt["formats"]["glb"]["psnr_db"]
            out["blender_import_problems"] = len(rt["formats"]["glb"]["import"]["problems"])
        rows.append(out)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", default="builtin", help="builtin, shared, a built-in name or shared:<stem>, comma-separated")
    parser.add_argument("--material", default="wood", help="the procedural target material")
    parser.add_argument("--levels", default="", help="comma-separated face fractions (default: the schema's)")
    parser.add_argument("--texture-size", type=int, default=None, help="texture width of every level (default: the full bake's)")
    parser.add_argument("--no-blender", action="store_true", help="skip the Blender round trip")
    parser.add_argument("--out", type=Path, default=RESULTS / "lod.json")
    args = parser.parse_args()
    args.levels = tuple(float(x) for x in args.levels.split(",")) if args.levels else None
    rows = []
    t_start = time.perf_counter()
    for name, source in mesh_sources(args.meshes):
        args.source = source
        with tempfile.TemporaryDirectory() as d:
            for r in levels_of(Path(d), name, args):
                blender = ""
                if "blender_glb_psnr_db" in r:
                    blender = f"  Blender GLB {r['blender_glb_psnr_db']:.2f} dB ({r['blender_import_problems']} import problems)"
                print(
                    f"{name:14s} {r['level']:5s} {100 * r['fraction']:5.1f}% faces {r['faces']:6d}  "
                    f"GLB {r['glb_bytes'] / 1e6:6.3f} MB  USDZ {r['usdz_bytes'] / 1e6:6.3f} MB  tex {r['texture_size']}  "
                    f"decimate {r['decimate_seconds'] or 0:5.2f} s  bake {r['bake_seconds']:5.2f} s  "
                    f"on surface {100 * r['texels_on_traced_surface']:5.1f}%  ours {r['ours_psnr_db']:6.2f} dB "
                    f"(IoU {r['silhouette_iou']:.3f}){blender}",
                    flush=True,
                )
                rows.append(r)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(".json.part")
    tmp.write_text(json.dumps(rows, indent=1))
    tmp.replace(args.out)
    print(f"wrote {args.out} ({time.perf_counter() - t_start:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
