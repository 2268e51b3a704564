"""The settings of every stage: one frozen dataclass per config section, the only home of defaults.

Each class is what its stage receives (as JSON on the command line) and what the workflow resolves
per mesh or per grid cell; unknown keys fail (:class:`~stages.core.settings.Settings`). The config
schema (``workflow/schemas/config.schema.yaml``) repeats the defaults for users reading it;
``tests/config/test_sections.py`` checks every section of it against these classes. Nothing here
imports torch or numpy: the workflow builds its DAG from this module alone.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, fields
from typing import ClassVar

from ..core.cli import BF16_CHOICES
from ..core.errors import ConfigError
from ..core.settings import Settings

#: input up axes the normalize stage can turn into +y
UP_AXES = ("+y", "-y", "+z", "-z", "+x", "-x")
#: procedural target materials and lights of ``guidance: image`` (:mod:`stages.model.procedural`)
MATERIALS = ("wood", "metal", "chrome", "plaster")
LIGHTS = ("studio", "sky")
#: how the learned light's lobes start (``optimize.light_init``, :func:`stages.model.networks.initial_sharpness`):
#: all broad, TANGO's random draw, or sharpnesses spread log-uniformly from broad to sharp
LIGHT_INITS = ("broad", "tango", "spread")
#: the optimisation's light (``optimize.light``): learned with the material (TANGO), or the SG fit
#: of a known environment (``optimize.light_map``), held fixed
LIGHT_MODES = ("learn", "fixed")
#: the BRDF models (``optimize.brdf``, :mod:`stages.render.shading`): TANGO's diffuse + specular sum,
#: or glTF 2.0's metallic-roughness BRDF (GGX, separable Smith, dielectric/metal layering)
BRDFS = ("tango", "gltf")
#: the specular models of ``optimize.specular_lobe`` (:func:`stages.render.shading.shade`): TANGO's
#: closed form, the split sum with exact energy, and the fitted lobe with exact energy corrected by
#: the BRDF at each light lobe
SPECULAR_LOBES = ("isotropic", "split_sum", "fitted")
#: when the raycache stage traces the visibility shadows are cast from (``raycache.visibility``)
VISIBILITIES = ("off", "auto", "on")
#: shading normals (``optimize.shading_normals``, :mod:`stages.geometry.normals`): TANGO's face
#: normals, or vertex normals interpolated across faces with creases kept
SHADING_NORMALS = ("flat", "smooth")
#: corner weights of a smooth vertex normal (``optimize.normal_weighting``)
NORMAL_WEIGHTINGS = ("angle", "area")
#: who renders image targets (``optimize.target_renderer``)
TARGET_RENDERERS = ("mitsuba", "sg")
#: CLIP image-tower paths (stages/guidance/vit.py): "batched" (the same function on contiguous
#: matrix products) or "open_clip" (its own modules, the reference)
CLIP_TOWERS = ("batched", "open_clip")
#: the procedural environment maps ``relight.envmap: builtin:<name>`` names (:mod:`stages.render.envmap`)
PROCEDURAL_ENVMAPS = ("sunset", "overcast", "night", "sun_sky", "studio")
ENCODINGS = ("nerf", "fourier", "hashgrid", "none")
#: decimate.mode: to a face count, or to the ray cache's face budget
DECIMATE_MODES = ("faces", "share", "budget")
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
    """Settings of the normalize stage (config section ``normalize``, overridable per mesh)."""

    section = "normalize"
    #: the input's up axis (UP_AXES); it becomes +y, the up axis of the cameras. "auto": the file
    #: format's convention where it has one, else a guess recorded with its evidence in the
    #: metadata (stages/geometry/normalization.py)
    up_axis: str = "+y"
    #: the most faces a mesh may have: past it the stage refuses it, naming decimation as the remedy
    #: (the unwrap, the bake and the assets grow with the faces; the training does not)
    max_faces: int = 2_000_000
    #: settings that accept or refuse a mesh without changing what is written: left out of the
    #: mesh-level work's key (a raised limit does not recompute meshes already normalised)
    UNKEYED: ClassVar[tuple[str, ...]] = ("max_faces",)

    def keyed(self) -> dict:
        return {k: v for k, v in self.to_dict().items() if k not in self.UNKEYED}

    def __post_init__(self) -> None:
        if self.up_axis not in (*UP_AXES, "auto"):
            raise ConfigError(f"normalize.up_axis must be auto or one of {sorted(UP_AXES)}, got {self.up_axis!r}")


@dataclass(frozen=True, kw_only=True)
class DecimateSettings(Settings):
    """Settings of the decimate stage (config section ``decimate``, overridable per mesh)."""

    section = "decimate"
    #: whether the workflow inserts this stage for a mesh (the stage itself always decimates)
    enabled: bool = False
    #: face count to reach (TANGO's robustness study: 5000)
    target_faces: int = 5000
    #: MeshLab's quality threshold for the collapse (0..1; higher avoids slivers)
    quality_threshold: float = 0.3
    #: keep boundary edges in place
    preserve_boundary: bool = True
    #: forbid collapses that flip a face normal
    preserve_normal: bool = True
    #: Hausdorff sampling: number of surface samples per direction
    hausdorff_samples: int = 100_000
    #: weld coincident vertices (UV/normal seams of exported meshes) before the collapse
    weld: bool = True
    #: vertices closer than this fraction of the bounding-box diagonal are welded (0: exact duplicates only)
    weld_tolerance: float = 1e-6
    #: if the collapse stops above the target with boundaries preserved, collapse again with
    #: boundary vertices free to slide along the boundary (topology kept); the reason is recorded
    relax_boundary: bool = True
    #: DECIMATE_MODES: "faces" decimates to target_faces (the robustness study); "share" to
    #: target_share of the mesh's own faces (0.1: a tenth); "budget" to the
    #: face budget of the mesh's ray cache (stages.geometry.decimation.face_budget: the faces
    #: whose mean area covers pixels_per_face pixels at the cache's camera distance), and a mesh
    #: already within its budget passes unchanged ("model only what the scene requires")
    mode: str = "faces"
    target_share: float = 0.1
    pixels_per_face: float = 1.0

    def __post_init__(self) -> None:
        if self.target_faces < 4:
            raise ConfigError(f"decimate.target_faces must be >= 4, got {self.target_faces}")
        if self.mode not in DECIMATE_MODES:
            raise ConfigError(f"decimate.mode must be one of {', '.join(DECIMATE_MODES)}, got {self.mode!r}")
        if not 0.0 < self.target_share < 1.0:
            raise ConfigError(f"decimate.target_share must be in (0, 1) (of the mesh's faces), got {self.target_share}")
        if not 0.01 <= self.pixels_per_face <= 1e4:
            raise ConfigError(f"decimate.pixels_per_face must be in [0.01, 1e4], got {self.pixels_per_face}")
        if not 0 <= self.weld_tolerance < 0.01:
            raise ConfigError(f"decimate.weld_tolerance must be in [0, 0.01) (of the diagonal), got {self.weld_tolerance}")


@dataclass(frozen=True, kw_only=True)
class RaycacheSettings(Settings):
    """Settings of the raycache stage (config section ``raycache``, overridable per mesh)."""

    section = "raycache"
    #: size of the sampled training view pool (view 0 is the anchor)
    views: int = 64
    #: image width = height in pixels (TANGO: 512)
    resolution: int = 512
    #: full field of view in degrees (TANGO: 60)
    fov_deg: float = 60.0
    #: camera distance from the origin; the unit sphere fills the view at 1 / sin(fov / 2)
    radius: float = 2.0
    #: anchor (front) view, radians (TANGO's demos: azimuth 1.96, elevation 0.63)
    anchor_azimuth: float = 1.96
    anchor_elevation: float = 0.63
    #: the anchor as [azimuth, elevation] in degrees (azimuth from +x towards +z about +y,
    #: elevation above the horizon), usually set per mesh so that the front view shows the
    #: object's front; when set it replaces anchor_azimuth/anchor_elevation
    anchor_deg: tuple[float, float] | None = None
    #: spread divisor: elevation std pi/std, azimuth std 2 pi/std (TANGO's demos: 8)
    std: float = 8.0
    #: seed of the view sampler
    seed: int = 0
    #: evaluation views: this many azimuths times these elevations (degrees)
    eval_azimuths: int = 8
    eval_elevations_deg: tuple[float, ...] = (-30.0, 0.0, 30.0)
    eval_radius: float = 2.0
    eval_fov_deg: float = 60.0
    eval_resolution: int = 512
    #: metric views (the X-Mesh protocol): azimuths x elevations, radius 2.5, 45 deg, 224 px
    metrics_azimuths: int = 8
    metrics_elevations_deg: tuple[float, ...] = (-30.0, 0.0, 30.0)
    metrics_radius: float = 2.5
    metrics_fov_deg: float = 45.0
    metrics_resolution: int = 224
    #: ray-tracing backend: "embree" (embreex) or "trimesh" (pure Python; tiny test inputs only)
    backend: str = "embree"
    #: shadows (VISIBILITIES; docs/method/shadows.md): "on" traces, for every cached hit, the
    #: visibility of visibility_directions directions (bits) that the field's shading casts shadows
    #: from; "auto" does so when the mesh's measured self-occlusion (the blocked share of the
    #: hemisphere over its surface) reaches visibility_auto_p95 at its 95th percentile, so a convex
    #: mesh (0 everywhere) pays nothing; "off" (TANGO) none.
    visibility: str = "auto"
    visibility_directions: int = 512
    #: auto's threshold on the 95th percentile of the self-occlusion: shadows raised the recovery
    #: of every built-in mesh (vase, p95 0.99, +7.3 dB; knot 0.45, +0.5 dB; candle 0.26, +0.3 dB;
    #: docs/method/shadows.md), and a convex mesh has 0
    visibility_auto_p95: float = 0.05

    def __post_init__(self) -> None:
        problems = []
        if self.views < 1:
            problems.append(f"views must be >= 1, got {self.views}")
        for name in ("resolution", "eval_resolution", "metrics_resolution"):
            if not 8 <= getattr(self, name) <= 8192:
                problems.append(f"{name} must be in [8, 8192], got {getattr(self, name)}")
        for name in ("fov_deg", "eval_fov_deg", "metrics_fov_deg"):
            if not 0.0 < getattr(self, name) < 180.0:
                problems.append(f"{name} must be in (0, 180), got {getattr(self, name)}")
        for name in ("radius", "eval_radius", "metrics_radius", "std"):
            if not getattr(self, name) > 0:
                problems.append(f"{name} must be > 0, got {getattr(self, name)}")
        if self.backend not in ("embree", "trimesh"):
            problems.append(f"backend must be 'embree' or 'trimesh', got {self.backend!r}")
        if isinstance(self.visibility, bool):  # YAML 1.1 reads a bare on/off as a boolean
            object.__setattr__(self, "visibility", "on" if self.visibility else "off")
        if self.visibility not in VISIBILITIES:
            problems.append(f"visibility must be one of {', '.join(VISIBILITIES)}, got {self.visibility!r}")
        if not (8 <= self.visibility_directions <= 4096 and self.visibility_directions % 8 == 0):
            problems.append(f"visibility_directions must be a multiple of 8 in [8, 4096], got {self.visibility_directions}")
        if not 0.0 <= self.visibility_auto_p95 <= 1.0:
            problems.append(f"visibility_auto_p95 must be in [0, 1], got {self.visibility_auto_p95}")
        if not -2 * math.pi - 1e-4 <= self.anchor_azimuth <= 2 * math.pi + 1e-4:
            problems.append(f"anchor_azimuth must be in [-2 pi, 2 pi] radians, got {self.anchor_azimuth}")
        if not -math.pi / 2 < self.anchor_elevation < math.pi / 2:
            problems.append(f"anchor_elevation must be in (-pi/2, pi/2) radians, got {self.anchor_elevation}")
        if self.anchor_deg is not None and len(self.anchor_deg) == 2 and not -360.0 <= self.anchor_deg[0] <= 360.0:
            problems.append(f"anchor_deg's azimuth must be in [-360, 360] degrees, got {self.anchor_deg[0]}")
        if self.anchor_deg is not None and (len(self.anchor_deg) != 2 or not -90.0 < self.anchor_deg[1] < 90.0):
            problems.append(f"anchor_deg must be [azimuth, elevation] with elevation in (-90, 90), got {list(self.anchor_deg)}")
        if problems:
            raise ConfigError("raycache settings: " + "; ".join(problems))

    def anchor(self) -> tuple[float, float, str]:
        """The anchor (front) view ``(azimuth, elevation)`` in radians and what set it."""
        if self.anchor_deg is not None:
            return math.radians(self.anchor_deg[0]), math.radians(self.anchor_deg[1]), "raycache.anchor_deg"
        default = (type(self).anchor_azimuth, type(self).anchor_elevation)
        if (self.anchor_azimuth, self.anchor_elevation) == default:
            return self.anchor_azimuth, self.anchor_elevation, "default (TANGO's demo scripts: azimuth 1.96, elevation 0.63 rad)"
        return self.anchor_azimuth, self.anchor_elevation, "raycache.anchor_azimuth/anchor_elevation (radians)"


def environment_problems(key: str, env: str) -> list[str]:
    """What is wrong with ``env`` as the environment map of setting ``key``: ``builtin:<name>`` of a
    procedural map, or an .hdr/.exr path."""
    if env.startswith("builtin:") and env.split(":", 1)[1] not in PROCEDURAL_ENVMAPS:
        return [f"{key}: no procedural environment {env!r}; use one of {PROCEDURAL_ENVMAPS}"]
    if not env.startswith("builtin:") and not env.lower().endswith((".hdr", ".exr")):
        return [f"{key}: {env!r} is neither builtin:<name> nor an .hdr/.exr file"]
    return []


@dataclass(frozen=True, kw_only=True)
class FieldSettings:
    """What the stylisation field (:class:`~stages.model.field.StyleField`) is built from: the
    network, encoding and light fields of :class:`OptimizeSettings`, which is their one source
    (:meth:`OptimizeSettings.field_settings`); no defaults of its own."""

    seed: int
    symmetry: bool
    width: int
    material_encoding: str
    material_frequencies: int
    material_fourier_count: int
    material_fourier_sigma: float
    specular: bool
    init_specular: float | None
    init_roughness: float | None
    init_metallic: float | None
    min_roughness: float
    normal_network: bool
    normal_encoding: str
    normal_frequencies: int
    normal_fourier_count: int
    normal_fourier_sigma: float
    normal_max_delta: float
    hashgrid_levels: int
    hashgrid_features: int
    hashgrid_log2_size: int
    hashgrid_min_resolution: int
    hashgrid_max_resolution: int
    hashgrid_step_scale: float
    light_lobes: int
    light_rgb: bool
    light_energy: float
    light_init: str
    light_init_sharpness: float | None
    light_init_max_sharpness: float
    brdf: str
    specular_lobe: str
    shading_normals: str
    shadows: bool
    crease_angle_deg: float
    normal_weighting: str


@dataclass(frozen=True, kw_only=True)
class OptimizeSettings(ClipChoice, Settings):
    """Settings of the optimize stage (config section ``optimize``; presets and variants override).

    Defaults follow TANGO's paper and demo scripts where they state a value.
    """

    section = "optimize"
    # schedule
    iterations: int = 1500
    lr: float = 5e-4
    weight_decay: float = 0.0
    milestones: tuple[int, ...] = (500, 1000)
    gamma: float = 0.7
    seed: int = 0
    # images per step
    views_per_step: int = 1
    image_size: int = 224
    supersample: int = 1
    crops: int = 4
    crop_scale: tuple[float, float] = (0.01, 0.2)
    crop_coverage: float = 0.3
    crop_max_tries: int = 20
    background: str = "black"
    # networks
    symmetry: bool = False
    width: int = 256
    material_encoding: str = "nerf"
    material_frequencies: int = 12
    material_fourier_count: int = 128
    material_fourier_sigma: float = 0.5
    specular: bool = True
    init_specular: float | None = None
    init_roughness: float | None = None
    #: glTF's metallic head starts near this value everywhere (null: the networks' random start,
    #: about 0.5); a dielectric start is 0.02
    init_metallic: float | None = None
    min_roughness: float = 0.01
    normal_network: bool = True
    normal_encoding: str = "nerf"
    normal_frequencies: int = 10
    normal_fourier_count: int = 128
    normal_fourier_sigma: float = 0.5
    normal_max_delta: float = 0.3
    #: the multiresolution hash grid (an encoding "hashgrid", Mueller et al. 2022; each network
    #: that uses it has its own table): levels, features per level, log2 of the entries per
    #: level, coarsest and finest grid resolution over [-1, 1]^3, and how many times the
    #: networks' step the table's optimiser step is (stages/model/networks.py HashGridEncoding)
    hashgrid_levels: int = 16
    hashgrid_features: int = 2
    hashgrid_log2_size: int = 17
    hashgrid_min_resolution: int = 16
    hashgrid_max_resolution: int = 1024
    hashgrid_step_scale: float = 20.0
    light_lobes: int = 32
    light_rgb: bool = True
    light_energy: float = 6.25
    #: how the lobes start (LIGHT_INITS): "broad" (every lobe at light_init_sharpness, or where
    #: Fibonacci neighbours overlap at half maximum, about 2 for 16 lobes), "tango" (TANGO's draw
    #: 20 + |N(0,1)| 100, seeded by the run's seed) or "spread" (log-uniform from the broad
    #: sharpness to light_init_max_sharpness, interleaved over the sphere). "tango" since
    #: 2026-11-24, measured best on Mitsuba's wood vase and metal candle (docs/method/lighting.md)
    light_init: str = "tango"
    light_init_sharpness: float | None = None
    light_init_max_sharpness: float = 1000.0
    #: the light's own learning rate (its parameters are logarithms and directions, so a step moves
    #: them by a factor or an angle whatever the networks' rate); null: lr. No weight decay applies
    light_lr: float | None = 0.02
    #: lighting as the scene requires ("light_lobes: auto"): after this many iterations (the
    #: warm-up) the lobes whose energy is below light_prune_share of the light's total in every
    #: channel are dropped for the rest of the run; null: every lobe is kept (TANGO)
    light_prune_after: int | None = None
    light_prune_share: float = 0.01
    #: "learn" (TANGO: the light is learned with the material) or "fixed": the light is the SG fit
    #: of light_map (light_lobes lobes) and never moves, so nothing can trade the base colour
    #: against the light's brightness or colour (LIGHT_MODES; docs/method/lighting.md)
    light: str = "learn"
    #: the environment of light: fixed, builtin:<name> or an .hdr/.exr path (the light the asset
    #: is to be lit by, or the one the images were lit by)
    light_map: str | None = None
    #: weight of the prior that takes glTF's metallic to 0 or 1 (a surface is a metal or a
    #: dielectric; the glTF specification keeps values between for transitions): the mean of
    #: m (1 - m) over each step's shaded points (0: off)
    metallic_binary: float = 0.0
    #: weight of the prior that keeps a learned light's colour neutral: each lobe's spread of log
    #: energy over the channels, weighted by its share of the light's energy (0: off)
    light_neutral: float = 0.0
    #: weight of the prior that keeps the material smooth over the surface (nvdiffrec's): the mean
    #: absolute change of the base colour, and of metallic and roughness, between each step's hit
    #: points and the same points moved by a random offset of material_smooth_radius (0: off)
    material_smooth: float = 0.0
    #: the standard deviation of that offset per axis, in the unit sphere the mesh is scaled to
    material_smooth_radius: float = 0.01
    #: weight of the prior that keeps the predicted normals near the mesh's: the mean of 1 - cos of
    #: their angle over each step's hits (0: off; nothing to act on without normal_network). 0.01
    #: raised the training-light figure of every relighting cell by 0.28-0.35 dB and the relit
    #: figure after the scale by 0.14-1.05 dB, over three seeds (docs/measurements/relighting.md)
    normal_tilt: float = 0.01
    #: the specular model (SPECULAR_LOBES): "isotropic" (TANGO's closed form), "split_sum" (exact
    #: energy from the tabulated directional albedo, the isotropic lobe's shape) or "fitted" (exact
    #: energy, a lobe fitted to the BRDF's moments, corrected by the BRDF at each light lobe); see
    #: stages/render/shading.py and docs/measurements/shading.md (fitted: the most accurate at the
    #: isotropic model's cost, and no worse in recovery; measured 2026-11-22)
    specular_lobe: str = "fitted"
    #: the BRDF model (BRDFS): "tango" (TANGO's diffuse albedo + specular colour, the sum of a
    #: diffuse and a microfacet term) or "gltf" (glTF 2.0's metallic-roughness BRDF: base colour,
    #: metallic, roughness, GGX, the dielectric's F0 0.04 and (1 - F) diffuse weight, the metal's
    #: F0 its base colour; needs specular_lobe fitted or split_sum); bake and export write what was
    #: trained. "gltf" since 2026-11-25: its assets round-trip through Blender better in every
    #: demo cell (GLB +0.6 to +7.6 dB, USDZ +5.7 to +17.4 dB) and it recovers roughness better
    #: (docs/measurements/light-brdf.md); "tango" for TANGO's own model and its "-spec, rough"
    #: ablation (specular: false). docs/method/brdf.md
    brdf: str = "gltf"
    #: the normals the field shades with and its normal network starts from (SHADING_NORMALS):
    #: "flat" (TANGO: face normals) or "smooth" (vertex normals interpolated across each face,
    #: edges sharper than crease_angle_deg kept, corners weighted by normal_weighting); carried
    #: through training, baking (the tangent frame), export and relighting. Smooth since
    #: 2026-11-22: the same held-out PSNR on decimated meshes (within 0.1 dB), a lower normal
    #: error in every fit, and assets that look smooth in every viewer (docs/measurements/recovery.md)
    shading_normals: str = "smooth"
    crease_angle_deg: float = 60.0
    normal_weighting: str = "angle"
    #: cast shadows where the ray cache holds visibility (raycache.visibility; the shading scales
    #: each light lobe by its visible share, docs/method/shadows.md); false: TANGO's unshadowed
    #: shading whatever the cache holds (an ablation switch)
    shadows: bool = True
    # guidance
    guidance: str = "clip"
    clip_model: str = "ViT-B-32"
    clip_pretrained: str = "openai"
    clip_checkpoint: str | None = None
    clip_tiny_test: bool = False
    #: CLIP's image tower under bfloat16 autocast (BF16_CHOICES): auto where the device runs
    #: bfloat16 natively (stages.core.cli.bf16_choice), on, off; what ran goes into the metadata
    #: (clip_precision). auto since 2026-11-25: 2.2x faster on such a CPU, image-gradient cosine
    #: 0.9999 (docs/measurements/speed.md)
    bf16: str = "auto"
    #: CLIP's image tower (CLIP_TOWERS): "batched" (attention and patch embedding as contiguous
    #: matrix products, frozen weights cast once under bf16: the same function, faster on a CPU)
    #: or "open_clip" (its own modules)
    clip_tower: str = "batched"
    #: the SVBRDF and normal networks' matrix products under bfloat16 autocast during training
    #: (encodings, activations' outputs and the renderer stay float32; BF16_CHOICES, as bf16);
    #: metadata network_precision
    bf16_networks: str = "auto"
    #: the renderer through torch.compile while training (inductor; on a CPU it needs a C++
    #: compiler): fused pointwise loops, compiled once per process; auto: on a CPU with a compiler
    #: for runs long enough to repay it (stages.core.cli.compile_choice; metadata shading_path)
    compile_shading: str = "auto"
    target_material: str = "wood"
    #: who renders the image targets: "mitsuba" (path-traced ground truth, the target stage) or
    #: "sg" (our own SG renderer under target_light: fast, but the renderer grades itself)
    target_renderer: str = "mitsuba"
    target_light: str = "studio"
    # outputs
    checkpoint_every: int = 100
    eval_width: int = 256

    def __post_init__(self) -> None:
        p = []
        if self.iterations < 1:
            p.append(f"iterations must be >= 1, got {self.iterations}")
        for name in ("bf16", "bf16_networks", "compile_shading"):
            if isinstance(getattr(self, name), bool):  # YAML 1.1 reads a bare on/off as a boolean
                object.__setattr__(self, name, "on" if getattr(self, name) else "off")
            if getattr(self, name) not in BF16_CHOICES:
                p.append(f"{name} must be one of {', '.join(BF16_CHOICES)}, got {getattr(self, name)!r}")
        if self.guidance not in ("clip", "image"):
            p.append(f"guidance must be 'clip' or 'image', got {self.guidance!r}")
        for name in ("material_encoding", "normal_encoding"):
            if getattr(self, name) not in ENCODINGS:
                p.append(f"{name} must be one of {', '.join(ENCODINGS)}, got {getattr(self, name)!r}")
        if not (1 <= self.hashgrid_levels <= 32 and 1 <= self.hashgrid_features <= 8 and 10 <= self.hashgrid_log2_size <= 24):
            p.append("hashgrid_levels must be in 1..32, hashgrid_features in 1..8 and hashgrid_log2_size in 10..24")
        elif self.hashgrid_levels * self.hashgrid_features * 2**self.hashgrid_log2_size > 2**26:
            p.append(
                "a hash grid of hashgrid_levels x hashgrid_features x 2^hashgrid_log2_size must hold at most 2^26 "
                f"(67M) parameters per network, got {self.hashgrid_levels * self.hashgrid_features * 2**self.hashgrid_log2_size}"
            )
        if not 2 <= self.hashgrid_min_resolution <= self.hashgrid_max_resolution <= 2**16:
            # float32 coordinates resolve 2^-24 of the box: 2^16 cells leave 8 bits inside a cell
            p.append("hashgrid resolutions must satisfy 2 <= hashgrid_min_resolution <= hashgrid_max_resolution <= 65536")
        if not self.hashgrid_step_scale > 0:
            p.append(f"hashgrid_step_scale must be > 0, got {self.hashgrid_step_scale}")
        if self.background not in ("black", "white", "noise"):
            p.append(f"background must be black, white or noise, got {self.background!r}")
        lo, hi = self.crop_scale
        if not 0 < lo <= hi <= 1:
            p.append(f"crop_scale must satisfy 0 < lo <= hi <= 1, got {self.crop_scale}")
        if not 0 < self.min_roughness < 1:
            p.append(f"min_roughness must be in (0, 1), got {self.min_roughness}")
        if self.target_material not in MATERIALS:
            p.append(f"target_material must be one of {MATERIALS}, got {self.target_material!r}")
        if self.target_renderer not in TARGET_RENDERERS:
            p.append(f"target_renderer must be one of {TARGET_RENDERERS}, got {self.target_renderer!r}")
        if self.specular_lobe not in SPECULAR_LOBES:
            p.append(f"specular_lobe must be one of {', '.join(SPECULAR_LOBES)}, got {self.specular_lobe!r}")
        if self.shading_normals not in SHADING_NORMALS:
            p.append(f"shading_normals must be one of {', '.join(SHADING_NORMALS)}, got {self.shading_normals!r}")
        if self.normal_weighting not in NORMAL_WEIGHTINGS:
            p.append(f"normal_weighting must be one of {', '.join(NORMAL_WEIGHTINGS)}, got {self.normal_weighting!r}")
        if not 0.0 <= self.crease_angle_deg <= 180.0:
            p.append(f"crease_angle_deg must be in [0, 180], got {self.crease_angle_deg}")
        if self.brdf not in BRDFS:
            p.append(f"brdf must be one of {', '.join(BRDFS)}, got {self.brdf!r}")
        elif self.brdf == "gltf" and self.specular_lobe == "isotropic":
            p.append(
                "brdf gltf (the default) has no isotropic specular model (TANGO's closed form); "
                "use specular_lobe fitted or split_sum, or set brdf: tango"
            )
        elif self.brdf == "gltf" and not self.specular:
            p.append(
                "brdf gltf (the default) needs its metallic and roughness heads: "
                "set specular: true, or brdf: tango for a diffuse-only field"
            )
        elif self.brdf == "gltf" and self.init_specular is not None:
            p.append(
                "init_specular is TANGO's specular colour, which brdf gltf (the default) does not have: "
                "remove it, or set brdf: tango"
            )
        if self.light_init not in LIGHT_INITS:
            p.append(f"light_init must be one of {', '.join(LIGHT_INITS)}, got {self.light_init!r}")
        if not 1e-4 <= self.light_init_max_sharpness <= 1e5:
            p.append(f"light_init_max_sharpness must be in [1e-4, 1e5], got {self.light_init_max_sharpness}")
        if self.light_init_sharpness is not None and not 1e-4 <= self.light_init_sharpness <= 1e5:
            p.append(f"light_init_sharpness must be in [1e-4, 1e5] or null, got {self.light_init_sharpness}")
        if self.light_lr is not None and not self.light_lr > 0:
            p.append(f"light_lr must be > 0 or null, got {self.light_lr}")
        if self.light_prune_after is not None and self.light_prune_after < 1:
            p.append(f"light_prune_after must be >= 1 or null, got {self.light_prune_after}")
        if not 0.0 < self.light_prune_share < 1.0:
            p.append(f"light_prune_share must be in (0, 1), got {self.light_prune_share}")
        p += self._light_problems()
        if self.clip_tower not in CLIP_TOWERS:
            p.append(f"clip_tower must be one of {', '.join(CLIP_TOWERS)}, got {self.clip_tower!r}")
        if self.target_light not in LIGHTS:
            p.append(f"target_light must be one of {LIGHTS}, got {self.target_light!r}")
        if self.views_per_step < 1 or self.crops < 0 or self.supersample < 1 or self.checkpoint_every < 1:
            p.append("views_per_step, supersample and checkpoint_every must be >= 1 and crops >= 0")
        if p:
            raise ConfigError("optimize settings: " + "; ".join(p))

    def _light_problems(self) -> list[str]:
        """What is wrong with the light's mode, map and prior."""
        p = []
        if self.light not in LIGHT_MODES:
            p.append(f"light must be one of {', '.join(LIGHT_MODES)}, got {self.light!r}")
        elif self.light == "fixed" and not self.light_map:
            p.append("light is fixed but no light_map names its environment (builtin:<name> or an .hdr/.exr file)")
        elif self.light == "learn" and self.light_map is not None:
            p.append("light_map names the environment of light: fixed; with light: learn it would be ignored (remove it)")
        if self.light_map is not None:
            p += environment_problems("light_map", self.light_map)
        if not 0.0 <= self.metallic_binary <= 1e6:
            p.append(f"metallic_binary must be in [0, 1e6], got {self.metallic_binary}")
        elif self.metallic_binary > 0 and self.brdf != "gltf":
            p.append("metallic_binary is a prior on glTF's metallic: set brdf: gltf, or metallic_binary: 0")
        if self.init_metallic is not None and not 0.0 <= self.init_metallic <= 1.0:
            p.append(f"init_metallic must be in [0, 1] or null, got {self.init_metallic}")
        elif self.init_metallic is not None and self.brdf != "gltf":
            p.append("init_metallic is glTF's metallic, which brdf tango does not have: remove it, or set brdf: gltf")
        if not 0.0 <= self.light_neutral <= 1e6:
            p.append(f"light_neutral must be in [0, 1e6], got {self.light_neutral}")
        elif self.light == "fixed" and self.light_neutral > 0:
            p.append("light_neutral is a prior on a learned light; a fixed light (light: fixed) does not move")
        if not 0.0 <= self.material_smooth <= 1e6:
            p.append(f"material_smooth must be in [0, 1e6], got {self.material_smooth}")
        if not 0.0 < self.material_smooth_radius <= 1.0:
            p.append(f"material_smooth_radius must be in (0, 1] (the unit sphere's radius), got {self.material_smooth_radius}")
        if not 0.0 <= self.normal_tilt <= 1e6:
            p.append(f"normal_tilt must be in [0, 1e6], got {self.normal_tilt}")
        if self.light == "fixed" and self.light_prune_after is not None:
            p.append("light_prune_after prunes a learned light; a fixed light (light: fixed) keeps its fitted lobes")
        if self.light == "fixed" and not self.light_rgb:
            p.append("light: fixed needs light_rgb: true (the map's colour is part of the light)")
        return p

    def digest(self) -> str:
        """Hash of the settings that shape training (a checkpoint resumes only under the same)."""
        # compile_shading: the same renderer compiled or not (a resumed run may take the other)
        d = {k: v for k, v in self.to_dict().items() if k not in ("checkpoint_every", "eval_width", "compile_shading")}
        return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]

    def field_settings(self) -> FieldSettings:
        """The subset that builds the field (networks, encodings, light, seed)."""
        return FieldSettings(**{f.name: getattr(self, f.name) for f in fields(FieldSettings)})


@dataclass(frozen=True, kw_only=True)
class BakeSettings(Settings):
    """Settings of the bake stage (config section ``bake``; variants may override)."""

    section = "bake"
    #: texture width = height; null: from the texel density below
    texture_size: int | None = None
    #: texel density target when texture_size is null: texels per face (before packing losses)
    texels_per_face: float = 64.0
    min_size: int = 256
    max_size: int = 2048
    #: xatlas packing padding between charts, in texels
    padding: int = 4
    #: dilation passes that grow charts into empty texels
    dilation: int = 8
    #: the largest chart's area as a share of the surface (xatlas's max_chart_area); null:
    #: xatlas's unbounded charts. Bounding them makes large smooth meshes unwrap many times
    #: faster for more seams (benchmarks/bake_charts.py; docs/measurements/assets.md)
    max_chart_share: float | None = None
    #: width of the equirectangular light image (height = width / 2)
    light_width: int = 512
    #: resolution of the fidelity renders (evaluation views)
    eval_width: int = 256
    #: the ambient occlusion map (the red channel of metallic_roughness.png, glTF's
    #: occlusionTexture, UsdPreviewSurface's occlusion): "auto" where the field was trained with
    #: shadows (optimize.shadows and a ray cache with visibility), whose albedo then holds no
    #: shadows; "on" always; "off" never (the channel stays 1 and no material reads it)
    occlusion: str = "auto"
    #: surface points the occlusion is traced at (both sides, the ray cache's visibility
    #: directions) and interpolated between for every texel
    occlusion_samples: int = 32768

    def __post_init__(self) -> None:
        if isinstance(self.occlusion, bool):  # YAML 1.1 reads a bare on/off as a boolean
            object.__setattr__(self, "occlusion", "on" if self.occlusion else "off")
        if self.occlusion not in VISIBILITIES:
            raise ConfigError(f"bake.occlusion must be one of {', '.join(VISIBILITIES)}, got {self.occlusion!r}")
        if not 256 <= self.occlusion_samples <= 1 << 22:
            raise ConfigError(f"bake.occlusion_samples must be in [256, 4194304], got {self.occlusion_samples}")
        if self.texture_size is not None and not 16 <= self.texture_size <= 16384:
            raise ConfigError(f"bake.texture_size must be in [16, 16384], got {self.texture_size}")
        if not 16 <= self.min_size <= self.max_size:
            raise ConfigError("bake: need 16 <= min_size <= max_size")
        if self.max_chart_share is not None and not 0.0 < self.max_chart_share <= 1.0:
            raise ConfigError(f"bake.max_chart_share must be in (0, 1] or null, got {self.max_chart_share}")

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
    """Settings of the export stage (config section ``export``)."""

    section = "export"
    #: "original": the input's units and position (inverse transform); "normalized": unit sphere
    units: str = "original"
    #: metres per unit of the exported geometry (USD metersPerUnit; glTF positions are scaled
    #: to metres by it)
    meters_per_unit: float = 1.0
    #: share vertices wherever position, normal, UV and tangent agree (split only at UV seams,
    #: creases and handedness changes); false: every face corner its own vertex (the layout
    #: before 2026-11-22, about three times larger)
    weld: bool = True
    #: the root layer inside model.usdz: "usdc" (USD's binary crate, as usdz files usually carry)
    #: or "usda" (text, the packaging before 2026-11-22); model.usda beside it stays text
    usdz_root: str = "usdc"

    def __post_init__(self) -> None:
        if self.units not in ("original", "normalized"):
            raise ConfigError(f"export.units must be 'original' or 'normalized', got {self.units!r}")
        if not self.meters_per_unit > 0:
            raise ConfigError("export.meters_per_unit must be > 0")
        if self.usdz_root not in ("usdc", "usda"):
            raise ConfigError(f"export.usdz_root must be 'usdc' or 'usda', got {self.usdz_root!r}")


@dataclass(frozen=True, kw_only=True)
class RelightSettings(Settings):
    """Settings of the relight stage (config section ``relight``)."""

    section = "relight"
    #: environment map: a .hdr/.exr path or builtin:sunset | builtin:overcast | builtin:night
    envmap: str = "builtin:sunset"
    #: SG lobes fitted to the map, and fitting iterations
    lobes: int = 64
    fit_iterations: int = 400
    #: material editing grid (TANGO Fig. 6): rows scale roughness, columns scale specular
    roughness_scales: tuple[float, ...] = (0.5, 1.0, 2.0)
    specular_scales: tuple[float, ...] = (0.0, 1.0, 2.0)
    width: int = 256


#: Mitsuba variants the target stage may use ("auto": LLVM when a usable libLLVM is found)
MITSUBA_VARIANTS = ("auto", "scalar_rgb", "llvm_ad_rgb")


@dataclass(frozen=True)
class TargetSettings(Settings):
    """Settings of the target stage (config section ``target``, overridable per mesh): ground-truth
    image targets path-traced by Mitsuba 3 for ``guidance: image`` with ``target_renderer:
    mitsuba``. The material is the cell's ``optimize.target_material`` (as Mitsuba's principled
    BSDF with textures and a normal map); the light is an environment map."""

    section = "target"
    #: environment: builtin:sun_sky (a sun disc and a clear sky) or any .hdr/.exr path
    environment: str = "builtin:sun_sky"
    #: rows of a procedural environment (files keep their size); columns = 2 x rows
    environment_height: int = 512
    #: samples per pixel of the training views' targets and of the held-out metric views
    spp: int = 32
    metric_spp: int = 256
    #: longest light path (vertices after the camera): 1 = emitters only, 2 = direct light only
    max_depth: int = 8
    #: texture size of the ground-truth material and normal map
    texture_size: int = 1024
    #: steepest slope of the normal map's bumps (0 = no normal map)
    bump_slope: float = 0.3
    #: the truth's shading normals on the full-resolution mesh (SHADING_NORMALS): "smooth" (vertex
    #: normals, edges sharper than crease_angle_deg kept: the object the mesh approximates) or
    #: "flat" (faceted, as TANGO shades)
    shading_normals: str = "smooth"
    crease_angle_deg: float = 60.0
    #: Mitsuba variant: auto | scalar_rgb | llvm_ad_rgb
    variant: str = "auto"
    seed: int = 0
    #: environments the metric views are also rendered under (at metric_spp), the ground truth
    #: the relight stage grades the recovered field against (builtin:<name> or an .hdr/.exr path);
    #: empty: relighting is not graded
    relight_environments: tuple[str, ...] = ("builtin:sunset",)

    def __post_init__(self) -> None:
        problems = []
        for name in ("spp", "metric_spp"):
            value = getattr(self, name)
            if value < 2 or value % 2:
                problems.append(f"{name} must be an even number >= 2 (two halves measure the noise), got {value}")
        if self.max_depth < 2 and self.max_depth != -1:
            problems.append(f"max_depth must be >= 2 (or -1: unlimited), got {self.max_depth}")
        for env in self.relight_environments:
            problems += environment_problems("relight_environments", env)
        if len(set(self.relight_environments)) != len(self.relight_environments):
            problems.append(f"relight_environments lists an environment twice: {list(self.relight_environments)}")
        if not 16 <= self.texture_size <= 8192:
            problems.append(f"texture_size must be in [16, 8192], got {self.texture_size}")
        if not 0.0 <= self.bump_slope <= 2.0:
            problems.append(f"bump_slope must be in [0, 2], got {self.bump_slope}")
        if self.shading_normals not in SHADING_NORMALS:
            problems.append(f"shading_normals must be one of {', '.join(SHADING_NORMALS)}, got {self.shading_normals!r}")
        if not 0.0 <= self.crease_angle_deg <= 180.0:
            problems.append(f"crease_angle_deg must be in [0, 180], got {self.crease_angle_deg}")
        if not 16 <= self.environment_height <= 8192:
            problems.append(f"environment_height must be in [16, 8192], got {self.environment_height}")
        if self.variant not in MITSUBA_VARIANTS:
            problems.append(f"variant must be one of {MITSUBA_VARIANTS}, got {self.variant!r}")
        if not self.environment.strip():
            problems.append("environment must name builtin:<name> or a .hdr/.exr file")
        if self.environment.startswith("builtin:") and self.environment[8:] not in PROCEDURAL_ENVMAPS:
            problems.append(f"environment {self.environment!r}: choose builtin:<{'|'.join(PROCEDURAL_ENVMAPS)}> or a file")
        if problems:
            raise ConfigError("target: " + "; ".join(problems))


@dataclass(frozen=True, kw_only=True)
class MetricsSettings(ClipChoice, Settings):
    """Settings of the metrics stage (config section ``metrics``)."""

    section = "metrics"
    #: compute the CLIP-based metrics (needs weights, or clip_tiny_test)
    clip: bool = True
    #: the independent evaluation model (open_clip name, pretrained tag or local checkpoint)
    clip_model: str = "ViT-B-16"
    clip_pretrained: str = "openai"
    clip_checkpoint: str | None = None
    clip_tiny_test: bool = False
    background: str = "white"


#: asset formats the Blender round trip imports, and the light transport of its Cycles renders
ROUNDTRIP_FORMATS = ("glb", "usdz")
ROUNDTRIP_TRANSPORTS = ("direct_unshadowed", "full")


@dataclass(frozen=True, kw_only=True)
class RoundtripSettings(Settings):
    """Settings of the roundtrip stage (config section ``roundtrip``): the exported assets
    imported into Blender and rendered with Cycles under the learned light from the evaluation
    views, against our render of the trained field (the ``blender`` extra; off by default, the
    main job never needs Blender)."""

    section = "roundtrip"
    enabled: bool = False
    #: which exported files to import and render
    formats: tuple[str, ...] = ROUNDTRIP_FORMATS
    #: evaluation views rendered, evenly spread over the ray cache's (0 = all of them)
    views: int = 8
    #: Cycles samples per pixel, in two halves with different seeds (their difference is the noise)
    spp: int = 64
    #: direct_unshadowed: light straight from the world, no self-shadowing (what our closed-form
    #: renderer models, so the figure measures the asset); full: path tracing (shadows, bounces)
    transport: str = "direct_unshadowed"
    #: also render the GLB's diffuse and specular lobes alone (two more Blender processes, about
    #: 7 s each on a 2-core CPU), which split the GLB's gap between the BRDF models
    split_lobes: bool = True
    seed: int = 0
    #: longest a Blender job may run (seconds)
    timeout_s: float = 3600.0

    def __post_init__(self) -> None:
        problems = []
        bad = [f for f in self.formats if f not in ROUNDTRIP_FORMATS]
        if bad or not self.formats:
            problems.append(f"formats must be a non-empty list of {ROUNDTRIP_FORMATS}, got {list(self.formats)}")
        if self.views < 0:
            problems.append(f"views must be >= 0 (0 = all), got {self.views}")
        if self.spp < 2 or self.spp % 2:
            problems.append(f"spp must be an even number >= 2 (two halves measure the noise), got {self.spp}")
        if self.transport not in ROUNDTRIP_TRANSPORTS:
            problems.append(f"transport must be one of {ROUNDTRIP_TRANSPORTS}, got {self.transport!r}")
        if not self.timeout_s > 0:
            problems.append(f"timeout_s must be > 0, got {self.timeout_s}")
        if problems:
            raise ConfigError("roundtrip: " + "; ".join(problems))


@dataclass(frozen=True, kw_only=True)
class LodSettings(Settings):
    """Settings of the lod stage (config section ``lod``): levels of detail for artists. The field
    trained on the traced mesh is baked onto decimated versions of that mesh (a high-to-low bake:
    each texel of a level looks along its normal for the traced surface and takes the field's
    material and normal there), and every level is exported on its own and in one USD (variant set
    ``LOD``) and one GLB (``MSFT_lod``). Off by default."""

    section = "lod"
    enabled: bool = False
    #: face fractions of the traced mesh, one level each (lod1, lod2, ...), decreasing, in (0, 1)
    levels: tuple[float, ...] = (0.5, 0.1, 0.02)
    #: texture width of every level; null: the full bake's width times the square root of the
    #: level's face fraction, to the nearest power of two (ties up), at least min_texture_size (a
    #: level is first shown at that fraction of the screen area the full mesh switches at, see
    #: full_coverage, so there its texels per screen pixel are about the full asset's)
    texture_size: int | None = None
    min_texture_size: int = 64
    #: how far a texel's ray looks for the traced surface, in Hausdorff distances between the
    #: level and the traced mesh (both directions along the level's normal)
    cage: float = 2.0
    #: fewest faces of a level (a level below it is refused)
    min_faces: int = 8
    #: glTF MSFT_lod switching: a reference screen coverage (share of the screen the object
    #: covers); level k takes over below ``full_coverage * levels[k-1]``, where it has the same
    #: triangles per screen area as the full mesh at full_coverage (and more while it is larger)
    full_coverage: float = 0.5

    def __post_init__(self) -> None:
        problems = []
        lv = list(self.levels)
        if not lv or any(not 0.0 < f < 1.0 for f in lv) or any(a <= b for a, b in zip(lv, lv[1:], strict=False)):
            problems.append(f"levels must be face fractions in (0, 1), strictly decreasing, got {lv}")
        if self.texture_size is not None and not 16 <= self.texture_size <= 16384:
            problems.append(f"texture_size must be in [16, 16384] or null, got {self.texture_size}")
        if not 16 <= self.min_texture_size <= 16384:
            problems.append(f"min_texture_size must be in [16, 16384], got {self.min_texture_size}")
        if not self.cage > 0:
            problems.append(f"cage must be > 0, got {self.cage}")
        if self.min_faces < 4:
            problems.append(f"min_faces must be >= 4, got {self.min_faces}")
        if not 0.0 < self.full_coverage <= 1.0:
            problems.append(f"full_coverage must be in (0, 1], got {self.full_coverage}")
        if problems:
            raise ConfigError("lod: " + "; ".join(problems))

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
    """Settings of the report stages (config section ``report``; one per experiment): which
    variant the others are compared with, which variants are ablations, and the HTML form."""

    section = "report"
    #: the variant the others are measured against (speed/accuracy factors, ablation deltas);
    #: null: the experiment's first variant
    reference: str | None = None
    #: the ablation variants (each removes something from the reference); null: every variant
    #: whose settings differ from the reference only by switching components off
    #: (:data:`ABLATION_SWITCHES`), seeds aside
    ablations: tuple[str, ...] | None = None
    #: one self-contained index.html (images and models inlined; for small grids) instead of a
    #: folder with one page per cell and its assets beside it
    single_file: bool = False
    #: panels per figure file of the small-multiple plots (a larger grid is split over files)
    panels_per_figure: int = 36
    #: width in pixels of the index's thumbnails
    thumbnail_size: int = 128

    def __post_init__(self) -> None:
        problems = []
        if self.panels_per_figure < 1:
            problems.append(f"panels_per_figure must be >= 1, got {self.panels_per_figure}")
        if not 32 <= self.thumbnail_size <= 512:
            problems.append(f"thumbnail_size must be in [32, 512], got {self.thumbnail_size}")
        if self.ablations is not None and self.reference is not None and self.reference in self.ablations:
            problems.append(f"the reference variant {self.reference!r} cannot be one of the ablations")
        if problems:
            raise ConfigError("report: " + "; ".join(problems))


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
