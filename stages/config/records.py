"""The figures each stage records for the summary: one dataclass per stage, which the stage fills
where it writes its metadata and the summary reads back, whose :meth:`StageRecord.row` gives the
summary's columns. The summary (:func:`stages.results.summary.summary_rows`) is a loop over
:data:`MESH_RECORDS` and :data:`CELL_RECORDS`; nothing else reads a stage's metadata for it.

A record sits in the stage's ``meta.json`` under ``stats`` (``place = "stats"``) or at its top level
(``"top"``), or is the stage's ``metrics.json`` (``file``). Like the file layout
(:mod:`stages.config.layout`), this is the contract between the stages and the rules and reports
that read them; no torch, no numpy.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, ClassVar, Self


@dataclass(frozen=True)
class StageRecord:
    """Base: what a stage records for the summary (subclasses are frozen dataclasses)."""

    #: the stage's folder, the file the record is in, and where in it
    stage: ClassVar[str]
    file: ClassVar[str] = "meta.json"
    place: ClassVar[str] = "stats"
    #: the summary's columns :meth:`row` gives, in order (a stage that did not run gives them empty)
    COLUMNS: ClassVar[tuple[str, ...]] = ()
    #: figures the stage writes only where it has them (others are written, null when missing)
    OPTIONAL: ClassVar[tuple[str, ...]] = ()

    def stats(self) -> dict[str, Any]:
        """The record as the stage writes it (merged into its ``stats``, or its metadata's top
        level); an :data:`OPTIONAL` figure the stage does not have is left out."""
        return {k: v for k, v in dataclasses.asdict(self).items() if v is not None or k not in self.OPTIONAL}

    @classmethod
    def from_meta(cls, meta: dict) -> Self:
        """The record read back from the stage's file (the fields the file lacks: None)."""
        source = (meta.get("stats") or {}) if cls.place == "stats" else meta
        return cls(**{f.name: source.get(f.name) for f in dataclasses.fields(cls)})

    def row(self) -> dict[str, Any]:
        """The summary's columns of this record (:data:`COLUMNS`, in order)."""
        return {k: getattr(self, k) for k in self.COLUMNS}

    @classmethod
    def empty_row(cls) -> dict[str, Any]:
        """The columns of a stage that did not run for the cell."""
        return dict.fromkeys(cls.COLUMNS)


@dataclass(frozen=True)
class NormalizeRecord(StageRecord):
    """The mesh as read."""

    stage = "normalize"
    COLUMNS = ("faces_before",)
    faces: int

    def row(self) -> dict[str, Any]:
        return {"faces_before": self.faces}


@dataclass(frozen=True)
class DecimateRecord(StageRecord):
    """The decimated mesh: its faces, the target and whether the collapse reached it (and why not)."""

    stage = "decimate"
    COLUMNS = ("faces_after", "decimated", "decimation_target", "decimation_target_reached", "decimation_shortfall")
    faces_after: int
    target_faces: int | None = None
    target_reached: bool | None = None
    target_shortfall_reason: str | None = None

    def row(self) -> dict[str, Any]:
        return {
            "faces_after": self.faces_after,
            "decimated": True,
            "decimation_target": self.target_faces,
            "decimation_target_reached": self.target_reached,
            "decimation_shortfall": self.target_shortfall_reason,
        }


@dataclass(frozen=True)
class RaycacheRecord(StageRecord):
    """The mesh's self-occlusion (the share of the hemisphere its surface sees blocked)."""

    stage, place = "raycache", "top"
    COLUMNS = ("self_occlusion_median", "self_occlusion_p95")
    self_occlusion: dict | None = None

    def row(self) -> dict[str, Any]:
        occ = self.self_occlusion or {}
        return {"self_occlusion_median": occ.get("median"), "self_occlusion_p95": occ.get("p95")}


@dataclass(frozen=True)
class OptimizeRecord(StageRecord):
    """The optimisation: its prompt, guidance and weights, and its figures on the evaluation views
    (``final_similarity`` under CLIP, ``eval_psnr_db`` against SG targets)."""

    stage, place = "optimize", "top"
    COLUMNS = ("prompt_text", "guidance", "weights", "iterations", "final_similarity", "eval_psnr_db")
    OPTIONAL = ("final_similarity", "eval_psnr_db")
    prompt: str
    guidance: str
    weights: str
    test_only_weights: bool
    settings: dict
    final_similarity: float | None = None
    eval_psnr_db: float | None = None

    def stats(self) -> dict[str, Any]:
        return {k: v for k, v in super().stats().items() if k != "settings"}  # (the metadata holds them)

    def weights_label(self) -> str:
        if self.test_only_weights:
            return "test-only random"
        if self.guidance == "image":
            return f"image-guided ({self.settings['target_material']} target)"
        return str(self.weights)

    def row(self) -> dict[str, Any]:
        return {
            "prompt_text": self.prompt,
            "guidance": "image-guided (procedural targets)" if self.guidance == "image" else "CLIP",
            "weights": self.weights_label(),
            "iterations": self.settings["iterations"],
            "final_similarity": self.final_similarity,
            "eval_psnr_db": self.eval_psnr_db,
        }


@dataclass(frozen=True)
class BakeRecord(StageRecord):
    """The bake: its texture size, its fidelity to the trained field and its UV layout."""

    stage = "bake"
    COLUMNS = ("bake_psnr_db", "texture_size", "uv_layout", "uv_why")
    texture_size: int
    bake_psnr_db: float
    #: the UV layout the textures use (``kept``: the input's own; ``atlas``: a new one) and why (bake.uv)
    uv_layout: str | None = None
    uv_why: str | None = None


@dataclass(frozen=True)
class ExportRecord(StageRecord):
    """The exported files' validation: the USD validators that ran and the errors and warnings of
    the USD and glTF validators."""

    stage = "export"
    COLUMNS = (
        "usd_validators",
        "usd_validation_errors",
        "usd_validation_warnings",
        "gltf_validation_errors",
        "gltf_validation_warnings",
    )
    usd_validators: list | None
    usd_validation_errors: int | None
    usd_validation_warnings: int | None
    gltf_validation_errors: int | None
    gltf_validation_warnings: int | None


@dataclass(frozen=True)
class MetricsRecord(StageRecord):
    """The metrics on the held-out metric views (``metrics.json``): the guidance CLIP's similarity,
    the independent evaluation CLIP's scores, and the figures against image targets."""

    stage, file, place = "metrics", "metrics.json", "top"
    COLUMNS = (
        "guidance_similarity",
        "eval_weights",
        "eval_test_only",
        "clip_score",
        "r_precision",
        "r_precision_candidates",
        "target_psnr_db",
        "target_ssim",
        "target_renderer",
        "target_albedo_rmse",
        "target_albedo_rmse_scaled",
        "target_roughness_mae",
        "target_normal_angle_deg",
    )
    OPTIONAL = ("guidance", "evaluation", "image_target")
    guidance: dict | None = None
    evaluation: dict | None = None
    image_target: dict | None = None

    def row(self) -> dict[str, Any]:
        ev, it, gd = self.evaluation or {}, self.image_target or {}, self.guidance or {}
        material = it.get("material") or {}
        return {
            "guidance_similarity": gd.get("similarity"),
            "eval_weights": ev.get("weights"),
            "eval_test_only": ev.get("test_only"),
            "clip_score": ev.get("clip_score"),
            "r_precision": ev.get("r_precision"),
            "r_precision_candidates": ev.get("candidates"),
            "target_psnr_db": it.get("psnr_db"),
            "target_ssim": it.get("ssim"),
            "target_renderer": it.get("target_renderer"),
            "target_albedo_rmse": material.get("albedo_rmse"),
            "target_albedo_rmse_scaled": material.get("albedo_rmse_scaled"),
            "target_roughness_mae": material.get("roughness_mae"),
            "target_normal_angle_deg": material.get("normal_angle_deg_mean"),
        }


def _joined(values, fmt: str = "{:.2f}") -> str | None:
    """Per-entry figures ``/``-separated (None where there are none)."""
    return "/".join(fmt.format(v) for v in values) or None


@dataclass(frozen=True)
class RelightRecord(StageRecord):
    """The relighting graded against Mitsuba's relit ground truth: one entry per environment of
    ``target.relight_environments``."""

    stage = "relight"
    COLUMNS = ("relit_environments", "relit_psnr_db", "relit_psnr_scaled_db", "relit_ceiling_psnr_db", "relit_scale")
    ground_truth: list | None = None

    def row(self) -> dict[str, Any]:
        gt = self.ground_truth or []
        return {
            # the environments " | "-separated (a path holds slashes), the figures "/"-separated
            "relit_environments": " | ".join(g["environment"] for g in gt) or None,
            "relit_psnr_db": _joined(g["psnr_db"] for g in gt),
            "relit_psnr_scaled_db": _joined(g["psnr_scaled_db"] for g in gt if "psnr_scaled_db" in g),
            "relit_ceiling_psnr_db": _joined(g["ceiling_psnr_db"] for g in gt if "ceiling_psnr_db" in g),
            # the per-channel factors of the scaled figures, "r,g,b" per environment: unequal
            # factors mean the light's colour went into the base colour
            "relit_scale": "/".join(",".join(f"{x:.2f}" for x in g["scale"]) for g in gt if "scale" in g) or None,
        }


@dataclass(frozen=True)
class RoundtripRecord(StageRecord):
    """The Blender round trip: each format's PSNR against our render, the GLB's lobes alone, the
    import problems and the light transport of the Cycles renders."""

    stage = "roundtrip"
    COLUMNS = (
        "roundtrip_glb_psnr_db",
        "roundtrip_usdz_psnr_db",
        "roundtrip_glb_diffuse_psnr_db",
        "roundtrip_glb_lobes_summed_psnr_db",
        "roundtrip_problems",
        "roundtrip_transport",
    )
    OPTIONAL = ("glb_psnr_db", "usdz_psnr_db", "glb_diffuse_psnr_db", "glb_lobes_summed_psnr_db")
    problems: int
    transport: str
    glb_psnr_db: float | None = None
    usdz_psnr_db: float | None = None
    glb_diffuse_psnr_db: float | None = None
    glb_lobes_summed_psnr_db: float | None = None

    def row(self) -> dict[str, Any]:
        return {column: getattr(self, column.removeprefix("roundtrip_")) for column in self.COLUMNS}


@dataclass(frozen=True)
class LodRecord(StageRecord):
    """The levels of detail: one row per level (lod0 = the full mesh)."""

    stage = "lod"
    COLUMNS = ("lod_faces", "lod_glb_bytes", "lod_fidelity_psnr_db")
    levels: list

    def row(self) -> dict[str, Any]:
        return {
            "lod_faces": _joined((r["faces"] for r in self.levels), "{}"),
            "lod_glb_bytes": _joined((r["file_bytes"]["model.glb"] for r in self.levels), "{}"),
            "lod_fidelity_psnr_db": _joined(r["fidelity_psnr_db"] for r in self.levels),
        }


#: the mesh-level stages' records, in the summary's order
MESH_RECORDS: tuple[type[StageRecord], ...] = (NormalizeRecord, DecimateRecord, RaycacheRecord)
#: the cell stages' records, in the summary's order
CELL_RECORDS: tuple[type[StageRecord], ...] = (
    OptimizeRecord,
    BakeRecord,
    ExportRecord,
    MetricsRecord,
    RelightRecord,
    RoundtripRecord,
    LodRecord,
)
