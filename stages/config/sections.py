"""The settings of every stage: one frozen dataclass per config section, the one home of each
setting's type, default, limits and description.

Each class is what its stage receives (as JSON on the command line) and what the workflow resolves
per mesh or per grid cell; unknown keys fail and every value is checked against its field's
limits (:class:`~stages.core.settings.Settings`). The config schema
(``workflow/schemas/config.schema.yaml``) and the configuration reference are generated from these
classes (:mod:`stages.config.schema`, :mod:`stages.config.reference`). Measured reasons for a
default live in the documentation, not here. Nothing here imports torch or numpy: the workflow
builds its DAG from this module alone.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import math
from dataclasses import dataclass, fields
from functools import cache
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal, get_args

from ..core.errors import StageInputError
from ..core.safefiles import read_json
from ..core.settings import Settings, Spec, setting
from .brdfs import BRDFS as BRDF_SPECS
from .brdfs import stray_settings
from .guidance_modes import GUIDANCE_DOC, GUIDANCE_MODES, GuidanceMode, GuidanceName, guidance_mode
from .layout import BLENDER_IMPORTS

#: the input up axes the normalize stage can turn into +y
UpAxis = Literal["+y", "-y", "+z", "-z", "+x", "-x"]
UP_AXES = get_args(UpAxis)
#: procedural target materials and lights of ``guidance: image`` (:mod:`stages.model.procedural`)
Material = Literal["wood", "metal", "chrome", "plaster"]
MATERIALS = get_args(Material)
TargetLight = Literal["studio", "sky"]
LIGHTS = get_args(TargetLight)
#: how the learned light's lobes start (:func:`stages.model.lights.sg.initial_sharpness`)
LightInit = Literal["broad", "tango", "spread"]
LIGHT_INITS = get_args(LightInit)
#: the optimisation's light: learned with the material, or the SG fit of a known environment
LightMode = Literal["learn", "fixed"]
LIGHT_MODES = get_args(LightMode)
#: the BRDF models, one row each in :mod:`stages.config.brdfs` (their objects: :mod:`stages.render.brdf`)
Brdf = Annotated[str, BRDF_SPECS]  # the table's names, in its order, when a value is checked
#: the specular models (:meth:`stages.render.brdf.Brdf.shade`; each BRDF's own: ``BrdfSpec.lobes``)
SpecularLobe = Literal["isotropic", "split_sum", "fitted"]
SPECULAR_LOBES = get_args(SpecularLobe)
#: off / auto / on switches (YAML's bare on/off, booleans, mean the same)
Switch = Literal["auto", "on", "off"]
VISIBILITIES = get_args(Switch)
#: shading normals (:mod:`stages.geometry.normals`)
ShadingNormals = Literal["flat", "smooth"]
SHADING_NORMALS = get_args(ShadingNormals)
NormalWeighting = Literal["angle", "area"]
NORMAL_WEIGHTINGS = get_args(NormalWeighting)
TargetRenderer = Literal["mitsuba", "sg"]
TARGET_RENDERERS = get_args(TargetRenderer)
#: CLIP image-tower paths (:mod:`stages.guidance.vit`)
ClipTower = Literal["batched", "open_clip"]
CLIP_TOWERS = get_args(ClipTower)
Encoding = Literal["nerf", "fourier", "hashgrid", "none"]
ENCODINGS = get_args(Encoding)
#: the UV layout a bake writes into (:mod:`stages.assets.layouts`)
UvLayout = Literal["auto", "keep", "second", "atlas"]
UV_LAYOUTS = get_args(UvLayout)
#: what each layout a bake wrote into is, in the user's words (a bake's ``uv.layout``)
UV_LAYOUT_WORDS = {"kept": "the input's own", "second": "a second UV set beside the input's own", "atlas": "a new atlas"}
DecimateMode = Literal["faces", "share", "budget"]
DECIMATE_MODES = get_args(DecimateMode)
#: Mitsuba variants the target stage may use ("auto": LLVM when a usable libLLVM is found)
MitsubaVariant = Literal["auto", "scalar_rgb", "llvm_ad_rgb"]
MITSUBA_VARIANTS = get_args(MitsubaVariant)
#: the exported files the Blender round trip may import, by suffix (the export formats' table,
#: :data:`stages.config.layout.EXPORT_FORMATS`), and the light transport of its Cycles renders
RoundtripFormat = Literal[BLENDER_IMPORTS]
ROUNDTRIP_FORMATS = get_args(RoundtripFormat)
Transport = Literal["direct_unshadowed", "full"]
ROUNDTRIP_TRANSPORTS = get_args(Transport)
#: the procedural environment maps ``builtin:<name>`` names (:mod:`stages.render.envmap`)
PROCEDURAL_ENVMAPS = ("sunset", "overcast", "night", "sun_sky", "studio")
#: the ray-cache settings a face budget reads (stages.geometry.decimation.face_budget): only they
#: go to the decimate job, so that other cache edits do not rerun it
FACE_BUDGET_FIELDS = (
    "resolution",
    "fov_deg",
    "radius",
    "eval_resolution",
    "eval_fov_deg",
    "eval_radius",
    "metrics_resolution",
    "metrics_fov_deg",
    "metrics_radius",
)
#: what the CLIP of each config section is for (how a message about its weights names it)
CLIP_ROLES = {
    "optimize": "guidance CLIP (the model the optimisation follows)",
    "metrics": "evaluation CLIP (the metrics' CLIP score and R-precision)",
}
#: the largest seed (an unsigned 32-bit integer)
MAX_SEED = 2**32 - 1
#: the limits shared by many settings
IMAGE_PX = {"ge": 8, "le": 8192}
FOV = {"gt": 0, "lt": 180}
DISTANCE = {"gt": 0, "le": 1000}
PRIOR_WEIGHT = {"ge": 0, "le": 1e6}
ENV_DOC = "builtin:sunset | overcast | night | sun_sky | studio, or an .hdr/.exr path"
#: what a file path in a config may hold: no braces (Snakemake reads {...} in a file name as a
#: wildcard and fills it in, while the stage is given the text as written), and none of the
#: characters that make a name look other than it is, in any of its components: control
#: characters (U+0085 among them), line and paragraph separators (U+2028, U+2029), bidirectional
#: overrides and isolates (U+202A-U+202E, U+2066-U+2069). ``(?!\n)``: Python's ``$`` (the schema
#: validator's) also matches before a trailing newline. A setting with this pattern is a path key.
PATH_PATTERN = "^[^{}\\x00-\\x1f\\x7f-\\x9f\\u2028\\u2029\\u202a-\\u202e\\u2066-\\u2069]*(?!\\n)$"
#: the longest path a config may give (Linux's PATH_MAX)
PATH_MAX = 4096
#: the tiny test CLIP's open_clip model name and its architecture file, which the settings read as a
#: file for its input size (stages.guidance.clip registers it with open_clip)
TINY_CLIP = "tango-tiny-test-clip"
TINY_CLIP_CONFIG = Path(__file__).resolve().parents[1] / "guidance" / "data" / f"{TINY_CLIP}.json"


def path_setting(default: Any, doc: str, **limits: Any) -> Any:
    """A setting that holds a file path (an environment's may be ``builtin:<name>`` instead): a text
    of 1 to :data:`PATH_MAX` characters matching :data:`PATH_PATTERN`, the mark of a path key
    (:func:`is_path`); for a list, each of its texts."""
    return setting(default, doc, min_length=1, max_length=PATH_MAX, pattern=PATH_PATTERN, **limits)


def is_path(spec: Spec) -> bool:
    """Whether a setting holds a file path (declared with :func:`path_setting`)."""
    return spec.pattern == PATH_PATTERN


@cache
def clip_input_size(model: str, tiny_test: bool = False) -> int | None:
    """The width (= height) of the images the CLIP ``model`` takes (the tiny test CLIP's when
    ``tiny_test``), from its open_clip architecture file, read as JSON without importing open_clip or
    torch; None when there is no such file here (a model open_clip would fetch from the model hub,
    or open_clip not installed): then the optimisation says so when it loads the model."""
    if tiny_test or model == TINY_CLIP:
        path = TINY_CLIP_CONFIG
    else:
        found = importlib.util.find_spec("open_clip")
        if found is None or found.origin is None:
            return None
        path = Path(found.origin).parent / "model_configs" / f"{model}.json"
    try:
        size = read_json(path)["vision_cfg"]["image_size"]
    except (OSError, StageInputError, KeyError, TypeError):
        return None
    size = size[0] if isinstance(size, list) else size
    return size if isinstance(size, int) else None


def environment_problems(key: str, env: str) -> list[str]:
    """What is wrong with ``env`` as the environment map of setting ``key``: ``builtin:<name>`` of a
    procedural map, or an .hdr/.exr path."""
    if env.startswith("builtin:") and env.split(":", 1)[1] not in PROCEDURAL_ENVMAPS:
        return [f"{key}: no procedural environment {env!r}; use one of {PROCEDURAL_ENVMAPS}"]
    if not env.startswith("builtin:") and not env.lower().endswith((".hdr", ".exr")):
        return [f"{key}: {env!r} is neither builtin:<name> nor an .hdr/.exr file"]
    return []


@dataclass(frozen=True)
class ClipSpec:
    """Which CLIP to load: an open_clip model name and a pretrained tag, or a local checkpoint
    (which takes precedence), or the tiny random test model; ``section``: the config section
    that chose it (:data:`CLIP_ROLES`), so that a message names the keys to change."""

    model: str = "ViT-B-32"
    pretrained: str = "openai"
    checkpoint: str | None = None
    tiny_test: bool = False
    section: str = "optimize"


class ClipChoice:
    """For settings that name a CLIP (``clip_model``, ``clip_pretrained``, ``clip_checkpoint``,
    ``clip_tiny_test``): the one way to turn them into a :class:`ClipSpec`."""

    def clip_spec(self) -> ClipSpec:
        return ClipSpec(self.clip_model, self.clip_pretrained, self.clip_checkpoint, self.clip_tiny_test, self.section)


@dataclass(frozen=True, kw_only=True)
class NormalizeSettings(Settings):
    """The mesh as read: its up axis and the most faces accepted (per mesh)."""

    section = "normalize"
    up_axis: Literal["auto", UpAxis] = setting(
        "+y",
        "the input's up axis, rotated to +y (the cameras' up); auto: the file format's convention (glTF: +y) "
        "or a guess from the object's resting base, recorded in the metadata",
    )
    max_faces: int = setting(
        2_000_000,
        "the most faces a mesh may have (more: refused as soon as the mesh is read, naming decimation as the remedy); "
        "not part of the mesh-level work's folder key",
        ge=4,
        le=20_000_000,
        keyed=False,
    )


@dataclass(frozen=True, kw_only=True)
class DecimateSettings(Settings):
    """Edge collapse to fewer faces, between normalize and raycache (per mesh; off by default)."""

    section = "decimate"
    enabled: bool = setting(False, "insert the decimate stage between normalize and raycache")
    target_faces: int = setting(5000, "mode faces: the face count to reach (TANGO's robustness study: 5000)", ge=4, le=10_000_000)
    quality_threshold: float = setting(0.3, "MeshLab's quality threshold for the collapse (higher avoids slivers)", ge=0, le=1)
    preserve_boundary: bool = setting(True, "keep boundary edges in place")
    preserve_normal: bool = setting(True, "forbid collapses that flip a face normal")
    hausdorff_samples: int = setting(100_000, "surface samples per direction of the Hausdorff distance", ge=1000, le=100_000_000)
    weld: bool = setting(True, "weld coincident vertices (UV/normal seams of exported meshes) before the collapse")
    weld_tolerance: float = setting(
        1e-6,
        "vertices closer than this fraction of the bounding-box diagonal are welded (0: exact duplicates only)",
        ge=0,
        lt=0.01,
    )
    relax_boundary: bool = setting(
        True,
        "if the collapse stops above the target with boundaries preserved, collapse again with boundary vertices "
        "free to move along the boundary (topology kept); recorded in the stats",
    )
    mode: DecimateMode = setting(
        "faces",
        "faces: decimate to target_faces (the robustness study); share: to target_share of the mesh's own faces; "
        "budget: to the face budget of the mesh's ray cache (faces whose mean area covers pixels_per_face pixels at "
        "the cache's camera distance; a mesh within its budget passes unchanged)",
    )
    target_share: float = setting(0.1, "mode share: the share of the mesh's faces to keep (0.1: a tenth)", gt=0, lt=1)
    pixels_per_face: float = setting(
        1.0,
        "mode budget: how many pixels a face of the budgeted size covers where the surface comes nearest to the "
        "cameras of the cache's finest view set (higher: fewer faces)",
        ge=0.01,
        le=1e4,
    )


@dataclass(frozen=True, kw_only=True)
class RaycacheSettings(Settings):
    """The views traced once per mesh: training pool, evaluation and metric views, shadows (per mesh)."""

    section = "raycache"
    views: int = setting(64, "size of the training view pool (view 0 is the anchor)", ge=1, le=4096)
    resolution: int = setting(512, "image width = height of the training views (TANGO: 512)", **IMAGE_PX)
    fov_deg: float = setting(60.0, "full field of view (degrees) of the training views (TANGO: 60)", **FOV)
    radius: float = setting(
        2.0, "camera distance from the origin; the unit sphere fills the view at 1 / sin(fov / 2)", **DISTANCE
    )
    anchor_azimuth: float = setting(
        1.96, "the anchor (front) view's azimuth, radians (one turn either way)", ge=-6.2832, le=6.2832
    )
    anchor_elevation: float = setting(0.63, "the anchor view's elevation, radians, between the poles", gt=-1.5708, lt=1.5708)
    anchor_deg: tuple[float, float] | None = setting(
        None,
        "the anchor (front) view as [azimuth, elevation] in degrees (azimuth from +x towards +z about +y); set per "
        "mesh so the front view shows the object's front; replaces anchor_azimuth/anchor_elevation",
        ge=-360,
        le=360,
    )
    std: float = setting(8.0, "spread divisor: elevation std pi/std, azimuth std 2pi/std (TANGO: 8)", gt=0, le=1e6)
    seed: int = setting(0, "seed of the view sampler", ge=0, le=MAX_SEED)
    eval_azimuths: int = setting(8, "azimuths of the evaluation views at each elevation", ge=1, le=360)
    eval_elevations_deg: tuple[float, ...] = setting(
        (-30.0, 0.0, 30.0),
        "elevations (degrees) of the evaluation views, eval_azimuths azimuths at each",
        ge=-89,
        le=89,
        min_items=1,
        max_items=32,
    )
    eval_radius: float = setting(2.0, "camera distance of the evaluation views", **DISTANCE)
    eval_fov_deg: float = setting(60.0, "full field of view (degrees) of the evaluation views", **FOV)
    eval_resolution: int = setting(512, "image width = height of the evaluation views", **IMAGE_PX)
    metrics_azimuths: int = setting(8, "azimuths of the metric views at each elevation (the X-Mesh protocol: 8)", ge=1, le=360)
    metrics_elevations_deg: tuple[float, ...] = setting(
        (-30.0, 0.0, 30.0),
        "elevations (degrees) of the metric views, metrics_azimuths azimuths at each",
        ge=-89,
        le=89,
        min_items=1,
        max_items=32,
    )
    metrics_radius: float = setting(2.5, "camera distance of the metric views (X-Mesh: 2.5)", **DISTANCE)
    metrics_fov_deg: float = setting(45.0, "full field of view (degrees) of the metric views (X-Mesh: 45)", **FOV)
    metrics_resolution: int = setting(224, "image width = height of the metric views (X-Mesh: 224)", **IMAGE_PX)
    backend: Literal["embree", "trimesh"] = setting(
        "embree", "ray tracer: embree (embreex) or trimesh (pure Python reference; tiny inputs only)"
    )
    visibility: Switch = setting(
        "auto",
        "shadows: on traces, for every cached hit, the visibility of visibility_directions directions that the "
        "field's shading casts shadows from; auto does so when the 95th percentile of the mesh's self-occlusion is "
        "at least visibility_auto_p95; off (TANGO) none",
    )
    visibility_directions: int = setting(
        512, "directions whose visibility is stored per hit (bits; a multiple of 8)", ge=8, le=4096, multiple_of=8
    )
    visibility_auto_p95: float = setting(
        0.05,
        "visibility auto: the 95th percentile of the blocked share of the hemisphere over the mesh's surface from "
        "which shadows are cast (a convex mesh has 0)",
        ge=0,
        le=1,
    )

    def relations(self) -> list[str]:
        if self.anchor_deg is not None and not -90.0 < self.anchor_deg[1] < 90.0:
            return [f"raycache.anchor_deg must be [azimuth, elevation] with elevation in (-90, 90), got {list(self.anchor_deg)}"]
        return []

    def anchor(self) -> tuple[float, float, str]:
        """The anchor (front) view ``(azimuth, elevation)`` in radians and what set it."""
        if self.anchor_deg is not None:
            return math.radians(self.anchor_deg[0]), math.radians(self.anchor_deg[1]), "raycache.anchor_deg"
        default = (type(self).anchor_azimuth, type(self).anchor_elevation)
        if (self.anchor_azimuth, self.anchor_elevation) == default:
            return self.anchor_azimuth, self.anchor_elevation, "default (TANGO's demo scripts: azimuth 1.96, elevation 0.63 rad)"
        return self.anchor_azimuth, self.anchor_elevation, "raycache.anchor_azimuth/anchor_elevation (radians)"


@dataclass(frozen=True, kw_only=True)
class TargetSettings(Settings):
    """Ground-truth image targets path-traced by Mitsuba 3 from the ray cache's own cameras, for
    ``guidance: image`` with ``target_renderer: mitsuba``: the cell's ``optimize.target_material``
    as a principled BSDF with textures and a normal map under an environment map (per mesh)."""

    section = "target"
    environment: str = path_setting("builtin:sun_sky", f"the environment the targets are lit by: {ENV_DOC}")
    environment_height: int = setting(
        512, "rows of a procedural environment (files keep their size); columns = 2 x rows", ge=16, le=8192
    )
    spp: int = setting(
        32, "samples per pixel of the training targets (even: two halves measure the noise)", ge=2, le=65536, multiple_of=2
    )
    metric_spp: int = setting(256, "samples per pixel of the held-out metric targets (even)", ge=2, le=65536, multiple_of=2)
    max_depth: int = setting(8, "longest light path (2: direct light only, -1: unlimited)", ge=-1, le=1024)
    texture_size: int = setting(1024, "texture size of the ground-truth material and normal map", ge=16, le=8192)
    bump_slope: float = setting(0.3, "steepest slope of the normal map's bumps (0: none)", ge=0, le=2)
    shading_normals: ShadingNormals = setting(
        "smooth", "the truth's normals on the full-resolution mesh: smooth (creases above crease_angle_deg kept) or flat"
    )
    crease_angle_deg: float = setting(
        60.0,
        "smooth truth normals: an edge whose faces' normals differ by more than this angle (degrees) stays sharp",
        ge=0,
        le=180,
    )
    variant: MitsubaVariant = setting("auto", "Mitsuba variant (auto: llvm_ad_rgb when a usable libLLVM is found)")
    seed: int = setting(
        0, "seed of the path tracer's samples (each view's two halves use seeds derived from it)", ge=0, le=MAX_SEED
    )
    relight_environments: tuple[str, ...] = path_setting(
        ("builtin:sunset",),
        "environments the held-out metric views are also rendered under (builtin:<name> or an .hdr/.exr path): "
        "Mitsuba's ground truth that the relight stage grades the recovered field's relighting against; empty: not graded",
        max_items=16,
    )

    def relations(self) -> list[str]:
        problems = environment_problems("target.environment", self.environment)
        if self.max_depth in (0, 1):
            problems.append(f"target.max_depth must be >= 2 (or -1: unlimited), got {self.max_depth}")
        for env in self.relight_environments:
            problems += environment_problems("target.relight_environments", env)
        if len(set(self.relight_environments)) != len(self.relight_environments):
            problems.append(f"target.relight_environments lists an environment twice: {list(self.relight_environments)}")
        return problems


#: the mark of a field setting that changes the compiled renderer's graph (its BRDF, lobe model,
#: inputs needing gradients...): the model layer's kind of a compiled renderer, by which a
#: compilation made before on a machine is found, is read from the settings so marked
#: (:func:`stages.model.compiled.renderer_kind`)
COMPILED_RENDERER = "compiled renderer"


@dataclass(frozen=True, kw_only=True)
class FieldSettings(Settings):
    """The settings the stylisation field (:class:`~stages.model.field.StyleField`) is built from:
    its networks, encodings, BRDF, shading and light. The ``optimize`` section holds them
    (:class:`OptimizeSettings` extends this class), so each is written once."""

    section = "optimize"
    seed: int = setting(
        0, "seed of the networks' initialisation and of each step's draws (views, crops, backgrounds)", ge=0, le=MAX_SEED
    )
    symmetry: bool = setting(False, "TANGO's symmetry prior: the networks see (x, y, |z|)")
    width: int = setting(256, "hidden width of the SVBRDF and normal networks (TANGO: 256)", ge=1, le=4096)
    material_encoding: Encoding = setting(
        "nerf",
        "positional encoding of the SVBRDF network: nerf (frequencies), fourier (Gaussian random features), "
        "hashgrid (multiresolution hash grid) or none",
    )
    material_frequencies: int = setting(
        12, "nerf encoding of the SVBRDF network: frequencies 2^k pi for k below this", ge=0, le=24
    )
    material_fourier_count: int = setting(128, "fourier encoding of the SVBRDF network: number of random features", ge=1, le=4096)
    material_fourier_sigma: float = setting(
        0.5, "fourier encoding of the SVBRDF network: standard deviation of the random frequencies", gt=0, le=1000
    )
    specular: bool = setting(True, "learn specular colour and roughness (false: diffuse only, the paper's ablation)")
    init_specular: float | None = setting(
        None, "brdf tango: start the specular colour near this value everywhere (null: the networks' random start)", ge=0, le=1
    )
    init_roughness: float | None = setting(
        None, "start the roughness near this value everywhere (null: the networks' random start)", ge=0, le=1
    )
    init_metallic: float | None = setting(
        None,
        "brdf gltf: start the metallic near this value everywhere (null: the networks' "
        "random start, about 0.5; a dielectric start: 0.02)",
        ge=0,
        le=1,
    )
    min_roughness: float = setting(0.01, "lower end of the roughness range [min_roughness, 1]", gt=0, lt=1)
    normal_network: bool = setting(
        True,
        "learn the normal-offset network (false: shade with the mesh's normals, the paper's ablation)",
        marks=(COMPILED_RENDERER,),
    )
    normal_encoding: Encoding = setting("nerf", "positional encoding of the normal network (as material_encoding)")
    normal_frequencies: int = setting(10, "nerf encoding of the normal network: frequencies 2^k pi for k below this", ge=0, le=24)
    normal_fourier_count: int = setting(128, "fourier encoding of the normal network: number of random features", ge=1, le=4096)
    normal_fourier_sigma: float = setting(
        0.5, "fourier encoding of the normal network: standard deviation of the random frequencies", gt=0, le=1000
    )
    normal_max_delta: float = setting(
        0.3,
        "bound of the normal offset in the tangent frame: the tilt is at most "
        "atan(sqrt(2) normal_max_delta); 0 switches the offsets off",
        ge=0,
        le=10,
    )
    hashgrid_levels: int = setting(
        16, "hash grid (an encoding hashgrid, Müller et al. 2022; one table per network that uses it): levels", ge=1, le=32
    )
    hashgrid_features: int = setting(2, "hash grid: features per level", ge=1, le=8)
    hashgrid_log2_size: int = setting(17, "hash grid: log2 of the table entries per level", ge=10, le=24)
    hashgrid_min_resolution: int = setting(16, "hash grid: coarsest grid resolution over [-1, 1]^3", ge=2, le=65536)
    hashgrid_max_resolution: int = setting(1024, "hash grid: finest grid resolution over [-1, 1]^3", ge=2, le=65536)
    hashgrid_step_scale: float = setting(
        20.0, "hash grid: the table's optimiser step as a multiple of the networks'", gt=0, le=10000
    )
    light_lobes: int = setting(32, "SG lobes of the learned environment light (TANGO: 32 or 64)", ge=1, le=1024)
    light_rgb: bool = setting(True, "an RGB amplitude per lobe (false: monochrome light)", marks=(COMPILED_RENDERER,))
    light_energy: float = setting(
        6.25, "the light's total energy at the start, the sum of its lobes' sphere integrals (TANGO: 6.25)", gt=0, le=1e6
    )
    light_init: LightInit = setting(
        "tango",
        "how the lobes start: broad (every lobe at light_init_sharpness), tango (TANGO's draw 20 + |N(0,1)| 100) or "
        "spread (log-uniform from light_init_sharpness to light_init_max_sharpness, interleaved over the sphere)",
    )
    light_init_sharpness: float | None = setting(
        None,
        "the broad lobes' sharpness at the start (null: neighbours on the Fibonacci sphere overlap at half maximum)",
        ge=1e-4,
        le=1e5,
    )
    light_init_max_sharpness: float = setting(1000.0, "the sharpest starting lobe of light_init spread", ge=1e-4, le=1e5)
    suns: int | Literal["auto"] = setting(
        0,
        "sharp lights beside the SG lobes (discs of the sky: a direction, an RGB irradiance and an angular radius, "
        "shaded by the BRDF at directions inside the disc, each with its own shadow ray): a count, or auto: as many "
        "as the known environment (light_map, or the image targets' environment) has regions holding suns_share of "
        "its energy within a radius the cached visibility cannot resolve (found one after another, at most 4); "
        "none where no environment is known",
        ge=0,
        le=8,
        marks=(COMPILED_RENDERER,),
    )
    suns_share: float = setting(
        0.2,
        "suns auto: the share of the environment's energy a compact region must hold to be a sun (builtin:sun_sky's "
        "sun holds 63%; the brightest regions of sunset and studio, a glow and a strip light, 8% and 11%)",
        gt=0,
        le=1,
    )
    sun_samples: int = setting(
        8,
        "directions of each sun's disc the BRDF is evaluated at (each with its shadow ray); a mirror sees the disc "
        "resolved to that many cells",
        ge=1,
        le=256,
        marks=(COMPILED_RENDERER,),
    )
    bounces: int | Literal["auto"] = setting(
        0,
        "one bounce of the mesh's own light (each face side's diffuse radiance under the light, refreshed every "
        "bounce_every steps, reflected by the diffuse term through bounce_samples first hits per point; needs shadows "
        "and a ray cache with visibility): 0, 1, or auto: 1 where the median over the training views' hits of the "
        "share of the hemisphere the mesh blocks reaches bounce_auto_median",
        ge=0,
        le=1,
        marks=(COMPILED_RENDERER,),
    )
    bounce_samples: int = setting(
        16, "bounces: first hits traced per shaded point (once: cosine-distributed directions of its own)", ge=1, le=1024
    )
    bounce_every: int = setting(
        25, "bounces: steps between refreshes of the table of what each face side sends (the material learns)", ge=1, le=100000
    )
    bounce_auto_median: float = setting(
        0.05,
        "bounces auto: the median blocked share of the hemisphere over the training views' hits from which a bounce "
        "is modelled (the knot: 0.135; the vase, open but mostly seen from outside: 0; the candle: 0.016)",
        ge=0,
        le=1,
    )
    brdf: Brdf = setting(
        "gltf",
        "the BRDF model: tango (TANGO's diffuse albedo + specular colour, a sum of a diffuse and a microfacet term) "
        "or gltf (glTF 2.0's metallic-roughness BRDF: base colour, metallic, roughness; needs specular_lobe fitted "
        "or split_sum); bake and export write what was trained; tango for TANGO's model "
        "and a diffuse-only field (specular: false)",
        marks=(COMPILED_RENDERER,),
    )
    specular_lobe: SpecularLobe = setting(
        "fitted",
        "specular model: isotropic (TANGO's closed form), split_sum (exact energy, tabulated directional albedo) or "
        "fitted (exact energy, a lobe fitted to the BRDF's moments, corrected by the BRDF at each light lobe)",
        marks=(COMPILED_RENDERER,),
    )
    shading_normals: ShadingNormals = setting(
        "smooth",
        "normals the field shades with: flat (TANGO's face normals) or smooth (vertex normals interpolated across "
        "faces, creases above crease_angle_deg kept); carried through baking, export and relighting",
    )
    shadows: bool = setting(
        True,
        "cast shadows where the ray cache holds visibility (raycache.visibility): each light lobe scaled by its "
        "visible share; false: TANGO's unshadowed shading (an ablation switch)",
        marks=(COMPILED_RENDERER,),
    )
    crease_angle_deg: float = setting(
        60.0, "smooth normals: an edge whose faces' normals differ by more than this angle (degrees) stays sharp", ge=0, le=180
    )
    normal_weighting: NormalWeighting = setting(
        "angle", "smooth normals: corner weights of a vertex normal (angle: corner angle, Blender's; area: face area)"
    )

    def relations(self) -> list[str]:
        p = []
        grid = self.hashgrid_levels * self.hashgrid_features * 2**self.hashgrid_log2_size
        if grid > 2**26:
            p.append(
                "optimize: a hash grid of hashgrid_levels x hashgrid_features x 2^hashgrid_log2_size must hold at most "
                f"2^26 (67M) parameters per network, got {grid}"
            )
        if self.hashgrid_min_resolution > self.hashgrid_max_resolution:
            p.append("optimize.hashgrid_min_resolution must not exceed hashgrid_max_resolution")
        return p + self.brdf_relations()

    def brdf_relations(self) -> list[str]:
        """The problems of the settings against the BRDF's row (:mod:`stages.config.brdfs`): a
        specular model it does not have, no specular heads where it needs them, and a setting that
        only another BRDF reads (of this class's fields, and of a subclass's)."""
        spec, lobe = BRDF_SPECS[self.brdf], self.specular_lobe
        defaults = {f.name: f.default for f in fields(self)}
        named = f"brdf {self.brdf}" + (" (the default)" if self.brdf == defaults["brdf"] else "")
        p = []
        if lobe not in spec.lobes:
            others = [s.name for s in BRDF_SPECS.values() if lobe in s.lobes]
            p.append(
                f"optimize: {named} has no {lobe} specular model; use specular_lobe {' or '.join(spec.lobes)}, "
                f"or set brdf: {' or '.join(others)}"
            )
        elif not self.specular and not spec.diffuse_only:
            heads = " and ".join(spec.parameters[1:])
            others = [s.name for s in BRDF_SPECS.values() if s.diffuse_only]
            p.append(
                f"optimize: {named} needs its {heads} heads: set specular: true, or brdf: {' or '.join(others)} "
                "for a diffuse-only field"
            )
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        return p + stray_settings(self.brdf, values, defaults, named)


@dataclass(frozen=True, kw_only=True)
class OptimizeSettings(ClipChoice, FieldSettings):
    """The optimisation of a cell's material, normals and light: schedule, images, priors, guidance
    and precision, and the field's own settings (presets and variants override). Guidance ``clip``
    follows open_clip's clip_model with clip_pretrained (a tag) or clip_checkpoint (a local file);
    clip_tiny_test uses a tiny random model for tests only. Guidance ``image`` fits image targets of
    a procedural target_material (verification without CLIP): Mitsuba's path-traced ground truth
    (target_renderer mitsuba, the target stage) or our own SG renders under target_light
    (target_renderer sg). Defaults follow TANGO's paper and demo scripts where they state a value."""

    section = "optimize"
    iterations: int = setting(1500, "optimisation steps (TANGO: 1500)", ge=1, le=1_000_000)
    lr: float = setting(5e-4, "AdamW learning rate (TANGO: 5e-4)", gt=0, le=1)
    weight_decay: float = setting(0.0, "AdamW weight decay", ge=0, le=1)
    milestones: tuple[int, ...] = setting(
        (500, 1000), "iterations at which the learning rate is multiplied by gamma (step decay)", ge=0, le=1_000_000, max_items=64
    )
    gamma: float = setting(0.7, "learning-rate factor at each milestone (TANGO: 0.7)", gt=0, le=1)
    views_per_step: int = setting(
        1, "views of the cached pool rendered per step, each as one global image and its crops", ge=1, le=64
    )
    image_size: int | None = setting(
        None,
        "width = height in pixels of the images CLIP sees; it must be the size the guidance CLIP takes (ViT-B-32: 224); "
        "null: that size (the tiny test CLIP's 64), or 224 where no CLIP guides",
        ge=32,
        le=1024,
    )
    supersample: int = setting(1, "samples per pixel along each axis (s x s cached samples averaged per pixel)", ge=1, le=8)
    crops: int = setting(4, "local crops per view and step (TANGO's 2D augmentation; 0: the global image only)", ge=0, le=64)
    crop_scale: tuple[float, float] = setting((0.01, 0.2), "range of a crop's area as a fraction of the image", gt=0, le=1)
    crop_coverage: float = setting(0.3, "smallest share of a crop the object must cover", ge=0, le=1)
    crop_max_tries: int = setting(20, "placements tried per crop before the best one is taken", ge=1, le=10000)
    background: Literal["black", "white", "noise"] = setting(
        "black", "background of the training images: black, white or fresh noise"
    )
    light_lr: float | None = setting(
        0.02,
        "the light's own learning rate (its sharpness and energy are logarithms, so a step moves them by a factor); "
        "null: lr. No weight decay applies to the light",
        gt=0,
        le=1,
    )
    light_prune_after: int | None = setting(
        None,
        "lighting as the scene requires: after this many iterations, drop the lobes whose energy is below "
        "light_prune_share of the light's total in every channel, for the rest of the run (and in every file after "
        "it); null keeps every lobe (TANGO)",
        ge=1,
        le=1_000_000,
    )
    light_prune_share: float = setting(0.01, "the energy share below which light_prune_after drops a lobe", gt=0, lt=1)
    light: LightMode = setting(
        "learn",
        "learn (TANGO: the light is learned with the material) or fixed: the light is the SG fit of light_map "
        "(light_lobes lobes) and never moves, so no base colour can trade against the light's brightness or colour "
        "(the known-light mode: name the HDR the asset is to be lit by)",
    )
    light_map: str | None = path_setting(None, f"the environment of light: fixed: {ENV_DOC}")
    metallic_binary: float = setting(
        0.0,
        "weight of the prior that takes glTF's metallic to 0 or 1 (a surface is a metal or a dielectric; the glTF "
        "specification keeps values between for transitions): the mean of m (1 - m) over each step's shaded points; "
        "0 switches it off",
        **PRIOR_WEIGHT,
    )
    light_neutral: float = setting(
        0.0,
        "weight of the prior that keeps a learned light's colour neutral (nvdiffrec regularises its light towards "
        "white): each lobe's spread of log energy over the channels, weighted by its share of the light's energy; "
        "0 switches it off",
        **PRIOR_WEIGHT,
    )
    material_smooth: float = setting(
        0.0,
        "weight of the prior that keeps the material smooth over the surface (nvdiffrec's): the mean absolute change "
        "of the base colour, and of metallic and roughness, between each step's hit points and the same points moved "
        "by a random offset of material_smooth_radius; 0 switches it off",
        **PRIOR_WEIGHT,
    )
    material_smooth_radius: float = setting(
        0.01, "the standard deviation per axis of that offset, in the unit sphere the mesh is scaled to", gt=0, le=1
    )
    normal_tilt: float = setting(
        0.01,
        "weight of the prior that keeps the predicted normals near the mesh's: the mean of 1 - cos of their angle over "
        "each step's hits; 0 switches it off (nothing to act on without normal_network)",
        **PRIOR_WEIGHT,
    )
    guidance: GuidanceName = setting("clip", GUIDANCE_DOC)
    clip_model: str = setting(
        "ViT-B-32",
        "open_clip architecture of the guidance CLIP (ViT-B-32-quickgelu for the OpenAI weights from a local file)",
        min_length=1,
    )
    clip_pretrained: str = setting("openai", "open_clip weights tag of the guidance CLIP", min_length=1)
    clip_checkpoint: str | None = path_setting(
        None, "a local open_clip checkpoint file for the guidance CLIP; takes precedence over clip_pretrained"
    )
    clip_tiny_test: bool = setting(False, "a tiny randomly initialised CLIP, for tests only: every output is marked TEST ONLY")
    bf16: Switch = setting(
        "auto",
        "the guidance CLIP's image tower under bfloat16 autocast: auto where the device has native bfloat16 (a GPU "
        "from Ampere on; a CPU with AVX-512 BF16 or AMX for oneDNN) and float32 elsewhere; on asks for it everywhere "
        "(float32 with a warning where it is not native); off keeps float32. The metadata's clip_precision, the plan "
        "and the doctor say what runs",
    )
    clip_tower: ClipTower = setting(
        "batched",
        "the CLIP image tower's path: batched (attention and patch embedding as contiguous matrix products, frozen "
        "weights cast to bfloat16 once under bf16: the same function as open_clip's within float rounding, faster on "
        "a CPU) or open_clip (its own modules, the reference)",
    )
    bf16_networks: Switch = setting(
        "auto",
        "the SVBRDF and normal networks' matrix products under bfloat16 autocast while training (encodings, the heads' "
        "outputs, normals and the renderer stay float32; evaluation, baking and relighting run float32): auto, on or "
        "off as for bf16; the metadata's network_precision says what ran",
    )
    compile_shading: Switch = setting(
        "auto",
        "run the renderer through torch.compile while training (inductor fuses its pointwise operations; on a CPU it "
        "needs a C++ compiler, on CUDA Triton): auto compiles on a CPU with a C++ compiler for runs of at least 1,000 "
        "iterations, or 100 where the same renderer has been compiled on this machine before (the compilation is "
        "cached across processes under .cache/torchinductor: 3 s instead of about 80), and on CUDA for runs of at "
        "least 1,400 (a compilation of about 80 s, then steps twice as fast), where it pays; the metadata's "
        "shading_path says what ran",
    )
    compile_networks: Switch = setting(
        "auto",
        "compile the SVBRDF and normal networks into the compiled renderer's graph while training (one graph: "
        "inductor fuses the networks' pointwise operations with the renderer's; fewer kernel launches); only where "
        "compile_shading compiles the renderer. auto puts them in on CUDA (a paper step measured 0.040 s against the "
        "compiled renderer's 0.051 on an H200, for the same compilation time) and leaves them out on a CPU (measured "
        "no faster there); on puts them in; the metadata's shading_path says what ran",
    )
    compile_static: Switch = setting(
        "auto",
        "compile the one graph of compile_networks for a fixed number of points: each step's points padded to the "
        "training pool's largest view (copies of its first point, whose outputs are dropped), so that on CUDA "
        "torch.compile captures the graph, forward and backward, as CUDA graphs (its reduce-overhead mode: one launch "
        "per graph, not one per kernel); on a CPU the same graph with static shapes. Only where the networks are in "
        "the renderer's graph. auto leaves it off (not yet measured to pay); on puts it in; the metadata's "
        "shading_path says what ran",
    )
    keep_freed_memory: Switch = setting(
        "auto",
        "keep the memory a training step frees for the next step instead of giving it back to the system (glibc's "
        "malloc: the mmap threshold at 32 MiB, the trim threshold never reached), which spares the next step tens of "
        "thousands of page faults; the process keeps its step's peak memory, which it reaches every step anyway. "
        "auto and on where the C library is glibc (on warns elsewhere); off leaves the allocator as it is; the "
        "metadata's allocator says what ran",
    )
    onednn_products: Switch = setting(
        "auto",
        "run the float32 linear layers of a training step (the networks' and CLIP's) by oneDNN's matrix kernels on a "
        "CPU instead of ATen's (MKL's, which on AMD CPUs takes its AVX2 code even where the CPU has AVX-512): the same "
        "products to float32 rounding. auto measures both at start (about 0.05 s) and takes oneDNN where it is at "
        "least 1.05 times as fast; on takes it wherever torch has oneDNN (on warns elsewhere); off keeps ATen's, and "
        "the memory oneDNN's path takes (a float32 paper step: 3.0-3.2 GB at its peak against 2.4 GB). bfloat16 "
        "products and GPUs are not affected; the metadata's float32_products says what ran",
    )
    target_material: Material = setting("wood", "procedural material of the image targets (guidance: image)")
    target_renderer: TargetRenderer = setting(
        "mitsuba",
        "who renders the image targets: mitsuba (ground truth path-traced by Mitsuba 3 in the target stage; needs the "
        "`reference` extra) or sg (our own SG renderer under target_light: quick, but it grades itself)",
    )
    target_light: TargetLight = setting("studio", "the SG light of target_renderer: sg")
    checkpoint_every: int = setting(
        100, "iterations between checkpoints (a killed run resumes from the last one)", ge=1, le=1_000_000
    )
    eval_width: int = setting(256, "width = height in pixels of each evaluation render (renders/*.png)", ge=8, le=4096)

    #: settings that do not change what training computes: left out of :meth:`digest`, so a run
    #: resumes across them (compile_shading, compile_networks, compile_static: the same functions,
    #: compiled or not; keep_freed_memory: the same arithmetic in reused memory; onednn_products: the
    #: same products by other kernels)
    UNTRAINED: ClassVar[tuple[str, ...]] = (
        "checkpoint_every",
        "eval_width",
        "compile_shading",
        "compile_networks",
        "compile_static",
        "keep_freed_memory",
        "onednn_products",
    )

    def __post_init__(self) -> None:
        """``image_size: null`` becomes the guidance CLIP's input size (:func:`clip_input_size`), or 224
        (the paper's, ViT-B-32's) where it is not known or no CLIP guides; then the checks."""
        if self.image_size is None:
            known = isinstance(self.clip_model, str) and isinstance(self.clip_tiny_test, bool) and self._clip_guided()
            size = clip_input_size(self.clip_model, self.clip_tiny_test) if known else None
            object.__setattr__(self, "image_size", size or 224)
        super().__post_init__()

    def relations(self) -> list[str]:
        p = super().relations()
        lo, hi = self.crop_scale
        if lo > hi:
            p.append(f"optimize.crop_scale must be [smallest, largest] with smallest <= largest, got {list(self.crop_scale)}")
        if self.light == "fixed" and not self.light_map:
            p.append("optimize: light is fixed but no light_map names its environment (builtin:<name> or an .hdr/.exr file)")
        elif self.light == "learn" and self.light_map is not None:
            p.append(
                "optimize.light_map names the environment of light: fixed; with light: learn it would be ignored (remove it)"
            )
        if self.light_map is not None:
            p += environment_problems("optimize.light_map", self.light_map)
        if self.light == "fixed" and self.light_neutral > 0:
            p.append("optimize.light_neutral is a prior on a learned light; a fixed light (light: fixed) does not move")
        if self.light == "fixed" and self.light_prune_after is not None:
            p.append("optimize.light_prune_after prunes a learned light; a fixed light (light: fixed) keeps its fitted lobes")
        if self.light == "fixed" and not self.light_rgb:
            p.append("optimize: light: fixed needs light_rgb: true (the map's colour is part of the light)")
        size = clip_input_size(self.clip_model, self.clip_tiny_test) if self.guidance_mode().uses_clip else None
        if size is not None and size != self.image_size:
            clip = "the tiny test CLIP" if self.clip_tiny_test else self.clip_model
            p.append(
                f"optimize.image_size is {self.image_size} but the guidance CLIP, {clip}, takes {size} x {size} images: "
                f"set image_size: {size}"
            )
        return p

    def guidance_mode(self) -> GuidanceMode:
        """The guidance mode of ``guidance`` (:mod:`stages.config.guidance_modes`)."""
        return guidance_mode(self.guidance)

    def _clip_guided(self) -> bool:
        """Whether a CLIP guides (False for a guidance that is not a mode: the checks name it)."""
        return self.guidance in GUIDANCE_MODES and GUIDANCE_MODES[self.guidance].uses_clip

    def mitsuba_targets(self) -> bool:
        """Whether the optimisation trains on Mitsuba's image targets (the target stage's)."""
        return self.guidance_mode().mitsuba_targets(self.target_renderer)

    def digest(self) -> str:
        """Hash of the settings that shape training (a checkpoint resumes only under the same)."""
        d = {k: v for k, v in self.to_dict().items() if k not in self.UNTRAINED}
        return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]

    def field_settings(self) -> FieldSettings:
        """The settings the field is built from (networks, encodings, BRDF, shading, light, seed)."""
        return FieldSettings(**{f.name: getattr(self, f.name) for f in fields(FieldSettings)})


@dataclass(frozen=True, kw_only=True)
class BakeSettings(Settings):
    """Texture baking: the trained field written into textures over a UV atlas (variants may override)."""

    section = "bake"
    texture_size: int | None = setting(None, "texture width = height; null: from texels_per_face", ge=16, le=16384)
    texels_per_face: float = setting(
        64.0, "texel density when texture_size is null: texels per face, before packing losses", gt=0, le=1e6
    )
    min_size: int = setting(256, "smallest texture width the texel density may choose", ge=16, le=16384)
    max_size: int = setting(2048, "largest texture width the texel density may choose", ge=16, le=16384)
    padding: int = setting(4, "xatlas's padding between charts, in texels", ge=0, le=256)
    dilation: int = setting(8, "dilation passes that grow charts into empty texels", ge=0, le=1024)
    max_chart_share: float | None = setting(
        None,
        "the largest chart's area as a share of the surface (xatlas's max_chart_area); null: xatlas's unbounded charts "
        "(slow on large smooth meshes)",
        gt=0,
        le=1,
    )
    light_width: int = setting(512, "width of the equirectangular light image (height = width / 2)", ge=16, le=8192)
    eval_width: int = setting(256, "resolution of the fidelity renders (evaluation views)", ge=8, le=4096)
    occlusion: Switch = setting(
        "auto",
        "the ambient occlusion map (red channel of metallic_roughness.png; glTF occlusionTexture, UsdPreviewSurface "
        "occlusion): auto where the field was trained with shadows (its albedo then holds none), on, off",
    )
    occlusion_samples: int = setting(
        32768, "surface points the occlusion is traced at (both sides) and interpolated between", ge=256, le=4_194_304
    )
    uv: UvLayout = setting(
        "auto",
        "the UV layout baked into: keep (the input's own, OBJ or glTF; stops when it is not usable), second (a new layout "
        "of the input's own triangles, written as a second UV set of its glTF document beside its own; stops for an OBJ), "
        "auto (the input's where usable, else a second set where the input is glTF, else a new atlas, the reason "
        "recorded), atlas (a new xatlas atlas of the traced mesh, welded)",
    )
    uv_max_overlap: float = setting(
        0.01,
        "the share of faces that may overlap other faces in the input's UV layout (stacked copies of an island "
        "excepted) for it to be kept",
        ge=0,
        le=1,
    )

    def relations(self) -> list[str]:
        if self.min_size > self.max_size:
            return [f"bake.min_size must not exceed bake.max_size, got {self.min_size} > {self.max_size}"]
        return []

    def size_for(self, faces: int) -> int:
        """Texture size: the configured one, or the power of two nearest to
        ``sqrt(faces * texels_per_face / 0.75)`` (xatlas packs about 75%), clamped."""
        if self.texture_size is not None:
            return int(self.texture_size)
        want = math.sqrt(faces * self.texels_per_face / 0.75)
        size = 2 ** round(math.log2(max(want, 1.0)))
        return int(min(max(size, self.min_size), self.max_size))


@dataclass(frozen=True, kw_only=True)
class ExportSettings(Settings):
    """USD and glTF export of the baked asset."""

    section = "export"
    units: Literal["original", "normalized"] = setting(
        "original", "original: the input's units and position (the inverse transform); normalized: the unit sphere"
    )
    meters_per_unit: float = setting(
        1.0,
        "metres per unit of the exported geometry (USD metersPerUnit; glTF positions are scaled to metres by it)",
        gt=0,
        le=1e6,
    )
    weld: bool = setting(True, "share vertices where position, normal, UV and tangent agree (false: one vertex per face corner)")
    usdz_root: Literal["usdc", "usda"] = setting("usdc", "root layer inside model.usdz: usdc (binary crate) or usda (text)")


@dataclass(frozen=True, kw_only=True)
class RelightSettings(Settings):
    """Relighting under a new environment and material editing (TANGO Fig. 6)."""

    section = "relight"
    envmap: str = path_setting("builtin:sunset", f"environment map: {ENV_DOC}")
    lobes: int = setting(64, "SG lobes fitted to the map", ge=1, le=1024)
    fit_iterations: int = setting(400, "iterations of the SG fit to the map", ge=1, le=100_000)
    roughness_scales: tuple[float, ...] = setting(
        (0.5, 1.0, 2.0),
        "material editing grid (TANGO Fig. 6): factors of the roughness, one row each",
        ge=0,
        le=100,
        min_items=1,
        max_items=16,
    )
    specular_scales: tuple[float, ...] = setting(
        (0.0, 1.0, 2.0),
        "material editing grid: factors of the specular colour, one column each",
        ge=0,
        le=100,
        min_items=1,
        max_items=16,
    )
    width: int = setting(256, "width = height in pixels of each relit and material-editing image", ge=8, le=4096)

    def relations(self) -> list[str]:
        return environment_problems("relight.envmap", self.envmap)


@dataclass(frozen=True, kw_only=True)
class MetricsSettings(ClipChoice, Settings):
    """Quality metrics on the metric views; the evaluation CLIP is independent of the guidance."""

    section = "metrics"
    clip: bool = setting(True, "compute the CLIP-based metrics (needs weights, or clip_tiny_test)")
    clip_model: str = setting("ViT-B-16", "open_clip architecture of the independent evaluation CLIP", min_length=1)
    clip_pretrained: str = setting("openai", "open_clip weights tag of the evaluation CLIP", min_length=1)
    clip_checkpoint: str | None = path_setting(
        None, "a local open_clip checkpoint file for the evaluation CLIP; takes precedence over clip_pretrained"
    )
    clip_tiny_test: bool = setting(False, "the tiny random test CLIP for evaluation: every output is marked TEST ONLY")
    background: Literal["white", "black"] = setting("white", "background of the metric views")


@dataclass(frozen=True, kw_only=True)
class RoundtripSettings(Settings):
    """The Blender round trip: exported GLB/USDZ imported into Blender, checked, rendered with Cycles
    under the learned light from evaluation views and compared with our render of the trained field
    over object pixels (the ``blender`` extra; off by default, the main job never needs Blender)."""

    section = "roundtrip"
    enabled: bool = setting(False, "run the roundtrip stage for every cell")
    formats: tuple[RoundtripFormat, ...] = setting(ROUNDTRIP_FORMATS, "which exported files to import and render", min_items=1)
    views: int = setting(8, "evaluation views rendered, evenly spread over the ray cache's (0: all of them)", ge=0, le=1024)
    spp: int = setting(
        64,
        "Cycles samples per pixel, in two halves with different seeds (their difference is the noise)",
        ge=2,
        le=65536,
        multiple_of=2,
    )
    transport: Transport = setting(
        "direct_unshadowed",
        "direct_unshadowed: light straight from the world, no self-shadowing (what our renderer models); full: path tracing",
    )
    split_lobes: bool = setting(
        True,
        "also render the GLB's diffuse and specular lobes alone (two more Blender "
        "processes), which split the GLB's gap between the BRDF models",
    )
    seed: int = setting(0, "seed of Cycles' first half of the samples (the second half uses seed + 1)", ge=0, le=MAX_SEED)
    timeout_s: float = setting(3600.0, "longest a Blender job may run (seconds)", gt=0, le=604800)


@dataclass(frozen=True, kw_only=True)
class LodSettings(Settings):
    """Levels of detail for artists: the field trained on the traced mesh baked onto decimated
    versions of it (high-to-low: each texel of a level looks along its normal for the traced surface,
    so the normal map carries the detail a level lost), exported per level and as one USD with a
    ``LOD`` variant set and one GLB with ``MSFT_lod``. Off by default."""

    section = "lod"
    enabled: bool = setting(False, "run the lod stage for every cell")
    levels: tuple[float, ...] = setting(
        (0.5, 0.1, 0.02),
        "face fractions of the traced mesh, one level each (lod1, lod2, ...), decreasing",
        gt=0,
        lt=1,
        min_items=1,
        max_items=16,
    )
    texture_size: int | None = setting(
        None,
        "texture width of every level; null: the full bake's times the square root of the level's face fraction (a "
        "power of two, at least min_texture_size)",
        ge=16,
        le=16384,
    )
    min_texture_size: int = setting(64, "smallest texture width of a level when texture_size is null", ge=16, le=16384)
    cage: float = setting(
        2.0,
        "how far a texel's ray looks for the traced surface, in Hausdorff distances between the level and the traced mesh",
        gt=0,
        le=1000,
    )
    min_faces: int = setting(8, "fewest faces of a level (a level below it is refused)", ge=4, le=10_000_000)
    full_coverage: float = setting(
        0.5,
        "glTF MSFT_lod switching: level k takes over below full_coverage times its face fraction (a share of the screen)",
        gt=0,
        le=1,
    )

    def relations(self) -> list[str]:
        lv = list(self.levels)
        if any(a <= b for a, b in zip(lv, lv[1:], strict=False)):
            return [f"lod.levels must be strictly decreasing face fractions, got {lv}"]
        return []

    def level_texture_size(self, full_size: int, fraction: float) -> int:
        """Texture width of a level with ``fraction`` of the faces when the full bake is ``full_size``."""
        if self.texture_size is not None:
            return int(self.texture_size)
        # the nearest power of two, a tie (a fraction of exactly 1/4^k x 2) going up, whatever
        # the rounding of the logarithm
        size = 2 ** math.floor(math.log2(full_size * math.sqrt(fraction)) + 0.5 + 1e-9)
        return int(min(max(size, self.min_texture_size), full_size))

    def screen_coverage(self) -> list[float]:
        """MSFT_screencoverage: the coverage above which each level (lod0 first) is shown."""
        return [self.full_coverage * f for f in self.levels] + [0.0]


#: optimize settings that switch a component of TANGO off, and their "off" value: a variant whose
#: only differences from the reference variant are among these is an ablation (``report.ablations``)
ABLATION_SWITCHES = {
    "specular": False,
    "normal_network": False,
    "material_encoding": "none",
    "normal_encoding": "none",
    "crops": 0,
    "light_rgb": False,
    "light_init": "broad",
    "light_lr": None,
    "brdf": "tango",
    "shadows": False,
}


@dataclass(frozen=True, kw_only=True)
class ReportSettings(Settings):
    """The report (one per experiment): comparisons are drawn per mesh x prompt across variants,
    against a reference variant; ablation bars only for ablation variants. The HTML report is a
    folder (index.html, one page per cell with its assets beside it, 3D viewers loaded on demand)
    or, with single_file, one self-contained page."""

    section = "report"
    reference: str | None = setting(None, "the variant the others are measured against; null: the first variant", min_length=1)
    ablations: tuple[str, ...] | None = setting(
        None,
        "the ablation variants; null: every variant that differs from the reference only by switching components "
        "off (specular, normal_network, material/normal_encoding none, crops 0, light_rgb), seeds aside",
        min_length=1,
    )
    single_file: bool = setting(
        False, "one self-contained index.html (images and models inlined; for small grids) instead of a folder"
    )
    panels_per_figure: int = setting(
        36, "panels per figure file of the small-multiple plots (a larger grid is split over files)", ge=1, le=400
    )
    thumbnail_size: int = setting(128, "width in pixels of the index's thumbnails", ge=32, le=512)

    def relations(self) -> list[str]:
        if self.ablations is not None and self.reference is not None and self.reference in self.ablations:
            return [f"report: the reference variant {self.reference!r} cannot be one of the ablations"]
        return []


#: every config section that holds a stage's settings, and its class
SECTIONS: dict[str, type[Settings]] = {
    cls.section: cls
    for cls in (
        NormalizeSettings,
        DecimateSettings,
        RaycacheSettings,
        TargetSettings,
        OptimizeSettings,
        BakeSettings,
        ExportSettings,
        RoundtripSettings,
        LodSettings,
        RelightSettings,
        MetricsSettings,
        ReportSettings,
    )
}
