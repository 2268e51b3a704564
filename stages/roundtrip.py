"""roundtrip: the exported assets through the artist's tool. Each exported file (``model.glb``,
``model.usdz``) is imported into Blender (``bpy``, the ``blender`` extra), checked (one mesh with
every face, positions in metres and Z-up, UVs, Blender's own tangents against the frame the normal
map was baked in, the Principled BSDF's wiring), and rendered with Cycles from evaluation views
under the learned light (``light.hdr`` as the world for the GLB; the USD brings its DomeLight),
then compared with our render of the trained field over fully covered object pixels (PSNR, sRGB).

Light transport ``direct_unshadowed`` (default) matches what our closed-form renderer models
(light straight from the environment, no self-shadowing), so the figure measures the asset and
the BRDF models; ``full`` path-traces shadows and bounces as an artist's render would.
"""

from __future__ import annotations

import logging
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .assets.formats import export_mesh, read_atlas
from .config.records import RoundtripRecord
from .config.sections import RoundtripSettings
from .core.cli import stage_main
from .core.errors import StageInputError
from .core.provenance import ORIGIN_KEY, Timer, metadata, read_origin, staged_outputs, write_json_atomic
from .core.safefiles import read_json_record
from .geometry.meshio import load_ply
from .geometry.normalization import Similarity
from .geometry.raycache import RayCache
from .imaging.sheets import save_png
from .imaging.views import ViewStore
from .model.checkpoint import load_field
from .reference.blender import BlenderUnavailable, blender_cameras, check_import, compare_renders, pick_views, render_job, run_job
from .render.color import srgb_encode, to_u8

log = logging.getLogger(__name__)


#: Cycles passes of the GLB: the material as imported, its diffuse lobe alone (no specular
#: reflection) and its specular lobe alone (black base colour)
PASSES = {
    "full": {},
    "diffuse": {"Specular IOR Level": 0.0},
    "specular": {"Base Color": (0.0, 0.0, 0.0, 1.0)},
}


@dataclass
class Lobes:
    """Our render at the hits of one view, linear ``(N, 3)`` each."""

    diffuse: np.ndarray
    specular: np.ndarray

    @property
    def rgb(self) -> np.ndarray:
        return self.diffuse + self.specular


def field_renders(field, cache: RayCache, views: list[int], device: str, shadows: bool = False) -> list[Lobes]:
    """Our render of the trained field at every hit of the given views, with the field's shadows
    when ``shadows`` (for Cycles' ``full`` transport; its ``direct_unshadowed`` casts none, so the
    comparison of like with like is unshadowed)."""
    store = ViewStore(cache, torch.device(device), field.normals, shadows=shadows and field.shadows)
    out = []
    for i in views:
        v = store[i]
        with torch.no_grad():
            sh = v.shade(field).shading
        out.append(Lobes(sh.diffuse.cpu().numpy().astype(np.float64), sh.specular.cpu().numpy().astype(np.float64)))
    return out


def comparison_sheet(ours: np.ndarray, theirs: dict[str, np.ndarray]) -> np.ndarray:
    """One row: ours | each format's Cycles render | 4 x |difference| of the first; sRGB, white
    where no pixel counted."""

    def show(x):
        return np.where(np.isnan(x), 1.0, np.clip(srgb_encode(np.clip(np.nan_to_num(x), 0, None)), 0, 1))

    first = next(iter(theirs.values()))
    diff = np.where(np.isnan(ours), np.nan, np.abs(show(first) - show(ours)) * 4.0)
    return np.concatenate([show(ours), *(show(t) for t in theirs.values()), np.where(np.isnan(diff), 1.0, diff)], axis=1)


def run(
    mesh_path: Path,
    transform_path: Path,
    field_path: Path,
    eval_path: Path,
    bake_dir: Path,
    export_dir: Path,
    out_dir: Path,
    settings: RoundtripSettings,
    device: str = "cpu",
) -> dict:
    """Import, check and render the cell's exported assets in Blender; write ``meta.json`` and
    ``compare.png`` into ``out_dir``."""
    timer = Timer()
    export_dir, bake_dir = Path(export_dir), Path(bake_dir)
    needed = [mesh_path, transform_path, field_path, eval_path, bake_dir / "atlas.npz", export_dir / "meta.json"]
    needed += [export_dir / f"model.{fmt}" for fmt in settings.formats] + [export_dir / "light.hdr"]
    for p in needed:
        if not Path(p).is_file():
            raise StageInputError(p, "file not found", "Run the bake and export stages first.")
    origin = read_origin(export_dir / "meta.json")
    export_meta = read_json_record(export_dir / "meta.json")
    units = export_meta["settings"]["units"]
    mpu = float(export_meta["settings"]["meters_per_unit"])
    with timer("load"):
        mesh = load_ply(mesh_path)
        atlas = read_atlas(bake_dir / "atlas.npz")
        tf = Similarity.from_json(read_json_record(transform_path))
        geom = export_mesh(mesh, atlas, tf if units == "original" else None, export_meta["settings"].get("weld", True))
        field, _ = load_field(field_path, device)
        cache = RayCache(eval_path)
    views = pick_views(len(cache), settings.views)
    hits = [cache.view(i) for i in views]
    with timer("ours"):
        reference = field_renders(field, cache, views, device, shadows=settings.transport == "full")
    cams = blender_cameras(np.stack([h.c2w for h in hits]), tf if units == "original" else None, mpu)
    results, images, lobes = {}, {}, {}
    with tempfile.TemporaryDirectory(prefix="roundtrip-") as work:
        for fmt in settings.formats:
            env = (export_dir / "light.hdr").resolve() if fmt == "glb" else None  # the USD carries its DomeLight
            asset = str((export_dir / f"model.{fmt}").resolve())
            # the GLB's lobes are also rendered alone, to split the gap between the BRDF models
            passes = PASSES if fmt == "glb" and settings.split_lobes else {"full": PASSES["full"]}
            for name, overrides in passes.items():
                job = {
                    "asset": asset,
                    "inspect": name == "full",
                    "render": {
                        **render_job(
                            cams,
                            cache.fov_deg,
                            cache.width,
                            spp=settings.spp,
                            seed=settings.seed,
                            transport=settings.transport,
                            environment=env,
                        ),
                        "principled_overrides": overrides,
                    },
                }
                with timer(f"blender_{fmt}_{name}"):
                    try:
                        res = run_job(job, Path(work) / f"{fmt}_{name}", settings.timeout_s)
                    except BlenderUnavailable as exc:
                        raise StageInputError(Path("blender"), str(exc), "Or set roundtrip.enabled: false.") from None
                if name != "full":
                    lobes[name] = res.renders
                    continue
                exported = export_meta.get("stats", {})
                occlusion = bool(exported.get("occlusion", False)) and fmt == "glb"  # Blender's USD importer drops it
                checks = check_import(res, geom, mpu, exported.get("brdf", "tango"), occlusion)
                world = [n["node"] for n in res.report.get("world", {}).get("nodes", [])]
                if "TEX_ENVIRONMENT" not in world:
                    checks["problems"].append("the world has no environment texture (the learned light did not arrive)")
                for problem in checks["problems"]:
                    log.warning("Blender import of model.%s: %s", fmt, problem)
                cmp = compare_renders(hits, res.renders, [r.rgb for r in reference])
                images[fmt] = cmp
                results[fmt] = {
                    "psnr_db": cmp.psnr_db,
                    "noise_psnr_db": cmp.noise_psnr_db,
                    "per_view_psnr_db": cmp.per_view_psnr_db,
                    "pixels": cmp.pixels,
                    "import": checks,
                    "blender": res.report.get("blender"),
                    "blender_seconds": res.seconds,
                    "render_seconds": res.report["render"]["seconds"],
                }
                log.info(
                    "model.%s in Blender %s: %.2f dB against our render over %d object pixels (Cycles noise %.1f dB), "
                    "%d problem(s)",
                    fmt,
                    res.report.get("blender"),
                    cmp.psnr_db,
                    cmp.pixels,
                    cmp.noise_psnr_db,
                    len(checks["problems"]),
                )
    split = {}
    if lobes:
        # each lobe alone against ours, and Blender's two lobes simply added (TANGO's sum, no layering)
        split["diffuse_psnr_db"] = compare_renders(hits, lobes["diffuse"], [r.diffuse for r in reference]).psnr_db
        split["specular_psnr_db"] = compare_renders(hits, lobes["specular"], [r.specular for r in reference]).psnr_db
        summed = lobes["diffuse"].copy()
        summed[..., :3] += lobes["specular"][..., :3]
        split["lobes_summed_psnr_db"] = compare_renders(hits, summed, [r.rgb for r in reference]).psnr_db
        ours_spec = float(np.concatenate([r.specular for r in reference]).mean())
        ours_all = float(np.concatenate([r.rgb for r in reference]).mean())
        split["specular_share"] = ours_spec / max(ours_all, 1e-12)
        results["glb"]["split"] = split
        log.info(
            "model.glb lobes: diffuse alone %.2f dB, specular alone %.2f dB, Blender's lobes added %.2f dB "
            "(specular is %.0f%% of our radiance)",
            split["diffuse_psnr_db"],
            split["specular_psnr_db"],
            split["lobes_summed_psnr_db"],
            100 * split["specular_share"],
        )
    front = cache.front_view()
    k = min(range(len(views)), key=lambda j: abs(views[j] - front))
    sheet = comparison_sheet(images[settings.formats[0]].ours[k], {f: c.theirs[k] for f, c in images.items()})
    stats = {
        "views": views,
        "width": cache.width,
        "spp": settings.spp,
        **{f"{fmt}_psnr_db": r["psnr_db"] for fmt, r in results.items()},
        **{f"glb_{k}": v for k, v in split.items()},
        **RoundtripRecord(
            problems=sum(len(r["import"]["problems"]) for r in results.values()),
            transport=settings.transport,
            glb_psnr_db=results["glb"]["psnr_db"] if "glb" in results else None,
            usdz_psnr_db=results["usdz"]["psnr_db"] if "usdz" in results else None,
            glb_diffuse_psnr_db=split.get("diffuse_psnr_db"),
            glb_lobes_summed_psnr_db=split.get("lobes_summed_psnr_db"),
        ).stats(),
        "pixels": "fully covered object pixels of the evaluation views, sRGB; Cycles render of the imported asset "
        "vs our render of the trained field",
    }
    with staged_outputs(Path(out_dir)) as staging:
        save_png(staging / "compare.png", to_u8(sheet))
        write_json_atomic(
            staging / "meta.json",
            metadata(
                stage="roundtrip",
                settings=settings.to_dict(),
                inputs={"field": field_path, "eval": eval_path, "export": export_dir},
                outputs={"compare": Path(out_dir) / "compare.png"},
                timings={**timer.seconds, "total": timer.total()},
                extra={"stats": stats, "formats": results, ORIGIN_KEY: origin},
            ),
        )
    return {"stats": stats, "formats": results}


def main(argv: list[str] | None = None) -> int:
    def arguments(parser):
        parser.add_argument("--mesh", required=True, type=Path, help="the traced mesh (.ply)")
        parser.add_argument("--transform", required=True, type=Path)
        parser.add_argument("--field", required=True, type=Path, help="trained field (field.pt)")
        parser.add_argument("--eval", required=True, type=Path, help="evaluation ray cache (.npz)")
        parser.add_argument("--bake-dir", required=True, type=Path)
        parser.add_argument("--export-dir", required=True, type=Path)
        parser.add_argument("--out-dir", required=True, type=Path)
        parser.add_argument("--settings", default="{}")

    def body(args):
        settings = RoundtripSettings.from_json(args.settings)
        run(args.mesh, args.transform, args.field, args.eval, args.bake_dir, args.export_dir, args.out_dir, settings, args.device)

    return stage_main("roundtrip", __doc__, arguments, body, argv, device="cpu")


if __name__ == "__main__":
    raise SystemExit(main())
