"""The figures each stage records for the summary: one dataclass per stage, which the stage fills
where it writes its metadata and the summary reads back, whose :meth:`StageRecord.row` gives the
summary's columns. The summary (:func:`stages.results.summary.summary_rows`) is a loop over
:data:`MESH_RECORDS` and :data:`CELL_RECORDS`; nothing else reads a stage's metadata for it.

Each column is declared once, on the field it comes from (:func:`columns` of :func:`column`):
its name, what it means and its unit, where in the field its value lies, and how the summary's CSV
writes a list (:meth:`Column.text`; the rows, ``summary.json`` and the HTML pages keep lists as
lists). A record sits in the stage's ``meta.json`` under ``stats`` (``place = "stats"``) or at its
top level (``"top"``), or is the stage's ``metrics.json`` (``file``). Like the file layout
(:mod:`stages.config.layout`), this is the contract between the stages and the rules and reports
that read them; no torch, no numpy.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from typing import Any, ClassVar, Self

from .guidance_modes import guidance_mode
from .layout import EXPORT_FILES


@dataclass(frozen=True)
class Column:
    """One column of the summary, declared on the record's field it comes from (:func:`columns`)."""

    #: the column's name ("": the field's)
    name: str
    #: what it holds, for a reader of the summary and the report's pages
    description: str
    #: its unit ("" for none)
    unit: str = ""
    #: its short heading in the report's tables ("": the name)
    heading: str = ""
    #: where its value lies in the field: a path of keys into a mapping (``("material", "albedo_rmse")``);
    #: with ``each``, the list of that path's value in each entry of a list (entries without it left out)
    key: tuple[str, ...] = ()
    each: bool = False
    #: its value from the whole record instead (a label, a constant)
    derive: Callable[[Any], Any] | None = None
    #: how the summary's CSV writes a list: each entry by ``fmt`` (an entry that is itself a list,
    #: its items ``,``-separated), the entries ``sep``-separated
    fmt: str = "{}"
    sep: str = "/"
    #: the record's field that declares it (set by :meth:`StageRecord.columns`)
    field: str = ""

    def value(self, record: StageRecord) -> Any:
        """The column's value in ``record`` (None where the record does not have it)."""
        if self.derive is not None:
            return self.derive(record)
        value = getattr(record, self.field)
        if not self.each:
            return _dig(value, self.key)
        entries = [_dig(e, self.key) for e in value or () if _dig(e, self.key) is not None]
        return entries or None

    def text(self, value: Any) -> Any:
        """``value`` as the summary's CSV writes it: a list as one text (``24.13/20.00``), anything
        else as it is."""
        if not isinstance(value, list):
            return value

        def entry(e):
            return ",".join(self.fmt.format(x) for x in e) if isinstance(e, list) else self.fmt.format(e)

        return self.sep.join(entry(e) for e in value) or None

    def title(self) -> str:
        """Its heading with its unit (``bake (dB)``)."""
        return (self.heading or self.name) + (f" ({self.unit})" if self.unit else "")


def _dig(value: Any, key: tuple[str, ...]) -> Any:
    for k in key:
        value = value.get(k) if isinstance(value, dict) else None
    return value


def column(name: str = "", description: str = "", unit: str = "", **how) -> Column:
    """A summary column (:class:`Column`; ``how``: its ``heading``, ``key``, ``each``, ``derive``,
    ``fmt``, ``sep``); ``name`` "" names it after its field."""
    if not description:
        raise ValueError(f"column {name!r} needs its description")
    return Column(name, description, unit, **how)


def columns(*declared: Column, default: Any = dataclasses.MISSING, kw_only: bool = False) -> Any:
    """A record's field that gives the summary the ``declared`` columns, in order (a dataclass
    field with ``default``; ``kw_only``: a required field declared after ones with defaults)."""
    return dataclasses.field(default=default, metadata={"columns": declared}, **({"kw_only": True} if kw_only else {}))


@dataclass(frozen=True)
class StageRecord:
    """Base: what a stage records for the summary (subclasses are frozen dataclasses whose fields
    declare their columns)."""

    #: the stage's folder, the file the record is in, and where in it
    stage: ClassVar[str]
    file: ClassVar[str] = "meta.json"
    place: ClassVar[str] = "stats"
    #: figures the stage writes only where it has them (others are written, null when missing)
    OPTIONAL: ClassVar[tuple[str, ...]] = ()

    @classmethod
    def columns(cls) -> tuple[Column, ...]:
        """The summary's columns this record gives, in order (a stage that did not run gives them
        empty): its fields' :func:`columns`, in the fields' order."""
        return _record_columns(cls)

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
        """The summary's columns of this record (:meth:`columns`, in order); lists stay lists."""
        return {c.name: c.value(self) for c in self.columns()}

    @classmethod
    def empty_row(cls) -> dict[str, Any]:
        """The columns of a stage that did not run for the cell."""
        return dict.fromkeys(c.name for c in cls.columns())


@cache
def _record_columns(cls: type[StageRecord]) -> tuple[Column, ...]:
    return tuple(
        dataclasses.replace(c, field=f.name, name=c.name or f.name)
        for f in dataclasses.fields(cls)
        for c in f.metadata.get("columns", ())
    )


@dataclass(frozen=True)
class NormalizeRecord(StageRecord):
    """The mesh as read."""

    stage = "normalize"
    faces: int = columns(column("faces_before", "faces of the mesh as read"))


@dataclass(frozen=True)
class DecimateRecord(StageRecord):
    """The decimated mesh: its faces, the target and whether the collapse reached it (and why not)."""

    stage = "decimate"
    faces_after: int = columns(
        column("", "faces of the mesh the cell used (decimated, or as read)", heading="faces"),
        column("decimated", "whether the mesh was decimated", derive=lambda r: True),
    )
    target_faces: int | None = columns(column("decimation_target", "the decimation's target face count"), default=None)
    target_reached: bool | None = columns(
        column("decimation_target_reached", "whether the decimation reached its target"), default=None
    )
    target_shortfall_reason: str | None = columns(
        column("decimation_shortfall", "why the decimation stopped short of its target"), default=None
    )


@dataclass(frozen=True)
class RaycacheRecord(StageRecord):
    """The mesh's self-occlusion (the share of the hemisphere its surface sees blocked)."""

    stage, place = "raycache", "top"
    self_occlusion: dict | None = columns(
        column(
            "self_occlusion_median", "median over the surface of the share of its hemisphere the mesh blocks", key=("median",)
        ),
        column(
            "self_occlusion_p95", "95th percentile over the surface of the share of its hemisphere the mesh blocks", key=("p95",)
        ),
        default=None,
    )


def _guidance_label(record: OptimizeRecord) -> str:
    return guidance_mode(record.guidance).label


def _weights_label(record: OptimizeRecord) -> str:
    return record.weights_label()


def _suns_label(record) -> list[str] | None:
    """Each learned sun of an optimisation's light in words (None where it has none)."""
    suns = [sun for c in record.light_components or () if c.get("kind") == "sun" for sun in c.get("suns", ())]
    if not suns:
        return None
    return [
        f"elevation {s['elevation_deg']:.1f} deg, azimuth {math.degrees(s['azimuth_rad']):.1f} deg, "
        f"radius {s['radius_deg']:.2f} deg, irradiance {', '.join(f'{x:.3g}' for x in s['irradiance'])}"
        for s in suns
    ]


@dataclass(frozen=True)
class OptimizeRecord(StageRecord):
    """The optimisation: its prompt, guidance and weights, and its figures on the evaluation views
    (``final_similarity`` under CLIP, ``eval_psnr_db`` against SG targets)."""

    stage, place = "optimize", "top"
    OPTIONAL = ("final_similarity", "eval_psnr_db")
    prompt: str = columns(column("prompt_text", "the prompt's text", heading="prompt"))
    guidance: str = columns(column("", "the guidance mode (optimize.guidance)", derive=_guidance_label))
    weights: str = columns(
        column("", "the weights or image targets that guided it (test-only random: the tiny test CLIP)", derive=_weights_label)
    )
    test_only_weights: bool
    settings: dict = columns(column("iterations", "optimisation steps", key=("iterations",)))
    final_similarity: float | None = columns(
        column("", "CLIP similarity of the prompt with the evaluation views (CLIP guidance)"), default=None
    )
    eval_psnr_db: float | None = columns(
        column("", "PSNR against the SG targets on the evaluation views (object pixels)", "dB"), default=None
    )
    #: each component of the learned light, as the optimisation describes it (``meta.json``)
    light_components: list | None = columns(
        column(
            "learned_suns",
            "each learned sun (optimize.suns): its elevation and azimuth, angular radius and irradiance per channel",
            derive=_suns_label,
            sep=" | ",
        ),
        default=None,
    )

    def stats(self) -> dict[str, Any]:
        return {k: v for k, v in super().stats().items() if k != "settings"}  # (the metadata holds them)

    def weights_label(self) -> str:
        """The weights as the summary names them (the guidance mode's wording)."""
        return guidance_mode(self.guidance).weights_label(self.weights, self.test_only_weights, self.settings)


@dataclass(frozen=True)
class BakeRecord(StageRecord):
    """The bake: its texture size, its fidelity to the trained field and its UV layout."""

    stage = "bake"
    bake_psnr_db: float = columns(
        column("", "PSNR of the baked textures' render against the trained field's", "dB", heading="bake")
    )
    texture_size: int = columns(column("", "texture width = height", "px"))
    #: the UV layout the textures use (``kept``: the input's own; ``atlas``: a new one) and why (bake.uv)
    uv_layout: str | None = columns(
        column("", "the UV layout the textures use (kept: the input's own; atlas: a new one)", heading="UV layout"),
        default=None,
    )
    uv_why: str | None = columns(column("", "why the bake chose that layout"), default=None)


@dataclass(frozen=True)
class ExportRecord(StageRecord):
    """The exported files' validation: the USD validators that ran and the errors and warnings of
    the USD and glTF validators."""

    stage = "export"
    usd_validators: int | None = columns(column("", "USD validators that ran"))
    usd_validation_errors: int | None = columns(column("", "errors the USD validators found"))
    usd_validation_warnings: int | None = columns(column("", "warnings of the USD validators"))
    gltf_validation_errors: int | None = columns(column("", "errors the glTF validator found"))
    gltf_validation_warnings: int | None = columns(column("", "warnings of the glTF validator"))


@dataclass(frozen=True)
class MetricsRecord(StageRecord):
    """The metrics on the held-out metric views (``metrics.json``): the guidance CLIP's similarity,
    the independent evaluation CLIP's scores, and the figures against image targets."""

    stage, file, place = "metrics", "metrics.json", "top"
    OPTIONAL = ("guidance", "evaluation", "image_target")
    guidance: dict | None = columns(
        column("guidance_similarity", "the guidance CLIP's similarity of the prompt with the metric views", key=("similarity",)),
        default=None,
    )
    evaluation: dict | None = columns(
        column("eval_weights", "the independent evaluation CLIP's weights", key=("weights",)),
        column("eval_test_only", "whether the evaluation CLIP is the tiny test one", key=("test_only",)),
        column("clip_score", "CLIP score of the prompt on the metric views (100 x mean cosine)", key=("clip_score",)),
        column("r_precision", "share of metric views that rank their own prompt first", key=("r_precision",)),
        column("r_precision_candidates", "prompts ranked for R-precision", key=("candidates",)),
        default=None,
    )
    image_target: dict | None = columns(
        column("target_psnr_db", "PSNR against the image targets (held-out views, object pixels)", "dB", key=("psnr_db",)),
        column("target_ssim", "SSIM against the image targets (held-out views)", key=("ssim",)),
        column(
            "target_ceiling_psnr_db",
            "the training light's ceiling: the true material in our renderer with the run's transport under the "
            "environment's fit (fully covered hits of the held-out views)",
            "dB",
            key=("ceiling", "ceiling_psnr_db"),
        ),
        column(
            "target_recovered_hits_psnr_db",
            "the recovered field under its learned light on the ceiling's pixels (fully covered hits)",
            "dB",
            key=("ceiling", "recovered_psnr_db"),
        ),
        column("target_renderer", "who rendered the image targets (optimize.target_renderer)", key=("target_renderer",)),
        column("target_albedo_rmse", "RMSE of the recovered albedo against the truth", key=("material", "albedo_rmse")),
        column(
            "target_albedo_rmse_scaled",
            "RMSE of the recovered albedo after one scale of it",
            key=("material", "albedo_rmse_scaled"),
        ),
        column("target_roughness_mae", "mean error of the recovered roughness", key=("material", "roughness_mae")),
        column(
            "target_normal_angle_deg",
            "mean angle of the recovered shading normals to the truth",
            "degrees",
            key=("material", "normal_angle_deg_mean"),
        ),
        default=None,
    )


@dataclass(frozen=True)
class RelightRecord(StageRecord):
    """The relighting graded against Mitsuba's relit ground truth: one entry per environment of
    ``target.relight_environments``."""

    stage = "relight"
    ground_truth: list | None = columns(
        # the environments " | "-separated in the CSV (a path holds slashes), the figures "/"-separated
        column("relit_environments", "the environments of the relit truth", key=("environment",), each=True, sep=" | "),
        column(
            "relit_psnr_db",
            "PSNR of the relit renders per environment",
            "dB",
            heading="relit",
            key=("psnr_db",),
            each=True,
            fmt="{:.2f}",
        ),
        column(
            "relit_psnr_scaled_db",
            "PSNR of the relit renders after one factor per colour channel",
            "dB",
            key=("psnr_scaled_db",),
            each=True,
            fmt="{:.2f}",
        ),
        column(
            "relit_ceiling_psnr_db",
            "the true material's PSNR in our renderer (the ceiling)",
            "dB",
            key=("ceiling_psnr_db",),
            each=True,
            fmt="{:.2f}",
        ),
        # unequal factors mean the light's colour went into the base colour
        column("relit_scale", "the per-channel factors of the scaled figures (r, g, b)", key=("scale",), each=True, fmt="{:.2f}"),
        default=None,
    )


@dataclass(frozen=True)
class RoundtripRecord(StageRecord):
    """The Blender round trip: each format's PSNR against our render, the GLB's lobes alone, the
    import problems and the light transport of the Cycles renders."""

    stage = "roundtrip"
    OPTIONAL = ("glb_psnr_db", "usdz_psnr_db", "glb_diffuse_psnr_db", "glb_lobes_summed_psnr_db")
    glb_psnr_db: float | None = columns(
        column("roundtrip_glb_psnr_db", "PSNR of Cycles' render of the GLB against ours", "dB"), default=None
    )
    usdz_psnr_db: float | None = columns(
        column("roundtrip_usdz_psnr_db", "PSNR of Cycles' render of the USDZ against ours", "dB"), default=None
    )
    glb_diffuse_psnr_db: float | None = columns(
        column("roundtrip_glb_diffuse_psnr_db", "PSNR of Cycles' render of the GLB's diffuse lobe alone against ours", "dB"),
        default=None,
    )
    glb_lobes_summed_psnr_db: float | None = columns(
        column("roundtrip_glb_lobes_summed_psnr_db", "PSNR of the GLB's lobes rendered apart and summed against ours", "dB"),
        default=None,
    )
    problems: int = columns(column("roundtrip_problems", "problems Blender's import reported"), kw_only=True)
    transport: str = columns(column("roundtrip_transport", "the light transport of the Cycles renders"), kw_only=True)


@dataclass(frozen=True)
class LodRecord(StageRecord):
    """The levels of detail: one entry per level (lod0 = the full mesh)."""

    stage = "lod"
    levels: list = columns(
        column("lod_faces", "faces of each level", key=("faces",), each=True),
        column("lod_glb_bytes", "size of each level's GLB", "bytes", key=("file_bytes", EXPORT_FILES["glb"]), each=True),
        column(
            "lod_fidelity_psnr_db",
            "PSNR of each level's baked render against the full neural render",
            "dB",
            key=("fidelity_psnr_db",),
            each=True,
            fmt="{:.2f}",
        ),
    )


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


@cache
def _all_columns() -> dict[str, Column]:
    return {c.name: c for record in (*MESH_RECORDS, *CELL_RECORDS) for c in record.columns()}


def text_row(row: dict[str, Any]) -> dict[str, Any]:
    """A summary row as its CSV writes it: each record column's list as one text (:meth:`Column.text`)."""
    found = _all_columns()
    return {k: found[k].text(v) if k in found else v for k, v in row.items()}
