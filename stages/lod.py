"""lod: levels of detail. The field trained on the traced mesh is baked onto decimated versions of
that mesh (``lod.levels``, face fractions), each level is exported on its own (``lodK/model.glb``,
``.usda``, ``.usdz``) and all of them, with the full bake as ``lod0``, in one USD whose ``/Asset``
has a variant set ``LOD`` (``model_lods.usda``/``.usdz``) and one GLB with ``MSFT_lod``
(``model_lods.glb``).

The high-to-low bake (:func:`stages.assets.baking.bake_level`): every texel of a level looks along
the level's shading normal, forwards and backwards within ``lod.cage`` Hausdorff distances, for the
traced surface, and takes the field's material and predicted normal there; the normal is written in
the level's own frame, so the normal map carries the detail its geometry lost.

Fidelity of each level against the full-resolution neural render: the level's textures read through
its exported frame, rendered by our renderer from the evaluation cameras (traced on the level),
against the trained field rendered on the traced mesh from the same cameras; PSNR (sRGB) over the
pixels both cover, and the silhouettes' intersection over union beside it (a coarse level's outline
differs). ``levels.png`` shows the front evaluation view: the neural render, then lod0, lod1, ...
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from .assets.baking import bake_level, decode_textures, occlusion_samples, render_baked_views
from .assets.formats import (
    Level,
    check_reports,
    export_mesh,
    package_usdz,
    read_atlas,
    validate_glb,
    validate_usd,
    write_glb,
    write_model_files,
    write_usd,
)
from .config.layout import TEXTURE_FILES
from .config.sections import BakeSettings, DecimateSettings, ExportSettings, LodSettings
from .core.cli import stage_main
from .core.errors import StageInputError
from .core.provenance import ORIGIN_KEY, Timer, atomic_path, metadata, read_origin, staged_outputs, write_json_atomic
from .core.safefiles import read_json_record, require_plain_file
from .geometry.decimation import decimate_mesh
from .geometry.meshio import load_ply, save_ply
from .geometry.normalization import Similarity
from .geometry.raycache import RayCache, trace_views
from .geometry.tangents import CornerFrames
from .imaging.quality import psnr
from .imaging.sheets import contact_sheet, save_png
from .imaging.views import ViewStore, radiance_at_hits
from .model.checkpoint import load_field
from .render.color import linear_to_srgb

log = logging.getLogger(__name__)

#: files of the combined asset, in the stage's folder
COMBINED = ("model_lods.usda", "model_lods.usdz", "model_lods.glb")
#: what the metadata keeps of each validator's report
VALIDATION_KEYS = ("ran", "reason", "validators", "validator", "errors", "warnings", "infos", "messages")


def _level_fidelity(reference: list[tuple[np.ndarray, torch.Tensor]], cache: RayCache, rendered: list) -> dict:
    """PSNR (sRGB) of ``rendered`` (per view, linear, in ``cache``'s hit order) against the
    ``reference`` (per view: pixels and sRGB colours) over the pixels both cover, and the
    silhouettes' intersection over union."""
    ours, theirs, inter, union = [], [], 0, 0
    for i, (ref_pix, ref_rgb) in enumerate(reference):
        pix = cache.arrays["pixel"][cache.arrays["offsets"][i] : cache.arrays["offsets"][i + 1]].astype(np.int64)
        common, a, b = np.intersect1d(ref_pix, pix, assume_unique=True, return_indices=True)
        ours.append(linear_to_srgb(rendered[i])[torch.from_numpy(b)])
        theirs.append(ref_rgb[torch.from_numpy(a)])
        inter += len(common)
        union += len(ref_pix) + len(pix) - len(common)
    return {
        "fidelity_psnr_db": psnr(torch.cat(ours), torch.cat(theirs)),
        "silhouette_iou": inter / max(union, 1),
        "pixels_compared": inter,
    }


def _front_image(pixels: np.ndarray, srgb: np.ndarray, width: int) -> torch.Tensor:
    img = np.ones((width * width, 3))
    img[pixels] = np.clip(srgb, 0.0, 1.0)
    return torch.from_numpy(img.reshape(width, width, 3)).permute(2, 0, 1)


def run(
    mesh_path: Path,
    field_path: Path,
    eval_path: Path,
    transform_path: Path,
    bake_dir: Path,
    export_meta: Path,
    out_dir: Path,
    settings: LodSettings,
    bake_settings: BakeSettings,
    export_settings: ExportSettings,
    name: str = "model",
    device: str = "cpu",
    decimate_settings: DecimateSettings | None = None,
) -> dict:
    """Bake, export and grade every level of detail of one grid cell into ``out_dir``; the levels
    are decimated with the mesh's ``decimate_settings`` (welding, sampling) at their own targets."""
    decimate_settings = decimate_settings or DecimateSettings()
    timer = Timer()
    bake_dir, out_dir = Path(bake_dir), Path(out_dir)
    needed = [mesh_path, field_path, eval_path, transform_path, export_meta, bake_dir / "atlas.npz"]
    needed += [bake_dir / "light.exr", bake_dir / "light.hdr"]
    needed += [bake_dir / f for f in TEXTURE_FILES.values()]
    for p in needed:
        if not Path(p).is_file():
            raise StageInputError(p, "file not found", "Run the bake and export stages first.")
    origin = read_origin(bake_dir / "meta.json")
    with timer("load"):
        mesh = load_ply(mesh_path)
        field, _ = load_field(field_path, device)
        atlas0 = read_atlas(bake_dir / "atlas.npz")
        tf = Similarity.from_json(read_json_record(transform_path))
        bake_meta = read_json_record(bake_dir / "meta.json")
        export_stats = read_json_record(export_meta)["stats"]
    faces = len(mesh.faces)
    targets = [max(1, round(f * faces)) for f in settings.levels]
    too_few = [(f, t) for f, t in zip(settings.levels, targets, strict=True) if t < settings.min_faces]
    if too_few:
        raise StageInputError(
            mesh_path,
            f"has {faces} faces, so the levels {[f for f, _ in too_few]} would have {[t for _, t in too_few]} "
            f"faces, fewer than lod.min_faces = {settings.min_faces}",
            "Drop those levels from lod.levels, or lower lod.min_faces.",
        )
    full_size = int(bake_meta["stats"]["texture_size"])
    tf_export = tf if export_settings.units == "original" else None
    light = field.light()
    lobe = field.specular_lobe
    # the levels' occlusion maps: where the bake wrote one, from the same samples of the fine surface
    occlusion = bake_meta["stats"].get("occlusion", {"baked": False})
    with timer("occlusion"):
        ao = occlusion_samples(mesh, occlusion, bake_settings)
    baked_ao = ao is not None

    # the reference: the trained field on the traced mesh from the evaluation cameras
    with timer("reference"):
        eval_cache = RayCache(eval_path)
        store = ViewStore(
            eval_cache, torch.device(device), field.normals, shadows=False
        )  # the textures' fidelity: both unshadowed
        reference = [(eval_cache.view(i).pixel, linear_to_srgb(rgb)) for i, rgb in enumerate(radiance_at_hits(field, store))]
        front = eval_cache.front_view()
        cameras = eval_cache.view_set()

    def grade(level_mesh, uv, textures: dict, frames: CornerFrames) -> tuple[dict, torch.Tensor]:
        arrays, _ = trace_views(level_mesh, cameras)
        cache = RayCache(f"<{len(level_mesh.faces)}-face level traced from {eval_path}>", arrays)
        rendered = render_baked_views(cache, uv, decode_textures(textures), frames, light, device, lobe, field.brdf)
        lo, hi = arrays["offsets"][front], arrays["offsets"][front + 1]
        image = _front_image(
            arrays["pixel"][lo:hi].astype(np.int64), linear_to_srgb(rendered[front]).cpu().numpy(), eval_cache.width
        )
        return _level_fidelity(reference, cache, rendered), image

    rows, levels, images = [], [], [_front_image(reference[front][0], reference[front][1].cpu().numpy(), eval_cache.width)]
    with staged_outputs(out_dir) as staging:
        # lod0: the full bake, as the export stage shipped it
        with timer("lod0"):
            for rel in TEXTURE_FILES.values():
                with atomic_path(staging / "lod0" / rel) as tmp:
                    shutil.copyfile(bake_dir / rel, tmp)
            from_bake = {k: np.asarray(_png(bake_dir / rel)) for k, rel in TEXTURE_FILES.items()}
            fidelity, image = grade(mesh, atlas0["uv"].astype(np.float64), from_bake, CornerFrames.from_arrays(atlas0))
            images.append(image)
            geom0 = export_mesh(mesh, atlas0, tf_export, export_settings.weld)
            levels.append(Level("lod0", geom0, "lod0/textures"))
            rows.append(
                {
                    "level": "lod0",
                    "fraction": 1.0,
                    "faces": faces,
                    "vertices_exported": len(geom0.positions),
                    "texture_size": full_size,
                    "bake_seconds": float(bake_meta["timings_s"]["bake"]),
                    "file_bytes": {k: export_stats["file_bytes"][k] for k in ("model.glb", "model.usdz")},
                    "files": "export/model.glb, export/model.usdz (the export stage's)",
                    **fidelity,
                }
            )
        for k, (fraction, target) in enumerate(zip(settings.levels, targets, strict=True), start=1):
            tag = f"lod{k}"
            t_dec = Timer()
            with t_dec("decimate"):
                level_settings = dataclasses.replace(decimate_settings, enabled=True, target_faces=target)
                dec = decimate_mesh(mesh, level_settings, f"{mesh_path} ({tag})")
            low = dec.mesh
            hausdorff = float(dec.stats["hausdorff_max"])
            search = settings.cage * hausdorff + 1e-6
            size = settings.level_texture_size(full_size, fraction)
            with t_dec("bake"):
                res = bake_level(mesh, low, field, size, bake_settings, search, device, ao)
            with t_dec("write"):
                for key, rel in TEXTURE_FILES.items():
                    save_png(staging / tag / rel, res.textures[key])
                atlas = {"uv": res.texels.atlas.uv, **res.frames.arrays()}
                geom = export_mesh(low, atlas, tf_export, export_settings.weld)
                levels.append(Level(tag, geom, f"{tag}/textures"))
                for fname in ("light.exr", "light.hdr"):
                    with atomic_path(staging / tag / fname) as tmp:
                        shutil.copyfile(bake_dir / fname, tmp)
                # the level in the normalised frame with its atlas and frame, as the bake writes them
                # (what a round trip or a later re-grade of the level reads)
                save_ply(staging / tag / "mesh.ply", low)
                with atomic_path(staging / tag / "atlas.npz") as tmp:
                    with open(tmp, "wb") as fh:
                        np.savez(fh, uv=res.texels.atlas.uv.astype(np.float32), **res.frames.arrays())
                mpu, root = export_settings.meters_per_unit, export_settings.usdz_root
                checked = write_model_files(staging / tag, geom, mpu, root, name, origin, brdf=field.brdf, occlusion=baked_ao)
            with t_dec("grade"):
                fidelity, image = grade(low, res.texels.atlas.uv, res.textures, res.frames)
                images.append(image)
            found, opposite = res.projection.found, res.projection.opposite
            offset = np.abs(res.projection.offset[found])
            rows.append(
                {
                    "level": tag,
                    "fraction": fraction,
                    "faces": len(low.faces),
                    "target_faces": target,
                    "target_reached": bool(dec.stats.get("target_reached", True)),
                    "hausdorff_max": hausdorff,
                    "search_distance": search,
                    "texels_on_traced_surface": float(found.mean()),
                    "texels_on_faces_turned_away": float(opposite.mean()),
                    "offset_p95": float(np.percentile(offset, 95)) if len(offset) else None,
                    "vertices_exported": len(geom.positions),
                    "texture_size": size,
                    "texel_coverage": float(res.texels.filled.mean()),
                    "decimate_seconds": t_dec.seconds["decimate"],
                    "bake_seconds": t_dec.seconds["bake"],
                    "file_bytes": {f: (staging / tag / f).stat().st_size for f in ("model.glb", "model.usdz")},
                    "files": f"lod/{tag}/model.glb, lod/{tag}/model.usdz, lod/{tag}/model.usda",
                    "validation": {
                        **{r["file"]: {k: r[k] for k in VALIDATION_KEYS if k in r} for r in checked["usd"]},
                        "model.glb": {k: checked["gltf"][k] for k in VALIDATION_KEYS if k in checked["gltf"]},
                    },
                    **fidelity,
                }
            )
            write_json_atomic(
                staging / tag / "meta.json",
                metadata(
                    stage="lod",
                    settings=export_settings.to_dict(),
                    inputs={"mesh": mesh_path, "field": field_path, "bake": bake_dir},
                    outputs={f: out_dir / tag / f for f in ("model.glb", "model.usdz", "model.usda", "mesh.ply", "atlas.npz")},
                    timings=t_dec.seconds,
                    extra={"stats": rows[-1], "lod_settings": settings.to_dict(), ORIGIN_KEY: origin},
                ),
            )
            log.info(
                "%s: %d faces (%.0f%%), %.1f dB against the full neural render (silhouette IoU %.3f), %d bytes GLB",
                tag,
                len(low.faces),
                100 * fraction,
                fidelity["fidelity_psnr_db"],
                fidelity["silhouette_iou"],
                rows[-1]["file_bytes"]["model.glb"],
            )
        with timer("combined"):
            with atomic_path(staging / "light.exr") as tmp:
                shutil.copyfile(bake_dir / "light.exr", tmp)
            coverage = settings.screen_coverage()
            switch = {"tango_stylize_lod": {"levels": [r["level"] for r in rows], "msft_screencoverage": coverage}}
            with atomic_path(staging / "model_lods.usda") as tmp:
                tmp.unlink()
                write_usd(
                    tmp, levels, export_settings.meters_per_unit, "light.exr", origin, switch, brdf=field.brdf, occlusion=baked_ao
                )
            files = [f"{lv.textures}/{key}.png" for lv in levels for key in TEXTURE_FILES] + ["light.exr"]
            package_usdz(staging / "model_lods.usda", staging / "model_lods.usdz", files, export_settings.usdz_root)
            write_glb(
                staging / "model_lods.glb",
                levels[0].geom,
                staging / "lod0" / "textures",
                export_settings.meters_per_unit,
                name,
                origin,
                lods=[(lv.geom, staging / lv.textures) for lv in levels[1:]],
                screen_coverage=coverage,
                brdf=field.brdf,
                occlusion=baked_ao,
            )
        with timer("validate"):
            checked = {rel: validate_usd(staging / rel) for rel in ("model_lods.usda", "model_lods.usdz")}
            checked["model_lods.glb"] = validate_glb(staging / "model_lods.glb")
        check_reports(checked, out_dir)
        with timer("figure"):
            save_png(staging / "levels.png", contact_sheet(images, len(images)))
        stats = {
            "levels": rows,
            "screen_coverage": coverage,
            "combined_file_bytes": {f: (staging / f).stat().st_size for f in COMBINED},
            "validation": {
                **{f"{r['level']}/{f}": v for r in rows[1:] for f, v in r["validation"].items()},
                **{rel: {k: r[k] for k in VALIDATION_KEYS if k in r} for rel, r in checked.items()},
            },
            "fidelity": "sRGB PSNR over the pixels both the level and the traced mesh cover, evaluation views: "
            "the level's textures through its exported frame (our renderer) vs the trained field on the traced mesh",
            "figure": "levels.png: front evaluation view; the neural render on the traced mesh, then lod0, lod1, ...",
        }
        write_json_atomic(
            staging / "meta.json",
            metadata(
                stage="lod",
                settings={"lod": settings.to_dict(), "bake": bake_settings.to_dict(), "export": export_settings.to_dict()},
                inputs={"mesh": mesh_path, "field": field_path, "eval": eval_path, "bake": bake_dir, "export": export_meta},
                outputs={f: out_dir / f for f in COMBINED},
                timings={**timer.seconds, "total": timer.total()},
                extra={"stats": stats, ORIGIN_KEY: origin},
            ),
        )
    # a level folder of an earlier run with more levels is not part of this asset any more
    keep = {r["level"] for r in rows}
    for old in sorted(Path(out_dir).glob("lod*")):
        if old.is_dir() and old.name not in keep:
            log.info("removing %s: not a level of this run", old)
            shutil.rmtree(old)
    return stats


def _png(path: Path):
    with Image.open(require_plain_file(path, remedy="Run the bake stage again.")) as img:
        return np.asarray(img.convert("RGB"))


def main(argv: list[str] | None = None) -> int:
    def arguments(parser):
        parser.add_argument("--mesh", required=True, type=Path, help="the traced mesh (.ply) the field was trained on")
        parser.add_argument("--field", required=True, type=Path, help="trained field (field.pt)")
        parser.add_argument("--eval", required=True, type=Path, help="evaluation ray cache (.npz)")
        parser.add_argument("--transform", required=True, type=Path)
        parser.add_argument("--bake-dir", required=True, type=Path)
        parser.add_argument("--export-meta", required=True, type=Path, help="the export stage's meta.json (lod0's files)")
        parser.add_argument("--out-dir", required=True, type=Path)
        parser.add_argument("--name", default="model")
        parser.add_argument("--settings", default="{}", help="JSON of the lod settings")
        parser.add_argument("--bake-settings", default="{}", help="JSON of the bake settings (padding, dilation)")
        parser.add_argument("--export-settings", default="{}", help="JSON of the export settings (units, weld)")
        parser.add_argument("--decimate-settings", default="{}", help="JSON of the mesh's decimate settings (welding, sampling)")

    def body(args):
        run(
            args.mesh,
            args.field,
            args.eval,
            args.transform,
            args.bake_dir,
            args.export_meta,
            args.out_dir,
            LodSettings.from_json(args.settings),
            BakeSettings.from_json(args.bake_settings),
            ExportSettings.from_json(args.export_settings),
            args.name,
            args.device,
            DecimateSettings.from_json(args.decimate_settings),
        )

    return stage_main("lod", __doc__, arguments, body, argv, device="cpu")


if __name__ == "__main__":
    raise SystemExit(main())
