"""lod: levels of detail. The field trained on the traced mesh is baked onto decimated versions of
that mesh (``lod.levels``, face fractions), each level is exported on its own in every export
format (``lodK/model.glb``, ``.usda``, ``.usdz``) and all of them, with the full bake as ``lod0``,
in one file of each format that holds levels (``model_lods.*``: one USD whose ``/Asset`` has a
variant set ``LOD``, one GLB with ``MSFT_lod``).

The high-to-low bake (:func:`stages.assets.baking.bake_level`): every texel of a level looks along
the level's shading normal, forwards and backwards within ``lod.cage`` Hausdorff distances, for the
traced surface, and takes the field's material and predicted normal there; the normal is written in
the level's own frame, so the normal map carries the detail its geometry lost. Each level is graded
against the full-resolution neural render (:mod:`stages.assets.levels`); ``levels.png`` shows the
front evaluation view: the neural render, then lod0, lod1, ...
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

from .assets.baking import occlusion_samples
from .assets.formats import check_reports, read_atlas
from .assets.levels import (
    VALIDATION_KEYS,
    LevelGrader,
    LevelPlan,
    LevelRecord,
    LodSource,
    combined_files,
    make_level,
    make_lod0,
    write_combined,
)
from .config.layout import TEXTURE_FILES
from .config.records import LodRecord
from .config.sections import BakeSettings, DecimateSettings, ExportSettings, LodSettings
from .core.cli import stage_main
from .core.errors import ConfigError, StageInputError
from .core.provenance import ORIGIN_KEY, Timer, metadata, read_origin, staged_outputs, write_json_atomic
from .core.safefiles import read_json, remove_tree
from .geometry.meshio import load_ply
from .geometry.normalization import Similarity
from .imaging.sheets import contact_sheet, save_png
from .model.checkpoint import load_field

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CellFiles:
    """The files of a trained cell the levels are made from: the traced ``mesh`` (.ply) the field
    was trained on, the trained ``field``, the ``eval`` ray cache, the normalisation ``transform``,
    the bake's folder and the export stage's ``meta.json``."""

    mesh: Path
    field: Path
    eval: Path
    transform: Path
    bake_dir: Path
    export_meta: Path

    def check(self) -> None:
        needed = [self.mesh, self.field, self.eval, self.transform, self.export_meta, self.bake_dir / "atlas.npz"]
        needed += [self.bake_dir / "light.exr", self.bake_dir / "light.hdr"]
        needed += [self.bake_dir / f for f in TEXTURE_FILES.values()]
        for p in needed:
            if not Path(p).is_file():
                raise StageInputError(p, "file not found", "Run the bake and export stages first.")


def _source(files: CellFiles, bake: BakeSettings, export: ExportSettings, name: str, device: str) -> LodSource:
    """What every level is made from, read from the cell's files."""
    mesh = load_ply(files.mesh)
    bake_meta = read_json(files.bake_dir / "meta.json")
    sets = bake_meta["stats"].get("uv", {}).get("texture_sets", [])
    if len(sets) > 1:  # lod0 is one material on the traced mesh; one texture set per slot has no place there
        raise StageInputError(
            files.bake_dir / "meta.json",
            f"the bake kept the input's UV layout with {len(sets)} texture sets (one per material slot), "
            "and levels of detail hold one material",
            "Set bake.uv: atlas for cells with lod.enabled, or turn lod off for this mesh.",
        )
    # the levels' occlusion maps: where the bake wrote one, from the same samples of the fine surface
    occlusion = occlusion_samples(mesh, bake_meta["stats"].get("occlusion", {"baked": False}), bake)
    return LodSource(
        mesh=mesh,
        field=load_field(files.field, device)[0],
        bake_dir=files.bake_dir,
        atlas=read_atlas(files.bake_dir / "atlas.npz"),
        bake_meta=bake_meta,
        export_stats=read_json(files.export_meta)["stats"],
        transform=Similarity.from_json(read_json(files.transform)),
        bake=bake,
        export=export,
        occlusion=occlusion,
        origin=read_origin(files.bake_dir / "meta.json"),
        name=name,
        device=device,
        inputs={"mesh": files.mesh, "field": files.field, "bake": files.bake_dir},
    )


def _plans(files: CellFiles, faces: int, settings: LodSettings) -> list[LevelPlan]:
    """The decimated levels to make, refused where one would have fewer than ``lod.min_faces``."""
    targets = [max(1, round(f * faces)) for f in settings.levels]
    too_few = [(f, t) for f, t in zip(settings.levels, targets, strict=True) if t < settings.min_faces]
    if too_few:
        raise StageInputError(
            files.mesh,
            f"has {faces} faces, so the levels {[f for f, _ in too_few]} would have {[t for _, t in too_few]} "
            f"faces, fewer than lod.min_faces = {settings.min_faces}",
            "Drop those levels from lod.levels, or lower lod.min_faces.",
        )
    return [LevelPlan(f"lod{k}", f, t) for k, (f, t) in enumerate(zip(settings.levels, targets, strict=True), start=1)]


def _stats(records: list[LevelRecord], coverage: list[float], checked: dict, staging: Path) -> dict:
    """The stage's statistics: one row per level, the combined files and every validator's report."""
    rows = [r.row() for r in records]
    return {
        **LodRecord(levels=rows).stats(),
        "screen_coverage": coverage,
        "combined_file_bytes": {f: (staging / f).stat().st_size for f in combined_files()},
        "validation": {
            **{f"{r['level']}/{f}": v for r in rows[1:] for f, v in r["validation"].items()},
            **{rel: {k: r[k] for k in VALIDATION_KEYS if k in r} for rel, r in checked.items()},
        },
        "fidelity": "sRGB PSNR over the pixels both the level and the traced mesh cover, evaluation views: "
        "the level's textures through its exported frame (our renderer) vs the trained field on the traced mesh",
        "figure": "levels.png: front evaluation view; the neural render on the traced mesh, then lod0, lod1, ...",
    }


def run(
    files: CellFiles,
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
    timer, out_dir = Timer(), Path(out_dir)
    files.check()
    with timer("load"):
        source = _source(files, bake_settings, export_settings, name, device)
    plans = _plans(files, len(source.mesh.faces), settings)
    with timer("reference"):
        grader = LevelGrader(source, files.eval)
    with staged_outputs(out_dir) as staging:
        with timer("lod0"):
            records = [make_lod0(source, grader, staging)]
        for plan in plans:
            with timer(plan.tag):
                records.append(
                    make_level(source, grader, plan, settings, decimate_settings or DecimateSettings(), staging, out_dir)
                )
        coverage = settings.screen_coverage()
        with timer("combined"):
            checked = write_combined(source, staging, records, coverage)
        check_reports(checked, out_dir)
        with timer("figure"):
            images = [grader.reference_image()] + [r.image for r in records]
            save_png(staging / "levels.png", contact_sheet(images, len(images)))
        stats = _stats(records, coverage, checked, staging)
        write_json_atomic(
            staging / "meta.json",
            metadata(
                stage="lod",
                settings={"lod": settings.to_dict(), "bake": bake_settings.to_dict(), "export": export_settings.to_dict()},
                inputs={
                    "mesh": files.mesh,
                    "field": files.field,
                    "eval": files.eval,
                    "bake": files.bake_dir,
                    "export": files.export_meta,
                },
                outputs={f: out_dir / f for f in combined_files()},
                timings={**timer.seconds, "total": timer.total()},
                extra={"stats": stats, ORIGIN_KEY: source.origin},
            ),
        )
    _remove_old_levels(out_dir, {r.level for r in records})
    return stats


def _remove_old_levels(out_dir: Path, keep: set[str]) -> None:
    """A level folder of an earlier run with more levels is not part of this asset any more."""
    for old in sorted(out_dir.glob("lod*")):
        if old.is_dir() and old.name not in keep:
            log.info("removing %s: not a level of this run", old)
            remove_tree(old)


#: the sections ``--settings`` holds, and their classes
SETTINGS_SECTIONS = {"lod": LodSettings, "bake": BakeSettings, "export": ExportSettings, "decimate": DecimateSettings}


def parse_settings(text: str) -> dict:
    """``--settings``: one JSON object with the lod, bake, export and decimate settings (each
    section optional: its defaults), as settings objects."""
    data = json.loads(text or "{}")
    if not isinstance(data, dict) or set(data) - set(SETTINGS_SECTIONS):
        raise ConfigError(f"lod --settings must be a JSON object of the sections {', '.join(SETTINGS_SECTIONS)}")
    return {name: cls.from_dict(data.get(name)) for name, cls in SETTINGS_SECTIONS.items()}


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
        parser.add_argument(
            "--settings",
            default="{}",
            help="JSON: {lod: ..., bake: ..., export: ..., decimate: ...} (the mesh's decimate settings)",
        )

    def body(args):
        s = parse_settings(args.settings)
        files = CellFiles(args.mesh, args.field, args.eval, args.transform, args.bake_dir, args.export_meta)
        run(files, args.out_dir, s["lod"], s["bake"], s["export"], args.name, args.device, s["decimate"])

    return stage_main("lod", __doc__, arguments, body, argv, device="cpu")


if __name__ == "__main__":
    raise SystemExit(main())
