"""Ground-truth image targets path-traced by Mitsuba 3 through the ray cache's own cameras.

The scene, all of it rendered by Mitsuba (nobody here wrote its light transport or its BSDF):

* **geometry**: the full-resolution mesh (the normalised one, also for a decimated cell: the truth
  is the object, not its approximation), shaded with smooth vertex normals that keep creases
  (``target.shading_normals``, :mod:`stages.geometry.normals`) or flat, with an xatlas texture
  atlas (:mod:`stages.geometry.atlas`);
* **material**: Mitsuba's ``principled`` BSDF (GGX microfacets, Disney diffuse, dielectric or
  metallic Fresnel) wrapped in ``normalmap`` and ``twosided``, with textures for base colour,
  roughness and metallic, baked from the procedural material ``kind``
  (:func:`principled_material`), and a tangent-space normal map of procedural bumps
  (:func:`bumped_normals`);
* **light**: an environment map (by default ``builtin:sun_sky``, a sun disc and a clear sky, which
  no sum of SG lobes represents), rotated into Mitsuba's convention by :data:`ENV_TO_WORLD`;
* **transport**: the ``path`` integrator (shadows and interreflection up to ``max_depth``), the
  environment hidden from the camera, an RGBA film whose alpha is each pixel's covered fraction.

Each cached view is rendered twice with ``spp / 2`` samples and different seeds: the mean is the
target and half the squared difference of the two (in sRGB) estimates the target's own noise.
Per cached hit the target keeps the *unpremultiplied* radiance (pixel radiance / alpha) and the
coverage, so training composes it exactly as it composes the model's renders, and metrics count
only fully covered object pixels.

The material's ground truth in TANGO's terms (:func:`tango_equivalent`: diffuse albedo
``base (1 - metallic)``, specular colour ``F0``, roughness) is sampled where each hit's ray of the
metric views meets the rendered mesh, from the same textures Mitsuba reads, for the
material-error figures.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
import torch

from ..config.sections import TargetSettings
from ..geometry.atlas import dilate, rasterize_atlas, sample_bilinear, unwrap
from ..geometry.meshio import TriMesh
from ..geometry.normals import NormalSpec, interpolate_normals, perpendicular
from ..geometry.probes import probe_sphere
from ..geometry.raycache import RayCache
from ..geometry.tracing import EmbreeTracer
from ..model.procedural import procedural_material
from ..render.color import srgb_encode
from ..render.envmap import load_env, radiant_energy
from .mitsuba import choose_variant, import_mitsuba, locate_libllvm, sensor

log = logging.getLogger(__name__)

#: Mitsuba's environment map looks up ``u = atan2(x, -z) / 2 pi``, ``v = acos(y) / pi`` in its local
#: frame; ours has column azimuth ``a`` at ``(cos a, y, sin a)``. This to-world rotation makes the
#: two agree (checked in tests/reference by evaluating Mitsuba's emitter in given directions).
ENV_TO_WORLD = np.array([[0.0, 0.0, -1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


def mitsuba_rows(env: np.ndarray) -> np.ndarray:
    """Our equirectangular ``env (H, W, 3)`` (row ``i`` centred at polar angle ``pi (i + 0.5) / H``)
    resampled to the rows Mitsuba's envmap reads (row ``i`` *at* ``pi i / (H - 1)``, the poles on
    the first and last rows; its columns are centred like ours): linear in the polar angle,
    clamped at the poles. Measured in tests/reference against Mitsuba's own lookups."""
    h = env.shape[0]
    src = np.arange(h) / (h - 1) * h - 0.5  # fractional source row of each output row
    lo = np.clip(np.floor(src).astype(int), 0, h - 1)
    hi = np.clip(lo + 1, 0, h - 1)
    f = np.clip(src - np.floor(src), 0.0, 1.0)[:, None, None]
    f = np.where((src < 0)[:, None, None], 0.0, f)
    return (env[lo] * (1 - f) + env[hi] * f).astype(np.float32)


#: Mitsuba's principled ``specular`` sets a dielectric's normal-incidence Fresnel to ``0.08 specular``
PRINCIPLED_F0_PER_SPECULAR = 0.08
#: a procedural material whose mean specular colour exceeds this is made a metal
METAL_F0 = 0.2
#: the bumps of the normal map: wave vectors (radians per unit length) of three plane waves
BUMP_WAVES = np.array([[23.0, 7.0, -4.0], [-5.0, 19.0, 13.0], [9.0, -6.0, 27.0]])
BUMP_PHASES = np.array([0.3, 1.7, 4.1])


@dataclass(frozen=True)
class PrincipledMaps:
    """Mitsuba principled parameters per point: ``base_color (N, 3)`` linear, ``metallic (N, 1)``,
    ``roughness (N, 1)``, and the dielectric ``specular`` level (a scalar in Mitsuba)."""

    base_color: np.ndarray
    metallic: np.ndarray
    roughness: np.ndarray
    specular: float


def principled_material(kind: str, points: np.ndarray) -> PrincipledMaps:
    """The procedural material ``kind`` (:func:`~stages.model.procedural.procedural_material`) as
    principled parameters at ``points (N, 3)``: a metal where its specular colour is bright
    (base colour = that colour, metallic 1), else a dielectric (base colour = its albedo, the
    specular level from its mean ``F0``)."""
    m = procedural_material(kind, torch.from_numpy(np.asarray(points, np.float64)))
    albedo, f0, rough = (t.numpy() for t in (m.albedo, m.specular, m.roughness))
    metal = (f0.mean(1, keepdims=True) > METAL_F0).astype(np.float64)
    dielectric_f0 = f0[metal[:, 0] == 0].mean() if (metal == 0).any() else 0.04
    level = float(np.clip(dielectric_f0 / PRINCIPLED_F0_PER_SPECULAR, 0.0, 1.0))
    return PrincipledMaps(metal * f0 + (1 - metal) * albedo, metal, rough, level)


def tango_equivalent(base: np.ndarray, metallic: np.ndarray, roughness: np.ndarray, specular: float) -> dict:
    """TANGO's parameters closest to principled ones: diffuse ``albedo = base (1 - metallic)``,
    specular colour ``F0 = lerp(0.08 specular, base, metallic)``, the same roughness (both models
    use ``alpha = roughness^2``). Arrays ``(N, C)``."""
    f0 = (1 - metallic) * PRINCIPLED_F0_PER_SPECULAR * specular + metallic * base
    return {"albedo": base * (1 - metallic), "specular": f0, "roughness": roughness}


def bumped_normals(points: np.ndarray, normals: np.ndarray, slope: float) -> np.ndarray:
    """Unit normals ``(N, 3)`` of the height field ``h(p) = sum_i a sin(k_i . p + phi_i)`` on a
    surface with unit ``normals``: ``normalize(n - (grad h - (grad h . n) n))``, the amplitude ``a``
    chosen so that the steepest possible slope ``|grad h|`` is ``slope``."""
    k = BUMP_WAVES
    a = slope / np.linalg.norm(k, axis=1).sum()
    grad = (a * np.cos(points @ k.T + BUMP_PHASES)) @ k  # (N, 3)
    tangential = grad - (grad * normals).sum(1, keepdims=True) * normals
    bent = normals - tangential
    return bent / np.linalg.norm(bent, axis=1, keepdims=True)


def uv_dp_du(mesh: TriMesh, uv: np.ndarray) -> np.ndarray:
    """``dp/du (F, 3)`` of each face from its positions and atlas ``uv (F, 3, 2)`` (Mitsuba's
    ``si.dp_du``; zero where the UV triangle is degenerate)."""
    p = mesh.vertices[mesh.faces].astype(np.float64)
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    d1, d2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    ok = np.abs(det) > 1e-20
    return np.where(ok[:, None], (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) / np.where(ok, det, 1.0)[:, None], 0.0)


def mitsuba_frames(dp_du: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The shading frame Mitsuba's ``normalmap`` uses at points with unit shading normal ``n``
    (the face normal of a flat mesh, the interpolated vertex normal of a smooth one) and ``dp_du``:
    ``s`` = ``dp/du`` made orthogonal to ``n`` and normalised, ``t = n x s`` (whatever the UV
    handedness; measured in tests/reference). ``(N, 3)`` each."""
    s = dp_du - (dp_du * n).sum(1, keepdims=True) * n
    norm = np.linalg.norm(s, axis=1, keepdims=True)
    s = np.where(norm > 1e-20, s, perpendicular(n))
    s /= np.linalg.norm(s, axis=1, keepdims=True)
    return s, np.cross(n, s), n


@dataclass
class GroundTruth:
    """The scene's material as textures ``(S, S, C)`` (linear; row 0 at ``v = 0``, as Mitsuba and
    glTF read them), the atlas ``uv (F, 3, 2)``, each face's ``dp_du (F, 3)`` and the shading
    ``corner_normals (F, 3, 3)`` Mitsuba interpolates (flat: the face normal three times)."""

    uv: np.ndarray
    base_color: np.ndarray
    metallic: np.ndarray
    roughness: np.ndarray
    normal: np.ndarray  # tangent space, in [-1, 1]
    specular: float
    dp_du: np.ndarray
    corner_normals: np.ndarray

    def shading_normals(self, face: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """Unit shading normals ``(N, 3)`` at hits, as Mitsuba interpolates them."""
        return interpolate_normals(self.corner_normals, face, bary, self.corner_normals[face, 0])

    def at_hits(self, face: np.ndarray, bary: np.ndarray, back: np.ndarray) -> dict:
        """TANGO-equivalent maps, glTF's base colour and metallic, and the world shading normal at hits (``face (N,)``,
        ``bary (N, 2)``, ``back (N,) bool``: seen from behind the shading normal, where the
        viewer sees :func:`seen_normal`). Sampled bilinearly, as Mitsuba does."""
        tri = self.uv[face]
        uv = tri[:, 0] + bary[:, :1] * (tri[:, 1] - tri[:, 0]) + bary[:, 1:] * (tri[:, 2] - tri[:, 0])
        base, metallic = sample_bilinear(self.base_color, uv), sample_bilinear(self.metallic, uv)
        out = tango_equivalent(base, metallic, sample_bilinear(self.roughness, uv), self.specular)
        out["base"], out["metallic"] = base, metallic  # glTF's terms (optimize.brdf: gltf)
        ts = sample_bilinear(self.normal, uv)
        s, t, n = mitsuba_frames(self.dp_du[face], self.shading_normals(face, bary))
        world = ts[:, :1] * s + ts[:, 1:2] * t + ts[:, 2:3] * n
        world /= np.linalg.norm(world, axis=1, keepdims=True)
        out["normal"] = seen_normal(world, n, back)
        return out


def seen_normal(world: np.ndarray, n: np.ndarray, back: np.ndarray) -> np.ndarray:
    """The normal a viewer sees of ``twosided(normalmap(...))`` -> ``(N, 3)``: the perturbed
    ``world (N, 3)`` normal where ``back (N,)`` is false, and seen from behind the shading normal
    ``n (N, 3)`` its mirror image through the shading plane, ``world - 2 (world . n) n`` (``twosided``
    flips the directions' component along ``n`` before the normal map perturbs the frame), which
    faces the viewer. Until 2026-11-25 the negated mirror image was used, which faces away: every
    back-seen hit of an open mesh got a normal 175 degrees off in the metrics and the ceilings
    (tested against Mitsuba in tests/reference/test_mitsuba_targets.py)."""
    mirrored = world - 2.0 * (world * n).sum(1, keepdims=True) * n
    return np.where(back[:, None], mirrored, world)


def ground_truth(mesh: TriMesh, kind: str, settings: TargetSettings) -> GroundTruth:
    """Unwrap ``mesh`` and bake the procedural material ``kind`` and its bumps (around the
    shading normals of ``settings.shading_normals``) into textures."""
    size = settings.texture_size
    atlas = unwrap(mesh, size, padding=4)
    face, bary = rasterize_atlas(atlas.uv, size)
    filled = face >= 0
    fi = face[filled].astype(np.int64)
    b = bary[filled].astype(np.float64)
    tri = mesh.vertices[mesh.faces[fi]].astype(np.float64)
    points = tri[:, 0] + b[:, :1] * (tri[:, 1] - tri[:, 0]) + b[:, 1:] * (tri[:, 2] - tri[:, 0])
    mat = principled_material(kind, points)
    dp_du = uv_dp_du(mesh, atlas.uv)
    corners = target_normals(settings).corner_normals(mesh.vertices, mesh.faces)
    shading = interpolate_normals(corners, fi, b, corners[fi, 0])
    s, t, n = mitsuba_frames(dp_du[fi], shading)
    bent = bumped_normals(points, n, settings.bump_slope)
    local = np.stack([(bent * s).sum(1), (bent * t).sum(1), (bent * n).sum(1)], axis=1)

    def texture(values: np.ndarray, empty: float) -> np.ndarray:
        img = np.full((size, size, values.shape[1]), empty)
        img[filled] = values
        return dilate(img, filled, 8)

    normal = texture(local, 0.0)
    normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-12)
    return GroundTruth(
        atlas.uv,
        texture(mat.base_color, 0.0),
        texture(mat.metallic, 0.0),
        texture(mat.roughness, 1.0),
        normal,
        mat.specular,
        dp_du,
        corners,
    )


def target_normals(settings: TargetSettings) -> NormalSpec:
    """The truth's shading normals (``target.shading_normals``, ``target.crease_angle_deg``)."""
    return NormalSpec(settings.shading_normals, settings.crease_angle_deg)


def _mesh(mi, mesh: TriMesh, uv: np.ndarray, bsdf, corner_normals: np.ndarray | None = None):
    """A Mitsuba mesh with one vertex per face corner, the atlas's texcoords, and flat normals or,
    given ``corner_normals (F, 3, 3)``, those per corner (Mitsuba interpolates them). Works in
    every variant: the buffers are built with the types the mesh itself holds (``drjit.scalar.ArrayXf``
    in ``scalar_rgb``, where ``mi.Float`` is a Python float; ``drjit.llvm.ad.Float`` in ``llvm_ad_rgb``)."""
    corners = mesh.vertices[mesh.faces].reshape(-1, 3).astype(np.float32)
    nf = len(mesh.faces)
    smooth = corner_normals is not None
    m = mi.Mesh("target", 3 * nf, nf, has_vertex_normals=smooth, has_vertex_texcoords=True)
    params = mi.traverse(m)
    buffers = {
        "vertex_positions": corners.ravel(),
        "faces": np.arange(3 * nf, dtype=np.uint32),
        "vertex_texcoords": uv.reshape(-1, 2).astype(np.float32).ravel(),
    }
    if smooth:
        buffers["vertex_normals"] = corner_normals.reshape(-1).astype(np.float32)
    for key, values in buffers.items():
        params[key] = type(params[key])(np.ascontiguousarray(values))
    params.update()
    m.set_bsdf(bsdf)
    return m


def _bitmap(mi, img: np.ndarray) -> dict:
    return {
        "type": "bitmap",
        "bitmap": mi.Bitmap(np.ascontiguousarray(img.astype(np.float32))),
        "raw": True,
        "filter_type": "bilinear",
    }


def scene_dict(mi, mesh: TriMesh, gt: GroundTruth, env: np.ndarray, max_depth: int, smooth: bool) -> dict:
    """The Mitsuba scene description (see the module docstring); sensors are added per view."""
    principled = {
        "type": "principled",
        "base_color": _bitmap(mi, gt.base_color),
        "roughness": _bitmap(mi, gt.roughness),
        "metallic": _bitmap(mi, gt.metallic),
        "specular": float(gt.specular),
    }
    bsdf = {
        "type": "twosided",
        "material": {"type": "normalmap", "normalmap": _bitmap(mi, 0.5 * gt.normal + 0.5), "bsdf": principled},
    }
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": int(max_depth), "hide_emitters": True},
        "object": _mesh(mi, mesh, gt.uv, mi.load_dict(bsdf), gt.corner_normals if smooth else None),
        "light": {
            "type": "envmap",
            "bitmap": mi.Bitmap(np.ascontiguousarray(mitsuba_rows(env))),
            "to_world": mi.ScalarTransform4f(ENV_TO_WORLD.tolist()),
        },
    }


@dataclass
class ViewTargets:
    """One cache's targets: per hit ``radiance (N, 3) float32`` (unpremultiplied, linear) and
    ``coverage (N,) float32`` (Mitsuba's alpha at the hit's pixel); per view the object-pixel
    noise ``noise_mse (V,)`` (sRGB, of the mean of the two halves) and ``pixels (V,)``."""

    radiance: np.ndarray
    coverage: np.ndarray
    noise_mse: np.ndarray
    pixels: np.ndarray
    seconds: float

    @property
    def noise_psnr_db(self) -> float:
        """PSNR of the targets against their noise-free expectation, object pixels, sRGB."""
        mse = float((self.noise_mse * self.pixels).sum() / max(self.pixels.sum(), 1))
        return float("inf") if mse <= 0 else float(10.0 * np.log10(1.0 / mse))


class TargetRenderer:
    """A loaded Mitsuba scene that renders views of ray caches (one sensor, moved per view)."""

    def __init__(
        self,
        mesh: TriMesh,
        kind: str,
        settings: TargetSettings,
        environment: str | None = None,
        truth: GroundTruth | None = None,
    ) -> None:
        """The scene of ``mesh`` in the procedural material ``kind`` under ``environment`` (default
        ``settings.environment``); ``truth``: the textures of another renderer of the same mesh and
        material, reused instead of unwrapping and baking again (the relit judges)."""
        self.settings = settings
        self.variant = choose_variant(settings.variant)
        self.mi = import_mitsuba(self.variant)
        lib = locate_libllvm() if self.variant.startswith("llvm") else None
        #: the libLLVM an LLVM variant runs on (its description), None in scalar_rgb
        self.libllvm = lib.describe() if lib is not None else None
        t0 = time.perf_counter()
        self.truth = truth if truth is not None else ground_truth(mesh, kind, settings)
        self.seconds_textures = time.perf_counter() - t0
        self.environment = environment if environment is not None else settings.environment
        self.env = load_env(self.environment, settings.environment_height)
        self.env_energy = radiant_energy(self.env)
        smooth = settings.shading_normals == "smooth"
        self.scene = self.mi.load_dict(scene_dict(self.mi, mesh, self.truth, self.env, settings.max_depth, smooth))
        self.mesh = mesh

    def sensor_dict(self, c2w: np.ndarray, fov_deg: float, width: int, spp: int) -> dict:
        """Our camera as a Mitsuba sensor with ``spp`` random samples per pixel and an RGBA film."""
        return sensor(c2w, fov_deg, width, spp, centred=False, alpha=True, mi=self.mi)

    def render(self, c2w: np.ndarray, fov_deg: float, width: int, spp: int, seed: int) -> np.ndarray:
        """``(W, W, 4)`` float32: linear RGB (premultiplied by coverage) and alpha."""
        mi = self.mi
        cam = mi.load_dict(self.sensor_dict(c2w, fov_deg, width, spp))
        return np.array(mi.render(self.scene, sensor=cam, seed=int(seed), spp=int(spp)), dtype=np.float32)

    def render_cache(self, cache: RayCache, spp: int, seed: int) -> ViewTargets:
        """Targets of every view of ``cache`` (two half renders per view, see the module docstring)."""
        t0 = time.perf_counter()
        radiance, coverage, noise, pixels = [], [], [], []
        for i in range(len(cache)):
            hits = cache.view(i)
            halves = [self.render(hits.c2w, cache.fov_deg, cache.width, spp // 2, seed + 2 * (i * 7919) + h) for h in (0, 1)]
            img = 0.5 * (halves[0] + halves[1])
            flat = img.reshape(-1, 4)[hits.pixel]
            alpha = flat[:, 3]
            rgb = np.where(alpha[:, None] > 0, flat[:, :3] / np.maximum(alpha[:, None], 1e-8), 0.0)
            radiance.append(rgb.astype(np.float32))
            coverage.append(alpha.astype(np.float32))
            full = alpha >= ALPHA_FULL
            a, b = (srgb_encode(np.clip(h.reshape(-1, 4)[hits.pixel][full, :3], 0, None)) for h in halves)
            noise.append(float(((a - b) ** 2).mean() / 4.0) if full.any() else 0.0)
            pixels.append(int(full.sum()))
            log.info("target view %d/%d: %d hits, %.1f s so far", i + 1, len(cache), len(hits.pixel), time.perf_counter() - t0)
        return ViewTargets(
            np.concatenate(radiance) if radiance else np.zeros((0, 3), np.float32),
            np.concatenate(coverage) if coverage else np.zeros(0, np.float32),
            np.array(noise),
            np.array(pixels),
            time.perf_counter() - t0,
        )

    def truth_at_hits(self, cache: RayCache) -> tuple[dict, np.ndarray]:
        """:func:`truth_at_cache` of this scene's mesh and material."""
        return truth_at_cache(self.truth, self.mesh, cache)


def truth_at_cache(truth: GroundTruth, mesh: TriMesh, cache: RayCache) -> tuple[dict, np.ndarray]:
    """The TANGO-equivalent material and world shading normal (:meth:`GroundTruth.at_hits`, the
    normal the viewer sees: :func:`seen_normal` where the hit is seen from behind) where each of
    ``cache``'s rays meets ``mesh`` (which may be finer than the cache's: the full-resolution mesh
    of a decimated one), and ``(N,) bool``: whether it meets it at all (the truth of a miss is
    zero)."""
    tracer = EmbreeTracer(mesh)
    face, bary, direction = [], [], []
    for i in range(len(cache)):
        h = cache.view(i)
        origins = np.broadcast_to(h.c2w[:3, 3], h.direction.shape).astype(np.float64)
        hits = tracer.trace(origins, h.direction.astype(np.float64))
        face.append(hits.face)
        bary.append(hits.bary)
        direction.append(h.direction.astype(np.float64))
    face, bary, direction = np.concatenate(face), np.concatenate(bary).astype(np.float64), np.concatenate(direction)
    met = face >= 0
    f = np.where(met, face, 0)
    back = (truth.shading_normals(f, bary) * direction).sum(1) > 0
    values = truth.at_hits(f, bary, back)
    return {k: np.where(met[:, None], v, 0.0) for k, v in values.items()}, met


def truth_at_senders(truth: GroundTruth, fine: TriMesh, mesh: TriMesh) -> dict:
    """The true material and shading normal at the centroid of each face side of ``mesh`` (the
    senders of a bounce, :class:`~stages.model.bounce.FaceSides`: row ``2 f`` the front, ``2 f + 1``
    the back, each seen from its side), found on ``fine`` (the rendered mesh, which may be finer)
    along the face's normal; a face whose centroid is not on ``fine`` within a hundredth of the
    mesh's size, or without an area, gets zeros. Keys as :meth:`GroundTruth.at_hits`', each
    ``(2 F, C)``."""
    n = mesh.face_normals
    c = mesh.vertices[mesh.faces].mean(axis=1)
    reach = 1e-2 * float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))
    tracer = EmbreeTracer(fine)
    down = tracer.trace(c + reach * n, -n)
    up = tracer.trace(c - reach * n, n)
    near_down = (down.face >= 0) & (down.depth <= 2.0 * reach)
    face = np.where(near_down, down.face, up.face)
    bary = np.where(near_down[:, None], down.bary, up.bary).astype(np.float64)
    met = (face >= 0) & (np.linalg.norm(n, axis=1) > 0.5) & (near_down | ((up.face >= 0) & (up.depth <= 2.0 * reach)))
    f = np.where(met, face, 0)
    front, back = truth.at_hits(f, bary, np.zeros(len(f), bool)), truth.at_hits(f, bary, np.ones(len(f), bool))
    out = {}
    for k in front:
        both = np.stack([front[k], back[k]], axis=1).reshape(2 * len(f), -1)
        out[k] = np.where(np.repeat(met, 2)[:, None], both, 0.0).astype(np.float32)
    return out


#: a pixel counts as an object pixel of the figures when Mitsuba's alpha says it is fully covered
ALPHA_FULL = 0.999


@dataclass(frozen=True)
class RenderProbe:
    """What :func:`probe` measured: the variant, the seconds of the first render (scene set-up and,
    in an LLVM variant, the kernels' compilation) and the rate of the second, in samples per second."""

    variant: str
    first_seconds: float
    samples_per_second: float
    width: int
    spp: int


def target_samples(raycache, target: TargetSettings) -> dict[str, int]:
    """The Mitsuba samples one target job path-traces, by kind: ``training`` (every training view
    at ``target.spp``), ``metric`` (every held-out metric view at ``target.metric_spp``) and
    ``relit`` (the metric views again under each of ``target.relight_environments``, at
    ``metric_spp``: the relit truths), whole images, as :meth:`TargetRenderer.render_cache` and the
    target stage render them. ``raycache``: the mesh's :class:`~stages.config.sections.RaycacheSettings`."""
    metric_views = raycache.metrics_azimuths * len(raycache.metrics_elevations_deg)
    metric = metric_views * raycache.metrics_resolution**2 * target.metric_spp
    return {
        "training": raycache.views * raycache.resolution**2 * target.spp,
        "metric": metric,
        "relit": metric * len(target.relight_environments),
    }


def probe(settings: TargetSettings, width: int = 128, spp: int = 64) -> RenderProbe:
    """The smallest real use of the target renderer: the target stage's own scene (principled BSDF
    with textures and a normal map, the configured environment and transport) on the doctor's
    320-face probe sphere (:func:`stages.geometry.probes.probe_sphere`), rendered twice at
    ``width x width`` pixels and ``spp`` samples in the variant a run of ``settings`` uses
    (:func:`~stages.reference.mitsuba.choose_variant`). The sphere covers about 45% of the
    pixels, like an object in a target view, and the rate counts whole images, as the target
    stage does. The default size is large enough for the LLVM variant's rate to be its rate on
    whole target views (at 48 pixels and 32 samples it measured 2.5x slower, its fixed costs
    counted in), and the scene's textures and environment are the run's sizes (the material's
    texture lookups cost: a 64-texel probe read 1.3x the rate of the 1,024-texel scene). Raises
    what the renderer raises."""
    mesh = probe_sphere(2)
    c2w = np.eye(4)
    c2w[2, 3] = 2.0  # looking down -z at the origin
    t0 = time.perf_counter()
    renderer = TargetRenderer(mesh, "wood", settings)
    img = renderer.render(c2w, 60.0, width, spp, seed=0)
    first = time.perf_counter() - t0
    if not np.isfinite(img).all() or img[..., 3].max() <= 0:
        raise RuntimeError(f"Mitsuba ({renderer.variant}) rendered an empty or non-finite probe image")
    t1 = time.perf_counter()
    renderer.render(c2w, 60.0, width, spp, seed=1)
    rate = width * width * spp / max(time.perf_counter() - t1, 1e-9)
    return RenderProbe(renderer.variant, first, rate, width, spp)
