"""export: turn a bake into an asset pack: the asset in every export format (the table
:data:`stages.config.layout.EXPORT_FORMATS`, the writers :mod:`stages.assets.formats`: glTF 2.0,
``model.glb``; USD, ``model.usda`` + packaged ``model.usdz``), textures, the learned light and a
preview image, each file validated. The learned light's environment ships as ``light.exr`` (the
USD's DomeLight) and its suns as lights in the files (glTF ``KHR_lights_punctual`` directional
lights, USD ``DistantLight`` s).

Where the bake kept the input's UV layout (``bake.uv``), the asset is the input's own topology
(:mod:`stages.assets.ownformat`): a glTF input's own document with new materials, an OBJ input's
own lines with a new material library (``model.obj``, ``model.mtl``) beside the USD and glTF files.
Where it made a second UV set for a glTF input, the document also gets that set
(:mod:`stages.assets.gltfuvset`), its own UVs kept; the USD holds the bake's set.

Geometry is returned to the input's units through the normalisation's inverse transform (or left
normalised, ``units: normalized``); the material mapping and what each format loses are in
its module of :mod:`stages.assets.formats`.
"""

from __future__ import annotations

import logging
from pathlib import Path

from PIL import Image

from .assets import formats
from .assets.formats import AssetInfo, read_atlas, recorded_lights, write_asset_files
from .assets.gltfuvset import SecondSet
from .assets.layouts import kept_materials, kept_source, second_set
from .assets.ownformat import asset_geometry, input_faults, own_document, write_obj
from .config.brdfs import brdf_spec
from .config.layout import TEXTURE_FILES, export_files
from .config.records import ExportRecord
from .config.sections import ExportSettings
from .core.cli import stage_main
from .core.errors import StageInputError
from .core.provenance import ORIGIN_KEY, Timer, metadata, read_origin, staged_outputs, write_json_atomic
from .core.safefiles import IMAGE_LIMIT, copy_file, open_read, read_json
from .geometry.meshio import load_ply
from .geometry.normalization import Similarity
from .geometry.sourcemesh import GLTF_SOURCE, OBJ_SOURCE

log = logging.getLogger(__name__)


def run(
    mesh_path: Path,
    transform_path: Path,
    bake_dir: Path,
    preview: Path,
    out_dir: Path,
    settings: ExportSettings,
    name: str = "model",
    source: str | None = None,
) -> dict:
    """Write the asset pack of one grid cell into ``out_dir`` (``source``: the input mesh, read
    where the bake kept its UV layout)."""
    timer = Timer()
    bake_dir, out_dir = Path(bake_dir), Path(out_dir)
    needed = [mesh_path, transform_path, bake_dir / "atlas.npz", bake_dir / "light.exr", preview]
    needed += [bake_dir / f for f in TEXTURE_FILES.values()]
    for p in needed:
        if not Path(p).is_file():
            raise StageInputError(p, "file not found", "Run the bake stage first.")
    origin = read_origin(bake_dir / "meta.json")
    mesh = load_ply(mesh_path)
    atlas = read_atlas(bake_dir / "atlas.npz")
    tf = Similarity.from_json(read_json(transform_path))
    bake_stats = read_json(bake_dir / "meta.json").get("stats", {})
    brdf = brdf_spec(bake_stats.get("brdf", "tango"))  # the BRDF the bake's textures hold
    occlusion = bool(bake_stats.get("occlusion", {}).get("baked", False))
    kept = kept_source(bake_stats, atlas, source, bake_dir)
    second = second_set(bake_stats, atlas)
    materials = None if kept is None else kept_materials(bake_stats, kept, second)
    asset = asset_geometry(mesh, atlas, tf, settings, kept, materials, second)
    geom = asset.geom
    # the learned suns, their directions in the files' frame (the input's own: R^T d)
    lights = recorded_lights(bake_stats, tf.rotation.T if asset.own_frame else None)
    extra_files: list[str] = []
    with staged_outputs(out_dir) as staging:
        with timer("copy"):
            for rel in geom.texture_files():  # every texture set (a kept layout may have one per slot)
                copy_file(bake_dir / rel, staging / rel, remedy="Rerun the bake stage.")
            for fname in ("light.exr", "light.hdr"):
                copy_file(bake_dir / fname, staging / fname, remedy="Rerun the bake stage.")
            copy_file(preview, staging / "preview.png", remedy="Rerun the bake stage.")
        instead, changed = {}, []  # a glTF input's own document; what of it was not carried over, and why
        uv_set = None if second is None else SecondSet(second)
        inherited, input_report = {}, None  # the faults the input's document has itself, handed on
        if kept is not None and kept.kind == GLTF_SOURCE:
            instead = own_document(kept, origin, brdf, occlusion, geom.slot_textures, changed, lights, uv_set)
            with timer("validate_input"):
                inherited, input_report = input_faults(kept)
        if kept is not None and kept.kind == OBJ_SOURCE:
            with timer("obj"):
                extra_files = write_obj(staging, geom, kept, None if settings.units == "original" else tf, brdf)
        info = AssetInfo(asset.meters_per_unit, name, origin, brdf, occlusion, settings, lights=lights)
        reports = write_asset_files(staging, geom, info, timer, instead, inherited)
        files = export_files()
        with open_read(staging / TEXTURE_FILES["basecolor"], IMAGE_LIMIT) as fh, Image.open(fh) as img:
            texture_size = int(img.size[0])
        stats = {
            "faces": len(mesh.faces),
            "vertices_exported": len(geom.positions),
            "topology": topology(kept, second),
            # the bake's UV set beside the input's own (bake.uv: second): where, and the seam vertices it appended
            "second_uv_set": None if uv_set is None or uv_set.written is None else uv_set.written.record(),
            "extra_files": extra_files,
            "input_document_changes": changed,
            # the Khronos validator on the glTF input itself: its errors are handed on, not the export's
            "input_validation": input_report,
            # the files' frame: metres per unit, and whether positions are the input's own
            "meters_per_unit": asset.meters_per_unit,
            "own_frame": asset.own_frame,
            "corners": 3 * len(geom.indices),
            "file_bytes": {f: (staging / f).stat().st_size for f in files.values()},
            "texture_size": texture_size,
            "brdf": brdf.name,
            "occlusion": occlusion,
            # the learned suns as the files carry them (glTF KHR_lights_punctual, USD DistantLight)
            "distant_lights": [light.record() for light in lights],
            "validation": reports,
            **ExportRecord(**{k: v for e in formats.exporters() for k, v in e.record(reports).items()}).stats(),
            "bounds": [geom.positions.min(0).tolist(), geom.positions.max(0).tolist()],
        }
        write_json_atomic(
            staging / "meta.json",
            metadata(
                stage="export",
                settings=settings.to_dict(),
                inputs={"mesh": mesh_path, "transform": transform_path, "bake": bake_dir},
                outputs={k: out_dir / k for k in (*files.values(), *extra_files)},
                timings={**timer.seconds, "total": timer.total()},
                extra={"stats": stats, ORIGIN_KEY: origin},
            ),
        )
    return stats


def topology(kept, second) -> str:
    """What the asset's geometry is: the traced mesh, or the input's own (with its layout, or
    with a second UV set for the bake)."""
    if kept is None:
        return "the traced mesh, welded"
    return "the input's own (kept UV layout)" if second is None else "the input's own, with a second UV set for the bake"


def main(argv: list[str] | None = None) -> int:
    def arguments(parser):
        parser.add_argument("--mesh", required=True, type=Path)
        parser.add_argument("--transform", required=True, type=Path)
        parser.add_argument("--bake-dir", required=True, type=Path)
        parser.add_argument("--preview", required=True, type=Path, help="preview image to ship (PNG)")
        parser.add_argument("--out-dir", required=True, type=Path)
        parser.add_argument("--name", default="model")
        parser.add_argument("--settings", default="{}")
        parser.add_argument("--source", help="the input mesh (read where the bake kept its UV layout)")

    def body(args):
        settings = ExportSettings.from_json(args.settings)
        run(args.mesh, args.transform, args.bake_dir, args.preview, args.out_dir, settings, args.name, args.source)

    return stage_main("export", __doc__, arguments, body, argv)


if __name__ == "__main__":
    raise SystemExit(main())
