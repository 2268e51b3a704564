"""Levels of detail of a trained cell's asset: each level decimated from the traced mesh, baked from
the trained field through the traced surface (high-to-low, :func:`~stages.assets.baking.bake_level`),
exported in every export format (:func:`~stages.assets.formats.write_asset_files`), graded against
the trained field, and recorded as one :class:`LevelRecord`; then all of them in one file of each
format that holds levels (:meth:`~stages.assets.formats.base.Exporter.write_levels`: one USD with a
``LOD`` variant set, one GLB with ``MSFT_lod``).

Fidelity of each level against the full-resolution neural render (:class:`LevelGrader`): the
level's textures read through its exported frame, rendered by our renderer from the evaluation
cameras (traced on the level), against the trained field rendered on the traced mesh from the same
cameras; PSNR (sRGB) over the pixels both cover, and the silhouettes' intersection over union
beside it (a coarse level's outline differs).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from ..config.layout import LEVELS_STEM, TEXTURE_FILES, export_files
from ..config.sections import BakeSettings, DecimateSettings, ExportSettings, LodSettings
from ..core.provenance import ORIGIN_KEY, Timer, metadata, write_json_atomic
from ..core.safefiles import IMAGE_LIMIT, atomic_stream, copy_file, open_read
from ..geometry.decimation import decimate_mesh
from ..geometry.meshio import TriMesh, save_ply
from ..geometry.normalization import Similarity
from ..geometry.raycache import RayCache, trace_views
from ..geometry.tangents import CornerFrames
from ..geometry.visibility import OcclusionSamples
from ..imaging.quality import psnr
from ..imaging.sheets import save_png
from ..imaging.views import ViewStore, radiance_at_hits
from ..render.color import linear_to_srgb
from . import formats
from .baking import bake_level, decode_textures, render_baked_views
from .formats import AssetInfo, Level, export_mesh, recorded_lights, write_asset_files
from .layouts import SECOND

log = logging.getLogger(__name__)

#: what the metadata keeps of each validator's report
VALIDATION_KEYS = ("ran", "reason", "validators", "validator", "errors", "warnings", "infos", "messages")
#: the files each decimated level's folder holds besides its textures and its exported files
LEVEL_FILES = ("mesh.ply", "atlas.npz")


def combined_files() -> tuple[str, ...]:
    """The files of the combined asset, in the stage's folder: one of each suffix of every export
    format that holds every level in one file (``model_lods.<suffix>``)."""
    return tuple(export_files(LEVELS_STEM, levels=True).values())


@dataclass(frozen=True)
class LodSource:
    """What every level is made from: the traced ``mesh`` and the trained ``field``, the full bake
    (its folder, ``atlas`` and metadata) and how the export stage shipped it (``export_stats``), with
    the settings of the bake and the export, the ``occlusion`` samples of the fine surface (None
    where the bake wrote no occlusion map), the cell's ``origin`` record, the assets' ``name`` and the
    torch ``device``."""

    mesh: TriMesh
    field: object
    bake_dir: Path
    atlas: dict
    bake_meta: dict
    export_stats: dict
    transform: Similarity
    bake: BakeSettings
    export: ExportSettings
    occlusion: OcclusionSamples | None
    origin: dict
    name: str
    device: str
    #: the files it was read from (mesh, field, bake), for the levels' metadata
    inputs: dict

    @property
    def full_size(self) -> int:
        """The full bake's texture width."""
        return int(self.bake_meta["stats"]["texture_size"])

    @property
    def export_transform(self) -> Similarity | None:
        """The transform the exported geometry takes (None: the normalised frame)."""
        return self.transform if self.export.units == "original" else None

    def asset_info(self) -> AssetInfo:
        """What every level's files (and the combined ones) write beside their geometry."""
        brdf, occlusion = self.field.brdf.spec, self.occlusion is not None
        lights = recorded_lights(self.bake_meta.get("stats", {}))
        return AssetInfo(self.export.meters_per_unit, self.name, self.origin, brdf, occlusion, self.export, lights=lights)


class LevelGrader:
    """The trained field on the traced mesh from the evaluation cameras (unshadowed, as the
    textures are), against which each level's textures are graded."""

    def __init__(self, source: LodSource, eval_path: Path) -> None:
        self.source, self.eval_path = source, eval_path
        self.cache = RayCache(eval_path)
        field = source.field
        store = ViewStore(self.cache, torch.device(source.device), field.normals, shadows=False)
        radiance = radiance_at_hits(field, store)
        self.reference = [(self.cache.view(i).pixel, linear_to_srgb(rgb)) for i, rgb in enumerate(radiance)]
        self.front = self.cache.front_view()
        self.cameras = self.cache.view_set()
        self.light = field.light()

    def reference_image(self) -> torch.Tensor:
        """The front evaluation view of the neural render on the traced mesh."""
        pixels, rgb = self.reference[self.front]
        return front_image(pixels, rgb.cpu().numpy(), self.cache.width)

    def grade(
        self, level_mesh: TriMesh, uv: np.ndarray, textures: dict, frames: CornerFrames, wrap: bool = False
    ) -> tuple[dict, torch.Tensor]:
        """The level's fidelity figures and its front view (``wrap``: its textures repeat)."""
        field = self.source.field
        arrays, _ = trace_views(level_mesh, self.cameras)
        cache = RayCache(f"<{len(level_mesh.faces)}-face level traced from {self.eval_path}>", arrays)
        lobe = field.specular_lobe
        rendered = render_baked_views(
            cache, uv, decode_textures(textures), frames, self.light, self.source.device, lobe, field.brdf, wrap
        )
        lo, hi = arrays["offsets"][self.front], arrays["offsets"][self.front + 1]
        srgb = linear_to_srgb(rendered[self.front]).cpu().numpy()
        return level_fidelity(self.reference, cache, rendered), front_image(
            arrays["pixel"][lo:hi].astype(np.int64), srgb, cache.width
        )


def level_fidelity(reference: list[tuple[np.ndarray, torch.Tensor]], cache: RayCache, rendered: list) -> dict:
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


def front_image(pixels: np.ndarray, srgb: np.ndarray, width: int) -> torch.Tensor:
    """A ``(3, width, width)`` image, white where no pixel of ``pixels`` has a colour."""
    img = np.ones((width * width, 3))
    img[pixels] = np.clip(srgb, 0.0, 1.0)
    return torch.from_numpy(img.reshape(width, width, 3)).permute(2, 0, 1)


@dataclass
class LevelRecord:
    """One level as made: its row in the stage's statistics (what the summary and the report
    read), the level for the combined asset, and its tile of ``levels.png``. The decimated levels'
    own figures (``target_faces`` ...) are None for ``lod0``, the full bake, and left out of its row."""

    level: str
    fraction: float
    faces: int
    vertices_exported: int
    texture_size: int
    bake_seconds: float
    file_bytes: dict[str, int]
    files: str
    fidelity: dict
    asset: Level = dataclasses.field(repr=False)
    image: torch.Tensor = dataclasses.field(repr=False)
    target_faces: int | None = None
    target_reached: bool | None = None
    hausdorff_max: float | None = None
    search_distance: float | None = None
    texels_on_traced_surface: float | None = None
    texels_on_faces_turned_away: float | None = None
    offset_p95: float | None = None
    texel_coverage: float | None = None
    decimate_seconds: float | None = None
    validation: dict | None = None
    #: the level's UV layout: the bake's (lod0: the input's own or an atlas), a new atlas (decimated)
    uv_layout: str = "atlas"

    #: the row's keys in the order the metadata writes them
    ROW = (
        "level",
        "fraction",
        "uv_layout",
        "faces",
        "target_faces",
        "target_reached",
        "hausdorff_max",
        "search_distance",
        "texels_on_traced_surface",
        "texels_on_faces_turned_away",
        "offset_p95",
        "vertices_exported",
        "texture_size",
        "texel_coverage",
        "decimate_seconds",
        "bake_seconds",
        "file_bytes",
        "files",
        "validation",
    )

    def row(self) -> dict:
        """The level's row of the stage's statistics: every figure it has, then its fidelity."""
        decimated = self.target_faces is not None
        row = {k: getattr(self, k) for k in self.ROW if decimated or getattr(self, k) is not None}
        return {**row, **self.fidelity}


def make_lod0(source: LodSource, grader: LevelGrader, staging: Path) -> LevelRecord:
    """``lod0``: the full bake, as the export stage shipped it (its textures copied, graded); on
    the traced mesh's topology, in the input's own layout where the bake kept it."""
    for rel in TEXTURE_FILES.values():
        copy_file(source.bake_dir / rel, staging / "lod0" / rel, remedy="Run the bake stage again.")
    from_bake = {key: _texture(source.bake_dir / rel) for key, rel in TEXTURE_FILES.items()}
    uv = source.atlas["uv"].astype(np.float64)
    kept = "source_face" in source.atlas  # a layout of the input's triangles: its textures repeat
    fidelity, image = grader.grade(source.mesh, uv, from_bake, CornerFrames.from_arrays(source.atlas), kept)
    second = source.bake_meta["stats"].get("uv", {}).get("layout") == SECOND
    what = "second (a set made for the bake" if second else "kept (the input's own"
    layout = f"{what}, on the traced mesh's topology)" if kept else "atlas"
    geom = export_mesh(source.mesh, source.atlas, source.export_transform, source.export.weld)
    return LevelRecord(
        level="lod0",
        fraction=1.0,
        uv_layout=layout,
        faces=len(source.mesh.faces),
        vertices_exported=len(geom.positions),
        texture_size=source.full_size,
        bake_seconds=float(source.bake_meta["timings_s"]["bake"]),
        file_bytes=dict(source.export_stats["file_bytes"]),
        files=", ".join(f"export/{f}" for f in source.export_stats["file_bytes"]) + " (the export stage's)",
        fidelity=fidelity,
        asset=Level("lod0", geom, "lod0/textures"),
        image=image,
    )


@dataclass(frozen=True)
class LevelPlan:
    """One decimated level to make: its ``tag`` (lod1, lod2, ...), its face ``fraction`` of the
    traced mesh and the face count that is (``target``)."""

    tag: str
    fraction: float
    target: int


def make_level(
    source: LodSource,
    grader: LevelGrader,
    plan: LevelPlan,
    settings: LodSettings,
    decimate: DecimateSettings,
    staging: Path,
    out_dir: Path,
) -> LevelRecord:
    """Decimate, bake, export and grade one level into ``staging / plan.tag``, with its own
    ``meta.json`` (``out_dir``: where the stage's outputs land, as the metadata names them)."""
    timer, tag = Timer(), plan.tag
    with timer("decimate"):
        level_settings = dataclasses.replace(decimate, enabled=True, target_faces=plan.target)
        dec = decimate_mesh(source.mesh, level_settings, f"{source.inputs['mesh']} ({tag})")
    low, hausdorff = dec.mesh, float(dec.stats["hausdorff_max"])
    search = settings.cage * hausdorff + 1e-6
    size = settings.level_texture_size(source.full_size, plan.fraction)
    with timer("bake"):
        res = bake_level(source.mesh, low, source.field, size, source.bake, search, source.device, source.occlusion)
    with timer("write"):
        geom, checked = _write_level(source, staging / tag, low, res)
    with timer("grade"):
        fidelity, image = grader.grade(low, res.texels.atlas.uv, res.textures, res.frames)
    found, offset = res.projection.found, np.abs(res.projection.offset[res.projection.found])
    record = LevelRecord(
        level=tag,
        uv_layout="atlas (a decimated level has other faces than the input)",
        fraction=plan.fraction,
        faces=len(low.faces),
        target_faces=plan.target,
        target_reached=bool(dec.stats.get("target_reached", True)),
        hausdorff_max=hausdorff,
        search_distance=search,
        texels_on_traced_surface=float(found.mean()),
        texels_on_faces_turned_away=float(res.projection.opposite.mean()),
        offset_p95=float(np.percentile(offset, 95)) if len(offset) else None,
        vertices_exported=len(geom.positions),
        texture_size=size,
        texel_coverage=float(res.texels.filled.mean()),
        decimate_seconds=timer.seconds["decimate"],
        bake_seconds=timer.seconds["bake"],
        file_bytes={f: (staging / tag / f).stat().st_size for f in export_files().values()},
        files=", ".join(f"lod/{tag}/{f}" for f in export_files().values()),
        validation=_validation_record(checked),
        fidelity=fidelity,
        asset=Level(tag, geom, f"{tag}/textures"),
        image=image,
    )
    _write_level_meta(source, record, timer.seconds, settings, staging, out_dir)
    log.info(
        "%s: %d faces (%.0f%%), %.1f dB against the full neural render (silhouette IoU %.3f); %s",
        tag,
        record.faces,
        100 * plan.fraction,
        fidelity["fidelity_psnr_db"],
        fidelity["silhouette_iou"],
        ", ".join(f"{f} {n} bytes" for f, n in record.file_bytes.items()),
    )
    return record


def _write_level(source: LodSource, folder: Path, low: TriMesh, res):
    """A level's textures, light, mesh and atlas (in the normalised frame, as the bake writes
    them: what a round trip or a later re-grade reads) and its exported files; returns the
    exported geometry and the validators' reports."""
    for key, rel in TEXTURE_FILES.items():
        save_png(folder / rel, res.textures[key])
    for fname in ("light.exr", "light.hdr"):
        copy_file(source.bake_dir / fname, folder / fname, remedy="Run the bake stage again.")
    save_ply(folder / "mesh.ply", low)
    with atomic_stream(folder / "atlas.npz") as fh:
        np.savez(fh, uv=res.texels.atlas.uv.astype(np.float32), **res.frames.arrays())
    geom = export_mesh(low, {"uv": res.texels.atlas.uv, **res.frames.arrays()}, source.export_transform, source.export.weld)
    return geom, write_asset_files(folder, geom, source.asset_info())


def _validation_record(reports: dict[str, dict]) -> dict:
    """What the metadata keeps of a level's validator reports, per file."""
    return {name: {k: r[k] for k in VALIDATION_KEYS if k in r} for name, r in reports.items()}


def write_combined(source: LodSource, staging: Path, records: list[LevelRecord], coverage: list[float]) -> dict:
    """All levels in one file of each format that holds levels (one USD with a variant set
    ``LOD``, one GLB with ``MSFT_lod``, switching at ``coverage``), validated; returns the
    validators' reports per file."""
    levels, info = [r.asset for r in records], source.asset_info()
    copy_file(source.bake_dir / "light.exr", staging / info.light, remedy="Run the bake stage again.")
    holding = [e for e in formats.exporters() if e.spec.levels_in_one_file]
    for exporter in holding:
        exporter.write_levels(staging, levels, info, coverage)
    return {name: r for exporter in holding for name, r in exporter.validate(staging, LEVELS_STEM).items()}


def _write_level_meta(
    source: LodSource, record: LevelRecord, timings: dict, settings: LodSettings, staging: Path, out_dir: Path
) -> None:
    """A decimated level's own ``meta.json``: its row, the settings, its files."""
    tag = record.level
    write_json_atomic(
        staging / tag / "meta.json",
        metadata(
            stage="lod",
            settings=source.export.to_dict(),
            inputs=source.inputs,
            outputs={f: out_dir / tag / f for f in (*export_files().values(), *LEVEL_FILES)},
            timings=timings,
            extra={"stats": record.row(), "lod_settings": settings.to_dict(), ORIGIN_KEY: source.origin},
        ),
    )


def _texture(path: Path) -> np.ndarray:
    """A texture the bake wrote, as RGB (a plain file: a received results folder is data)."""
    with open_read(path, IMAGE_LIMIT, remedy="Run the bake stage again.") as fh, Image.open(fh) as img:
        return np.asarray(img.convert("RGB"))
