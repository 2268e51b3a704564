"""roundtrip: the exported assets through the artist's tool. Each exported file that
``roundtrip.formats`` names by suffix (``model.glb``, ``model.usdz``; the export formats' rows say
which files Blender imports, :data:`stages.config.layout.EXPORT_FORMATS`) is imported into
Blender (``bpy``, the ``blender`` extra), checked (one mesh with every face, positions in metres
and Z-up, UVs, Blender's own tangents against the frame the normal map was baked in, the
Principled BSDF's wiring), and rendered with Cycles from evaluation views under the learned light
(``light.hdr`` as the world for the GLB; the USD brings its DomeLight), then compared with our
render of the trained field over fully covered object pixels (PSNR, sRGB).

Light transport ``direct_unshadowed`` (default) matches what our closed-form renderer models
(light straight from the environment, no self-shadowing), so the figure measures the asset and
the BRDF models; ``full`` path-traces shadows and bounces as an artist's render would.
"""

from __future__ import annotations

import dataclasses
import logging
import tempfile
from pathlib import Path

import numpy as np

from .assets.formats import read_atlas
from .assets.layouts import kept_materials, kept_source, second_set
from .assets.ownformat import asset_geometry, kept_corner_tangents
from .config.layout import EXPORT_FILES, export_format_of
from .config.records import RoundtripRecord
from .config.sections import ExportSettings, RoundtripSettings
from .core.cli import stage_main
from .core.errors import StageInputError
from .core.provenance import ORIGIN_KEY, Timer, metadata, read_origin, staged_outputs, write_json_atomic
from .core.safefiles import read_json
from .geometry.meshio import load_ply
from .geometry.normalization import Similarity
from .geometry.raycache import RayCache
from .geometry.sourcemesh import GLTF_SOURCE
from .imaging.sheets import save_png
from .model.checkpoint import load_field
from .reference.blender import blender_cameras, pick_views
from .reference.roundtrip_job import (
    PASSES,
    RoundtripScene,
    blender_pass,
    comparison_sheet,
    field_renders,
    graded_import,
    lobe_split,
    own_format_check,
)
from .render.color import to_u8

log = logging.getLogger(__name__)


def _check_inputs(paths: list[Path]) -> None:
    for p in paths:
        if not Path(p).is_file():
            raise StageInputError(p, "file not found", "Run the bake and export stages first.")


def _scene(files: dict, settings: RoundtripSettings, device: str, timer: Timer, work: Path) -> RoundtripScene:
    """The cell's exported geometry (as the export stage wrote it: :func:`asset_geometry`), the
    evaluation views to render and our render of them."""
    export_dir, bake_dir = Path(files["export"]), Path(files["bake"])
    export_meta = read_json(export_dir / "meta.json")
    export_settings = ExportSettings.from_dict(export_meta["settings"])
    with timer("load"):
        tf = Similarity.from_json(read_json(files["transform"]))
        atlas = read_atlas(bake_dir / "atlas.npz")
        bake_stats = read_json(bake_dir / "meta.json").get("stats", {})
        kept = kept_source(bake_stats, atlas, files.get("source"), bake_dir)
        second = second_set(bake_stats, atlas)
        materials = None if kept is None else kept_materials(bake_stats, kept, second)
        asset = asset_geometry(load_ply(files["mesh"]), atlas, tf, export_settings, kept, materials, second)
        field, _ = load_field(files["field"], device)
        cache = RayCache(files["eval"])
    tf_export = tf if export_settings.units == "original" or asset.own_frame else None
    views = pick_views(len(cache), settings.views)
    hits = [cache.view(i) for i in views]
    with timer("ours"):
        reference = field_renders(field, cache, views, device, shadows=settings.transport == "full")
    cameras = blender_cameras(np.stack([h.c2w for h in hits]), tf_export, asset.meters_per_unit, asset.own_frame)
    tangents = None if kept is None else kept_corner_tangents(atlas, tf if asset.own_frame else None)
    return RoundtripScene(
        cache,
        views,
        hits,
        cameras,
        reference,
        asset.geom,
        asset.meters_per_unit,
        export_meta,
        settings,
        export_dir,
        work,
        tangents,
        None if kept is None else kept.path,
        kept is not None and kept.kind == GLTF_SOURCE,
    )


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
    source: str | None = None,
) -> dict:
    """Import, check and render the cell's exported assets in Blender; write ``meta.json`` and
    ``compare.png`` into ``out_dir``. Where the bake kept the input's UV layout (``source``: the
    input mesh), the asset in the input's own format is also imported beside the input itself and
    compared (:func:`~stages.reference.roundtrip_job.own_format_check`)."""
    timer = Timer()
    export_dir, bake_dir = Path(export_dir), Path(bake_dir)
    needed = [mesh_path, transform_path, field_path, eval_path, bake_dir / "atlas.npz", export_dir / "meta.json"]
    _check_inputs(needed + [export_dir / EXPORT_FILES[fmt] for fmt in settings.formats] + [export_dir / "light.hdr"])
    origin = read_origin(export_dir / "meta.json")
    files = {
        "mesh": mesh_path,
        "transform": transform_path,
        "field": field_path,
        "eval": eval_path,
        "bake": bake_dir,
        "export": export_dir,
        "source": source,
    }
    results, images, lobes, split_fmt = {}, {}, {}, None
    with tempfile.TemporaryDirectory(prefix="roundtrip-") as work:
        scene = _scene(files, settings, device, timer, Path(work))
        for fmt in settings.formats:
            # the lobes of the format that splits them (the GLB's) are also rendered alone, to
            # split the gap between the BRDF models
            splits = export_format_of(fmt).lobe_split and settings.split_lobes
            split_fmt = fmt if splits else split_fmt
            passes = PASSES if splits else {"full": PASSES["full"]}
            for name, overrides in passes.items():
                res = blender_pass(scene, fmt, name, overrides, timer)
                if name == "full":
                    results[fmt], images[fmt] = graded_import(scene, fmt, res)
                else:
                    lobes[name] = res.renders
        own = own_format_check(scene, timer) if scene.source is not None else None
    split = lobe_split(scene, lobes, split_fmt) if lobes else {}
    if split:
        results[split_fmt]["split"] = split
    stats = _stats(scene, results, split, split_fmt, own)
    front = scene.cache.front_view()
    k = min(range(len(scene.views)), key=lambda j: abs(scene.views[j] - front))
    sheet = comparison_sheet(images[settings.formats[0]].ours[k], {f: c.theirs[k] for f, c in images.items()})
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
                extra={"stats": stats, "formats": results, "own_format": own, ORIGIN_KEY: origin},
            ),
        )
    return {"stats": stats, "formats": results}


def _stats(scene: RoundtripScene, results: dict, split: dict, split_fmt: str | None, own: dict | None = None) -> dict:
    """The stage's statistics: the views, each file's figure (``<suffix>_psnr_db``), the lobes of
    the file that split them (``<suffix>_diffuse_psnr_db``, ...), the record (those figures it has
    a column for; its problems counting the own-format check's, where there is one)."""
    s = scene.settings
    figures = {
        **{f"{fmt}_psnr_db": r["psnr_db"] for fmt, r in results.items()},
        **{f"{split_fmt}_{k}": v for k, v in split.items()},
    }
    columns = {f.name for f in dataclasses.fields(RoundtripRecord)}
    return {
        "views": scene.views,
        "width": scene.cache.width,
        "spp": s.spp,
        **figures,
        **RoundtripRecord(
            problems=sum(len(r["import"]["problems"]) for r in results.values()) + len((own or {}).get("problems", [])),
            transport=s.transport,
            **{k: v for k, v in figures.items() if k in columns},
        ).stats(),
        "pixels": "fully covered object pixels of the evaluation views, sRGB; Cycles render of the imported asset "
        "vs our render of the trained field",
    }


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
        parser.add_argument("--source", help="the input mesh (where the bake kept its UV layout)")

    def body(args):
        settings = RoundtripSettings.from_json(args.settings)
        run(
            args.mesh,
            args.transform,
            args.field,
            args.eval,
            args.bake_dir,
            args.export_dir,
            args.out_dir,
            settings,
            args.device,
            args.source,
        )

    return stage_main("roundtrip", __doc__, arguments, body, argv, device="cpu")


if __name__ == "__main__":
    raise SystemExit(main())
