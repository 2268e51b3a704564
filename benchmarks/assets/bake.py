"""Bake and export cost against mesh size and texture size: wall time and peak memory.

Meshes: the generated torus-knot tube at about 5k, 30k and 80k faces, normalised. Field: a
randomly initialised TANGO field at the paper's width (256; baking cost does not depend on what
it learned). For each (faces, texture size) a fresh process unwraps (xatlas), rasterises, evaluates
the networks at every covered texel, dilates, writes the textures and the light, and exports USD
(usda + usdz) and GLB; the parent reports the stages' times and the child's peak resident memory.
The last rows bake the 80k mesh decimated to 5,000 faces (pymeshlab) for comparison.

    python -m benchmarks.assets.bake [--sizes 512 1024 2048] [--faces 5k 30k 80k]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import tempfile
import time
from pathlib import Path

from benchmarks.common import REPO, module_command

KNOTS = {"5k": (128, 20), "30k": (768, 20), "80k": (2048, 20)}


def child(faces: str, size: int, decimate_to: int | None) -> dict:
    import numpy as np
    import torch

    from stages.assets.baking import bake_field
    from stages.assets.formats import AssetInfo, export_mesh
    from stages.assets.formats.gltf import write_glb
    from stages.assets.formats.usd import package_usdz, write_usd
    from stages.config.brdfs import brdf_spec
    from stages.config.sections import BakeSettings, OptimizeSettings
    from stages.core.provenance import origin_record
    from stages.geometry.meshio import TriMesh, save_ply
    from stages.geometry.normalization import normalization_transform
    from stages.geometry.shapes import knot
    from stages.model.field import StyleField

    torch.set_num_threads(2)
    samples, sides = KNOTS[faces]
    v, f = knot(samples=samples, sides=sides)
    tf = normalization_transform(v)
    mesh = TriMesh(tf.forward(v), f)
    t = {}
    if decimate_to:
        from stages.config.sections import DecimateSettings
        from stages.geometry.decimation import decimate_mesh

        t0 = time.perf_counter()
        mesh = decimate_mesh(mesh, DecimateSettings(target_faces=decimate_to, hausdorff_samples=10000)).mesh
        t["decimate"] = time.perf_counter() - t0
    field = StyleField(OptimizeSettings().field_settings()).eval()
    t0 = time.perf_counter()
    res = bake_field(mesh, field, BakeSettings(texture_size=size))
    t["bake"] = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        from PIL import Image

        t0 = time.perf_counter()
        (d / "textures").mkdir()
        for name, img in res.textures.items():
            Image.fromarray(img).save(d / "textures" / f"{name}.png")
        from stages.render.hdrio import write_exr

        write_exr(d / "light.exr", res.light_equirect)
        t["write_textures"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        atlas = {"uv": res.atlas.uv, **res.frames.arrays()}
        geom = export_mesh(mesh, atlas, tf)
        origin = origin_record(guidance="clip", weights="random untrained field (benchmark)", test_only=True)
        write_usd(d / "model.usda", geom, 1.0, "light.exr", origin)
        package_usdz(d / "model.usda", d / "model.usdz", [f"textures/{k}.png" for k in res.textures] + ["light.exr"])
        write_glb(d / "model.glb", geom, d / "textures", AssetInfo(1.0, "bench", origin, brdf_spec("tango")))
        t["export"] = time.perf_counter() - t0
        sizes = {k: (d / k).stat().st_size for k in ("model.usdz", "model.glb")}
    del np, save_ply
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return {
        "faces": len(mesh.faces),
        "size": size,
        "coverage": res.coverage,
        "peak_mb": peak_mb,
        **t,
        **sizes,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[512, 1024, 2048])
    parser.add_argument("--faces", nargs="+", default=list(KNOTS))
    parser.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        faces, size, dec = args.child
        print(json.dumps(child(faces, int(size), int(dec) or None)))
        return
    runs = [(f, s, 0) for f in args.faces for s in args.sizes]
    if "80k" in args.faces:
        runs += [("80k", s, 5000) for s in args.sizes if s <= 1024]
    print(
        f"{'faces':>7}{'texture':>9}{'decimate s':>11}{'bake s':>8}{'write s':>8}{'export s':>9}{'total s':>8}"
        f"{'peak MB':>9}{'usdz MB':>9}{'glb MB':>8}"
    )
    rows = []
    for faces, size, dec in runs:
        out = subprocess.run(
            module_command(__spec__.name, "--child", faces, str(size), str(dec)),
            cwd=REPO,
            capture_output=True,
            text=True,
            check=True,
        )
        r = json.loads(out.stdout.strip().splitlines()[-1])
        r["decimate"] = r.get("decimate", 0.0)
        r["total"] = r["decimate"] + r["bake"] + r["write_textures"] + r["export"]
        r["label"] = f"{faces}->5k" if dec else faces
        rows.append(r)
        print(
            f"{r['faces']:>7}{size:>9}{r['decimate']:>11.2f}{r['bake']:>8.2f}{r['write_textures']:>8.2f}"
            f"{r['export']:>9.2f}{r['total']:>8.2f}{r['peak_mb']:>9.0f}{r['model.usdz'] / 1e6:>9.1f}"
            f"{r['model.glb'] / 1e6:>8.1f}"
        )
    kv = {}
    for r in rows:
        key = f"{r['label']}_{r['size']}"
        kv[f"total_s_{key}"] = r["total"]
        kv[f"peak_mb_{key}"] = r["peak_mb"]
    print(" ".join(f"{k}={v:.4g}" for k, v in kv.items()))


if __name__ == "__main__":
    main()
