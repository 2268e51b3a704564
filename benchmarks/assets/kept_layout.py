"""The input's own UV layout against a new xatlas atlas (``bake.uv: keep`` vs ``atlas``): bake
fidelity, texel density, seams and the exported asset, side by side in one run.

For each mesh with its own layout (``../shared/meshes/spot.obj`` and the others named, in a developer
checkout), this normalises it, traces 24 evaluation views at 256 pixels and bakes one field into
the layout ``bake.uv: auto`` chooses (the input's own where usable, with ``--max-overlap`` as
``bake.uv_max_overlap``) and into a new atlas (``atlas``) with the stages' own code (``bake.run``,
then ``export.run``), at the texture size
the bake's rule gives the mesh (``bake.texels_per_face``) or ``--size``. The field has detail at
texel scale: the ``fast`` preset's networks with their SVBRDF weights perturbed by seeded noise
(std 0.3), as in ``benchmarks.assets.bake_charts`` (its files are marked test-only: it was not
trained). Per layout it prints the bake's seconds, islands (charts), seams (3D edges whose two
faces' UVs differ), the share of texels covered, the texel density (covered texels per unit of
surface area, the normalised mesh having radius 1; and per face at the 10th and 90th percentile of
the area: how evenly the layout spends them), the fidelity (``bake_psnr_db``: the baked
textures rendered from the evaluation views against the field, object pixels), the exported
vertex count and the validators' errors and warnings. With ``--roundtrip`` (Blender) the kept
asset is also imported in the input's own format beside the input (vertices, UVs) and both layouts
are rendered with Cycles against the field (GLB, 2 views, 64 spp).

The glTF assets (``scripts/fetch_gltf_assets.sh``: Khronos sample models and others as published)
whose own layout cannot hold a bake get a second UV set (``auto``); the row gives the seam vertices
it appended, and with ``--roundtrip`` Blender's import of the input and of the asset side by side:
objects, armature bones, actions, shape keys and vertices (the asset's: the input's plus the
appended).

    bash scripts/fetch_uv_meshes.sh     # build/uv-meshes: duck, milk truck, jeep, converted (benchmarks/SOURCES.md)
    bash scripts/fetch_gltf_assets.sh   # build/gltf-assets: nine glTF 2.0 assets as published (benchmarks/SOURCES.md)
    python -m benchmarks.assets.kept_layout [--meshes spot.obj,...|gltf-assets] [--size N] [--max-overlap 0.01] [--roundtrip]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from benchmarks.common import REPO, SHARED_MESHES, perturbed_field

#: the measured set: spot (../shared/meshes), a made lathe layout, and the meshes
#: scripts/fetch_uv_meshes.sh fetches into build/uv-meshes (licences: benchmarks/SOURCES.md)
#: the published glTF assets scripts/fetch_gltf_assets.sh fetches (``--meshes gltf-assets``)
GLTF_ASSETS = ",".join(
    f"build/gltf-assets/{name}"
    for name in (
        "box-textured/BoxTextured.glb",
        "duck/Duck.gltf",
        "milk-truck/CesiumMilkTruck.gltf",
        "cesium-man/CesiumMan.gltf",
        "fox/Fox.gltf",
        "spider/gltf_spider_animated.gltf",
        "morph-cube/AnimatedMorphCube.gltf",
        "test-scene/TestScene.gltf",
        "sparse-morph/singleBlendshapeCube_sparse.glb",
    )
)
MESHES = "spot.obj,made:lathe-vase,build/uv-meshes/duck.glb,build/uv-meshes/milktruck.glb,build/uv-meshes/jeep.glb," + GLTF_ASSETS
#: names for sets of meshes
SETS = {"gltf-assets": GLTF_ASSETS}


def lathe_vase(path: Path, segments: int = 48, samples: int = 24) -> Path:
    """The built-in vase with the layout an artist gives a surface of revolution (a lathe unwrap):
    ``u`` the angle around the axis (a seam at 0), ``v`` the arc length along the profile from the
    base's centre to the floor's, each pole split per segment; written as an OBJ."""
    import numpy as np

    from stages.geometry.shapes import vase

    v, f = vase(segments, samples)
    n_rings = (len(v) - 2) // segments
    ring_pts = v[1 : 1 + n_rings * segments : segments]  # each ring's point at angle 0
    profile = np.concatenate([v[:1], ring_pts, v[-1:]])
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(profile, axis=0), axis=1))]
    arc /= arc[-1]
    ring = np.where(np.arange(len(v)) == 0, -1, (np.arange(len(v)) - 1) // segments)
    ring[-1] = n_rings
    k = (np.arange(len(v)) - 1) % segments
    pole = (ring[f] < 0) | (ring[f] == n_rings)
    cu = np.where(pole, np.nan, k[f] / segments)
    span = np.nanmax(cu, axis=1) - np.nanmin(cu, axis=1) > 0.5  # across the seam: small u go past 1
    cu[span] = np.where(cu[span] < 0.5, cu[span] + 1.0, cu[span])
    cu = np.where(pole, np.nanmean(cu, axis=1, keepdims=True), cu)
    cv = arc[ring[f] + 1]
    table, vt = np.unique(np.round(np.stack([cu, cv], -1).reshape(-1, 2), 12), axis=0, return_inverse=True)
    vt = vt.reshape(-1, 3)  # corners with the same (u, v) share a vt, as an artist's file does
    lines = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in v]
    lines += [f"vt {u:.9g} {t:.9g}" for u, t in table]
    lines += [" ".join(["f", *(f"{i + 1}/{j + 1}" for i, j in zip(fi, ti, strict=True))]) for fi, ti in zip(f, vt, strict=True)]
    path.write_text("\n".join(lines) + "\n")
    return path


def prepare(src: Path, d: Path, field, settings) -> None:
    """``src`` normalised and traced into ``d``, with ``field`` saved as the cell's field."""
    from stages.config.sections import NormalizeSettings, RaycacheSettings
    from stages.core.provenance import origin_record
    from stages.geometry.meshio import save_ply
    from stages.geometry.normalization import normalize_mesh
    from stages.model.checkpoint import save_field
    from stages.raycache import run as raycache_run

    res = normalize_mesh(str(src), NormalizeSettings())
    save_ply(d / "mesh.ply", res.mesh)
    (d / "transform.json").write_text(json.dumps({"source": str(src), **res.transform.to_json()}))
    cache = RaycacheSettings(views=2, resolution=32, eval_resolution=256, metrics_resolution=32)
    raycache_run(d / "mesh.ply", d / "train.npz", d / "eval.npz", d / "rc.json", cache, d / "metrics.npz")
    origin = origin_record(guidance="clip", weights="none: an untrained field, perturbed (benchmark)", test_only=True)
    save_field(d / "field.pt", field, settings, "benchmark", origin)


def one_layout(src: Path, d: Path, uv: str, size: int | None, roundtrip: bool, max_overlap: float = 0.01) -> dict:
    """Bake and export ``d``'s field into layout ``uv``; the figures of both (and of the round trip)."""
    import numpy as np

    from stages import bake, export
    from stages.assets.layouts import InputMesh
    from stages.config.sections import BakeSettings, ExportSettings
    from stages.geometry.meshio import load_ply
    from stages.geometry.uvlayout import seams_and_islands

    t0 = time.perf_counter()
    settings = BakeSettings(uv=uv, texture_size=size, uv_max_overlap=max_overlap)
    stats = bake.run(
        d / "mesh.ply",
        d / "field.pt",
        d / "eval.npz",
        d / f"bake_{uv}",
        settings,
        "cpu",
        InputMesh(str(src), d / "transform.json"),
    )
    bake_s = time.perf_counter() - t0
    out = export.run(
        d / "mesh.ply",
        d / "transform.json",
        d / f"bake_{uv}",
        d / f"bake_{uv}" / "preview.png",
        d / f"export_{uv}",
        ExportSettings(),
        "m",
        str(src),
    )
    mesh = load_ply(d / "mesh.ply")
    with np.load(d / f"bake_{uv}" / "atlas.npz") as z:
        seams, islands = seams_and_islands(mesh.vertices, mesh.faces, z["uv"].astype(np.float64))
    row = {
        "faces": len(mesh.faces),
        "size": stats["texture_size"],
        "bake_s": bake_s,
        "islands": islands,
        "seams": seams,
        "coverage": stats["texel_coverage"],
        "density": stats["texels_per_area"],
        "density_p10": stats["texels_per_area_percentiles"]["p10"],
        "density_p90": stats["texels_per_area_percentiles"]["p90"],
        "psnr": stats["bake_psnr_db"],
        "vertices": out["vertices_exported"],
        "gltf": f"{out['gltf_validation_errors']}/{out['gltf_validation_warnings']}",
        "usd": f"{out['usd_validation_errors']}/{out['usd_validation_warnings']}",
        "why": stats["uv"]["why"],
        "layout": stats["uv"]["layout"],
        "appended": (out.get("second_uv_set") or {}).get("appended_vertices", 0),
    }
    if roundtrip:
        row.update(blender(src, d, uv))
    return row


def blender(src: Path, d: Path, uv: str) -> dict:
    """The round trip of layout ``uv``'s asset: Cycles against the field, and for a kept layout
    the own-format import beside the input's."""
    from stages import roundtrip
    from stages.config.sections import RoundtripSettings

    settings = RoundtripSettings(enabled=True, views=2, spp=64, split_lobes=False, formats=("glb",))
    res = roundtrip.run(
        d / "mesh.ply",
        d / "transform.json",
        d / "field.pt",
        d / "eval.npz",
        d / f"bake_{uv}",
        d / f"export_{uv}",
        d / f"rt_{uv}",
        settings,
        "cpu",
        str(src),
    )
    own = json.loads((d / f"rt_{uv}" / "meta.json").read_text())["own_format"]
    out = {"cycles_psnr": res["formats"]["glb"]["psnr_db"], "import_problems": len(res["formats"]["glb"]["import"]["problems"])}
    if own:
        a, b = own["input"], own["output"]
        for key in ("objects", "bones", "actions", "shape_keys", "vertices"):
            out[f"blender_{key}"] = f"{a.get(key, '-')}/{b.get(key, '-')}"
        out["blender_uv_error"] = own["uv_error"]
        out["own_problems"] = len(own["problems"])
    return out


def main() -> None:
    import torch

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--meshes", default=MESHES, help="files with their own layouts (names: in ../shared/meshes), or gltf-assets (the nine)"
    )
    parser.add_argument("--size", type=int, help="texture width for both layouts (default: the bake's rule)")
    parser.add_argument("--roundtrip", action="store_true", help="also through Blender (Cycles, own-format import)")
    parser.add_argument("--max-overlap", type=float, default=0.01, help="bake.uv_max_overlap for the auto layout")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    field, settings = perturbed_field(shading_normals="smooth")
    cols = ["faces", "size", "bake_s", "islands", "seams", "coverage", "density", "density_p10", "density_p90", "psnr"]
    cols += ["vertices", "appended", "gltf", "usd"]
    blender_cols = [f"blender_{k}" for k in ("objects", "bones", "actions", "shape_keys", "vertices")]
    cols += ["cycles_psnr", "import_problems", *blender_cols, "blender_uv_error", "own_problems"] if args.roundtrip else []
    print(f"# a perturbed field with texel-scale detail; fidelity over 24 views at 256 px; {'; '.join(cols)}")
    kv = {}
    for name in SETS.get(args.meshes, args.meshes).split(","):
        with tempfile.TemporaryDirectory() as d:
            d = Path(d)
            src = Path(name) if Path(name).is_file() else REPO / name if (REPO / name).is_file() else SHARED_MESHES / name
            if name == "made:lathe-vase":
                src = lathe_vase(d / "lathe-vase.obj")
            if not src.is_file():
                where = "../shared/meshes in a developer checkout; scripts/fetch_uv_meshes.sh, scripts/fetch_gltf_assets.sh"
                print(f"{name}: not here ({where})", flush=True)
                continue
            prepare(src, d, field, settings)
            rows = {uv: one_layout(src, d, uv, args.size, args.roundtrip, args.max_overlap) for uv in ("auto", "atlas")}
        for uv, row in rows.items():
            cells = [f"{row.get(c, '-'):.4g}" if isinstance(row.get(c), float) else str(row.get(c, "-")) for c in cols]
            print(f"{src.name:<16}{uv}:{row['layout']:<7}" + " ".join(cells), flush=True)
            kv.update({f"{c}_{src.stem}_{uv}": row[c] for c in ("psnr", "density", "seams", "bake_s") if c in row})
        print(f"{src.name:<16}why: {rows['auto']['why']}", flush=True)
    print(" ".join(f"{k}={v:.4g}" for k, v in kv.items()))


if __name__ == "__main__":
    main()
