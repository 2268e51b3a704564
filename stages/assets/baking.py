"""Texture baking: xatlas charts, atlas rasterisation, tangent frames, the field evaluated at texel
centres, and the baked textures rendered back for the fidelity check.

1. xatlas charts and packs the (normalised, possibly decimated) mesh; face order is kept.
2. The atlas is rasterised in UV space with Embree (one ray per texel centre, cast at the flat
   UV-space triangles), so every covered texel knows its face and barycentrics, hence its 3D
   point and its face's frame.
3. The networks are evaluated at texel centres: base colour (diffuse albedo), roughness,
   specular colour and the predicted normal. The normal is stored in tangent space.
4. Empty texels are filled by dilation (so bilinear filtering and mip-maps do not bleed the
   background across seams), then the rest with the mean.
5. The learned light's environment (its SG lobes) is written as an equirectangular image
   (``light.exr`` and ``light.hdr``) and its suns as distant lights (the bake's ``meta.json``),
   which the exported assets carry as lights.
6. Fidelity: the baked asset (textures sampled bilinearly per pixel, as a viewer would) is
   rendered with the same SG renderer and light from the evaluation views and compared with the
   neural field's renders: PSNR over object pixels.

Conventions. Image row 0 is the top; texel ``(row, col)`` has centre ``u = (col + 0.5) / S``,
``v = (row + 0.5) / S`` (glTF's texture coordinates). USD's ``st = (u, 1 - v)``. The normal map's
frame is :class:`~stages.geometry.tangents.CornerFrames`: the field's shading normals per corner
(flat or smooth, ``optimize.shading_normals``) and MikkTSpace tangents, interpolated per pixel with
bitangent ``w (N x T)``, the frame glTF viewers and Blender rebuild from the exported normals and
tangents. The normal texture stores the unit ``c`` with ``normalize(c.x T + c.y B + c.z N)`` = the
predicted normal (+X right, +Y up: OpenGL/glTF/USD convention), written as ``(c + 1) / 2``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

from ..config.sections import BakeSettings, RaycacheSettings
from ..geometry.atlas import Atlas, dilate, rasterize_atlas, sample_bilinear, unwrap
from ..geometry.meshio import TriMesh
from ..geometry.normals import NormalSpec, interpolate_normals
from ..geometry.raycache import dequantize_bary
from ..geometry.tangents import CornerFrames, from_tangent_space, to_tangent_space
from ..geometry.tracing import EmbreeTracer
from ..geometry.uvlayout import face_tiles, wrapped_copies
from ..geometry.visibility import OcclusionSamples, fibonacci_directions
from ..model.field import shade_material
from ..model.networks import Material
from ..render import brdf as brdfs
from ..render.brdf import Brdf
from ..render.color import srgb_decode, srgb_encode, to_u8
from ..render.distant import DistantLight
from ..render.envmap import equirect_directions
from ..render.shading import face_viewer
from .layouts import KeptLayout


@dataclass
class BakeResult:
    """A bake: its ``atlas`` (UVs per face), the ``textures`` (uint8 ``(S, S, 3)`` images as
    written; a kept layout's first texture set), the frame, the share of texels covered, the
    light's environment image and ``distant`` lights (:func:`light_image`) and a kept layout's
    further texture ``sets`` (folder below ``textures/`` -> images, one per further material slot)."""

    atlas: Atlas
    textures: dict[str, np.ndarray]
    frames: CornerFrames
    coverage: float
    light_equirect: np.ndarray
    sets: dict[str, dict[str, np.ndarray]] = dataclasses.field(default_factory=dict)
    distant: list[DistantLight] = dataclasses.field(default_factory=list)


@dataclass
class AtlasTexels:
    """The covered texels of an atlas: ``filled (S, S) bool``, and per covered texel (row-major
    order) its ``face (M,)``, barycentrics ``bary (M, 2)`` (Embree's ``(u, v)``) and 3D ``points (M, 3)``."""

    atlas: Atlas
    filled: np.ndarray
    face: np.ndarray
    bary: np.ndarray
    points: np.ndarray


def atlas_texels(mesh: TriMesh, size: int, padding: int, max_chart_share: float | None = None) -> AtlasTexels:
    """Unwrap ``mesh`` into a ``size``-texel atlas (:func:`~stages.geometry.atlas.unwrap`) and
    locate every covered texel centre on it."""
    atlas = unwrap(mesh, size, padding, max_chart_share)
    face, bary = rasterize_atlas(atlas.uv, size)
    return locate_texels(mesh, atlas, face, bary)


def kept_texels(mesh: TriMesh, uv: np.ndarray, size: int, islands: int, faces: np.ndarray | None = None) -> AtlasTexels:
    """Locate every covered texel centre of the input's own layout ``uv (F, 3, 2)`` (per face of
    ``mesh``; every face in one tile, :func:`~stages.geometry.uvlayout.face_tiles`), or of the
    ``faces (F,) bool`` that share one texture set, on a ``size``-texel texture that repeats: each
    face is moved into the unit tile and its parts past an edge wrap round
    (:func:`~stages.geometry.uvlayout.wrapped_copies`); where faces are stacked, the texel takes
    one of them."""
    chosen = np.arange(len(uv)) if faces is None else np.flatnonzero(faces)
    sub = uv[chosen]
    tris, owner = wrapped_copies(sub - face_tiles(sub)[:, None, :])
    face, bary = rasterize_atlas(tris, size)
    face = np.where(face >= 0, chosen[owner[np.maximum(face, 0)]], -1)
    filled = face >= 0
    atlas = Atlas(uv.astype(np.float64), size, islands, float(filled.mean()))
    return locate_texels(mesh, atlas, face, bary)


def locate_texels(mesh: TriMesh, atlas: Atlas, face: np.ndarray, bary: np.ndarray) -> AtlasTexels:
    """The covered texels of ``atlas`` from the rasterised ``face (S, S)`` and ``bary (S, S, 2)``."""
    filled = face >= 0
    fi = face[filled].astype(np.int64)
    uvb = bary[filled].astype(np.float64)
    tri = mesh.vertices[mesh.faces[fi]]
    points = tri[:, 0] + uvb[:, :1] * (tri[:, 1] - tri[:, 0]) + uvb[:, 1:] * (tri[:, 2] - tri[:, 0])
    return AtlasTexels(atlas, filled, fi, uvb, points)


@torch.no_grad()
def evaluate_surface(
    field, points: np.ndarray, normals: np.ndarray, device="cpu", chunk: int = 65536
) -> tuple[dict[str, np.ndarray], Brdf | None]:
    """The field's material and predicted world normal at ``points (M, 3)`` with shading
    ``normals (M, 3)`` (float64 arrays), and the material's BRDF (None for no points): each
    channel the material has (:class:`~stages.model.networks.Material`'s fields: ``albedo,
    specular (M, 3)``, ``roughness (M, 1)``, the last two absent for a diffuse-only field, and for
    a field of glTF's BRDF what it was made of, ``base (M, 3)`` and ``metallic (M, 1)``: what was
    trained, baked as it is) and ``normal (M, 3)``."""
    out: dict[str, list] = {}
    brdf = None
    p_t = torch.from_numpy(points.astype(np.float32)).to(device)
    n_t = torch.from_numpy(normals.astype(np.float32)).to(device)
    for lo in range(0, len(p_t), chunk):
        mat, normal = field.surface(p_t[lo : lo + chunk], n_t[lo : lo + chunk])
        brdf = mat.brdf
        for f in dataclasses.fields(mat):
            if getattr(mat, f.name) is not None:
                out.setdefault(f.name, []).append(getattr(mat, f.name))
        out.setdefault("normal", []).append(normal)
    return {k: torch.cat(v).cpu().double().numpy() for k, v in out.items()}, brdf


def texture_images(
    texels: AtlasTexels,
    surface: dict[str, np.ndarray],
    tangent_normal: np.ndarray,
    dilation: int,
    brdf: Brdf,
    occlusion: np.ndarray | None = None,
) -> dict:
    """The four 8-bit texture images (see the module docstring) from the per-texel ``surface``
    (:func:`evaluate_surface`) of the BRDF ``brdf`` and the normal in tangent space, with empty
    texels dilated. Each of the BRDF's parameters goes to its texture (``brdf.texture_of``): the
    base colour, TANGO's diffuse albedo or glTF's base colour; the metallic-roughness texture's
    blue channel, glTF's metallic (0 for a BRDF without one); its red channel: the per-texel ambient
    ``occlusion (M,)`` (glTF's occlusion-roughness-metallic packing), or 1 without one;
    ``specular``: the F0 either way (for glTF's BRDF a preview of ``lerp(0.04, base, metallic)``;
    its assets do not read it)."""
    s = texels.atlas.size
    filled = texels.filled
    baked = {texture: name for name, texture in brdf.texture_of.items()}  # texture -> the parameter in it
    base = np.zeros((s, s, 3))
    base[filled] = surface[baked["albedo"]]
    spc = np.zeros((s, s, 3))
    rgh = np.ones((s, s, 1))
    metal = np.zeros((s, s, 1))
    occl = np.ones((s, s, 1))
    if occlusion is not None:
        occl[filled, 0] = occlusion
    if "specular" in surface:
        spc[filled] = surface["specular"]
        rgh[filled] = surface["roughness"]
    if "metallic" in baked:
        metal[filled] = surface[baked["metallic"]]
    nrm = np.zeros((s, s, 3))
    nrm[..., 2] = 1.0
    nrm[filled] = tangent_normal
    base, spc, rgh, metal, nrm, occl = (dilate(x, filled, dilation) for x in (base, spc, rgh, metal, nrm, occl))
    mr = np.concatenate([occl, rgh, metal], axis=-1)  # R occlusion (or 1), G rough, B metal
    return {
        "basecolor": to_u8(srgb_encode(base)),
        "metallic_roughness": to_u8(mr),
        "specular": to_u8(srgb_encode(spc)),
        "normal": to_u8(0.5 + 0.5 * nrm),
    }


def light_image(field, width: int, device="cpu") -> tuple[np.ndarray, list[DistantLight]]:
    """The field's learned light as an asset carries it: its environment (the SG lobes) as an
    equirectangular ``(width / 2, width, 3)`` float32 image, and its suns as distant lights
    (:meth:`~stages.render.light.Light.distant_lights`), which the image leaves out."""
    light = field.light()
    sky = light.environment()
    h = width // 2
    if sky is None:
        return np.zeros((h, width, 3), np.float32), light.distant_lights()
    dirs = equirect_directions(h, width).to(device)
    with torch.no_grad():
        env = sky.radiance(dirs.reshape(-1, 3))
    return env.reshape(h, width, 3).cpu().numpy().astype(np.float32), light.distant_lights()


def occlusion_decision(setting: str, field, cache) -> dict:
    """Whether the bake writes an ambient occlusion map (``bake.occlusion``) for ``field`` trained
    on a ray ``cache``: ``{"baked", "why", "directions"}``. ``auto``: where the field cast shadows
    (``optimize.shadows`` and a cache with visibility), so that its albedo holds none and a
    viewer's own ambient light needs the occlusion; a field trained without shadows painted them
    into its albedo, and an occlusion map would darken them twice. The directions are the cache's
    (``raycache.visibility_directions``), or that setting's default without visibility."""
    traced = int(cache.visibility_directions)
    directions = traced or RaycacheSettings().visibility_directions
    if setting != "auto":
        baked, why = setting == "on", f"bake.occlusion: {setting}"
    elif not field.shadows:
        baked, why = False, "auto: the field was trained without shadows (optimize.shadows: false)"
    elif not traced:
        baked, why = False, "auto: the ray cache holds no visibility (raycache.visibility)"
    else:
        baked, why = True, "auto: the field was trained with shadows"
    return {"baked": baked, "why": why, "directions": directions}


def occlusion_samples(mesh: TriMesh, decision: dict, settings: BakeSettings, seed: int = 0) -> OcclusionSamples | None:
    """The mesh's :class:`~stages.geometry.visibility.OcclusionSamples` when ``decision`` (from
    :func:`occlusion_decision`) bakes one, else None."""
    if not decision["baked"]:
        return None
    directions = fibonacci_directions(decision["directions"])
    return OcclusionSamples(mesh, EmbreeTracer(mesh), directions, settings.occlusion_samples, seed)


def bake_field(
    mesh: TriMesh,
    field,
    settings: BakeSettings,
    device="cpu",
    occlusion: OcclusionSamples | None = None,
    layout: KeptLayout | None = None,
) -> BakeResult:
    """Unwrap ``mesh`` (or take the input's own ``layout``, one bake per texture set), rasterise
    the atlas and evaluate ``field`` at every covered texel (and the ambient ``occlusion`` there,
    when given)."""
    size = settings.size_for(len(mesh.faces))
    env, distant = light_image(field, settings.light_width, device)
    if layout is None:
        texels = atlas_texels(mesh, size, settings.padding, settings.max_chart_share)
        frames = CornerFrames.build(mesh.vertices, mesh.faces, texels.atlas.uv, field.normals)
        textures = bake_texels(mesh, field, texels, frames, settings, device, occlusion, False)
        return BakeResult(texels.atlas, textures, frames, float(texels.filled.mean()), env, distant=distant)
    frames = layout.frames(mesh)
    face_set = layout.face_set
    baked, coverage = {}, []
    for k, ts in enumerate(layout.sets):
        texels = kept_texels(mesh, layout.uv, size, layout.check.islands, face_set == k)
        baked[ts.folder] = bake_texels(mesh, field, texels, frames, settings, device, occlusion, True)
        coverage.append(float(texels.filled.mean()))
    first = baked.pop("")
    atlas = Atlas(layout.uv.astype(np.float64), size, layout.check.islands, float(np.mean(coverage)))
    return BakeResult(atlas, first, frames, float(np.mean(coverage)), env, baked, distant)


def bake_texels(
    mesh: TriMesh,
    field,
    texels: AtlasTexels,
    frames: CornerFrames,
    settings: BakeSettings,
    device="cpu",
    occlusion: OcclusionSamples | None = None,
    own_frame: bool = False,
) -> dict[str, np.ndarray]:
    """The texture images of ``texels``: the field's material and normal there, written in
    ``frames``. ``own_frame``: the frame's normals are the input's (a kept layout), so the field
    reads the shading normals it was trained with instead."""
    t, b, n = frames.at(texels.face, texels.bary)
    if own_frame:
        normals = shading_normals(mesh, field.normals, texels.face, texels.bary)
    else:  # the frame's normals are the field's own
        normals = n / np.linalg.norm(n, axis=1, keepdims=True)
    surface, brdf = evaluate_surface(field, texels.points, normals, device)
    ao = None if occlusion is None else occlusion.at(texels.points, mesh.face_normals[texels.face])
    return texture_images(texels, surface, to_tangent_space(surface["normal"], t, b, n), settings.dilation, brdf, ao)


def texel_density(result: BakeResult, mesh: TriMesh) -> float:
    """Covered texels per unit of surface area (the normalised mesh's units: radius 1)."""
    return float(result.atlas.size**2 * result.coverage / max(mesh.face_areas.sum(), 1e-300))


def shading_normals(mesh: TriMesh, spec: NormalSpec, face: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """Unit shading normals ``(N, 3)`` of ``spec`` (flat, or smooth corner normals interpolated)
    at ``face (N,)`` and barycentrics ``bary (N, 2)`` of ``mesh``."""
    flat = mesh.face_normals[face]
    if spec.mode == "flat":
        return flat
    return interpolate_normals(spec.corner_normals(mesh.vertices, mesh.faces), face, bary, flat)


# ------------------------------------------------------------------------ levels of detail (high-to-low)
@dataclass
class Projection:
    """Texel points of a coarse level carried to the fine surface: ``points, normals (M, 3)`` on
    the fine mesh (shading normals of its ``spec``, turned to the coarse normal's side), ``found
    (M,) bool`` (a fine surface within the search distance; elsewhere the coarse point and normal
    are kept), ``opposite (M,) bool`` (found only on faces turned away from the coarse normal) and
    the signed ``offset (M,)`` along the coarse normal (NaN where not found)."""

    points: np.ndarray
    normals: np.ndarray
    found: np.ndarray
    opposite: np.ndarray
    offset: np.ndarray


def project_to_surface(fine: TriMesh, points: np.ndarray, normals: np.ndarray, search: float, spec: NormalSpec) -> Projection:
    """The classic high-to-low bake's ray casts: from each coarse ``points (M, 3)`` along its unit
    ``normals (M, 3)``, forwards and backwards, the nearest hit on ``fine`` within ``search`` (ray
    length) on a face that faces the coarse normal's way; only where neither ray meets such a face,
    the nearest hit at all (an inconsistently wound fine mesh; the field is two-sided). A face
    turned away is, on a consistently wound mesh, the far wall of a thin part (a tube's other
    side, a vase's inner wall), whose material is not this texel's. Ties go forwards. The fine
    hit's shading normal is ``spec``'s (flat, or its smooth corner normals interpolated), turned
    to the coarse normal's side."""
    tracer = EmbreeTracer(fine)
    fwd = tracer.trace(points, normals)
    bwd = tracer.trace(points, -normals)

    def reach_and_side(hits):
        reach = hits.depth <= search
        same = reach & ((fine.face_normals[np.maximum(hits.face, 0)] * normals).sum(1) >= 0)
        return reach, same

    reach_f, same_f = reach_and_side(fwd)
    reach_b, same_b = reach_and_side(bwd)
    nearer_b = bwd.depth < fwd.depth
    same = same_f | same_b
    use_b = np.where(same, same_b & (~same_f | nearer_b), reach_b & (~reach_f | nearer_b))
    found = reach_f | reach_b
    face = np.where(use_b, bwd.face, fwd.face).astype(np.int64)
    bary = np.where(use_b[:, None], bwd.bary, fwd.bary).astype(np.float64)
    offset = np.where(use_b, -bwd.depth, fwd.depth).astype(np.float64)
    offset[~found] = np.nan
    out_p = points.astype(np.float64).copy()
    out_n = normals.astype(np.float64).copy()
    if found.any():
        f, b = face[found], bary[found]
        tri = fine.vertices[fine.faces[f]]
        out_p[found] = tri[:, 0] + b[:, :1] * (tri[:, 1] - tri[:, 0]) + b[:, 1:] * (tri[:, 2] - tri[:, 0])
        n = shading_normals(fine, spec, f, b)
        n = np.where(((n * normals[found]).sum(1) < 0)[:, None], -n, n)
        out_n[found] = n
    return Projection(out_p, out_n, found, found & ~same, offset)


@dataclass
class LevelBake:
    """A coarse level baked from the field through the fine surface: its atlas texels, frame,
    textures (as :class:`BakeResult`'s) and the projection that found the fine surface."""

    texels: AtlasTexels
    frames: CornerFrames
    textures: dict[str, np.ndarray]
    projection: Projection


def bake_level(
    fine: TriMesh,
    coarse: TriMesh,
    field,
    size: int,
    settings: BakeSettings,
    search: float,
    device="cpu",
    occlusion: OcclusionSamples | None = None,
) -> LevelBake:
    """Bake ``field`` (trained on ``fine``) onto ``coarse``, a decimated version of it, in a
    ``size``-texel atlas: each texel's point on ``coarse`` is carried to ``fine`` along the coarse
    shading normal (:func:`project_to_surface`), the field is evaluated there with the fine
    surface's shading normal, and the predicted normal is written in the coarse level's own frame,
    so its normal map carries the detail the coarse geometry lost; the fine surface's ambient
    ``occlusion`` (when given) is read at the same points."""
    texels = atlas_texels(coarse, size, settings.padding, settings.max_chart_share)
    frames = CornerFrames.build(coarse.vertices, coarse.faces, texels.atlas.uv, field.normals)
    t, b, n = frames.at(texels.face, texels.bary)
    unit = n / np.linalg.norm(n, axis=1, keepdims=True)
    proj = project_to_surface(fine, texels.points, unit, search, field.normals)
    surface, brdf = evaluate_surface(field, proj.points, proj.normals, device)
    ao = None if occlusion is None else occlusion.at(proj.points, proj.normals)
    textures = texture_images(texels, surface, to_tangent_space(surface["normal"], t, b, n), settings.dilation, brdf, ao)
    return LevelBake(texels, frames, textures, proj)


# ------------------------------------------------------------------------ texture sampling / fidelity
def decode_textures(textures: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The 8-bit textures as float arrays in the renderer's units (linear): ``albedo`` is the base
    colour texture (TANGO's diffuse albedo, or glTF's base colour)."""
    return {
        "albedo": srgb_decode(textures["basecolor"] / 255.0),
        "specular": srgb_decode(textures["specular"] / 255.0),
        "roughness": textures["metallic_roughness"][..., 1:2] / 255.0,
        "metallic": textures["metallic_roughness"][..., 2:3] / 255.0,
        "occlusion": textures["metallic_roughness"][..., 0:1] / 255.0,
        "normal": textures["normal"] / 255.0 * 2.0 - 1.0,
    }


@torch.no_grad()
def render_baked(
    hits,
    uv_faces,
    tex: dict,
    frames: CornerFrames,
    light,
    device="cpu",
    lobe: str = "isotropic",
    brdf: Brdf | str = "tango",
    wrap: bool = False,
):
    """Shade cached hits (a :class:`BakedHits`) from the decoded textures read through the bake's
    ``frames``, with the specular model ``lobe`` and the BRDF ``brdf`` (the field's, its object or
    name: its parameters read from their textures, ``brdf.texture_of``: TANGO's albedo, specular
    and roughness textures, or glTF's base colour, metallic and roughness);
    ``wrap``: the textures repeat (a kept UV layout) rather than clamp (an atlas). Returns ``(N, 3)``
    linear radiance."""
    f = hits.face
    tri_uv = uv_faces[f]
    # barycentrics of the hit from its point (cache stores quantised Embree barycentrics)
    bu = hits.bary
    uv = tri_uv[:, 0] + bu[:, :1] * (tri_uv[:, 1] - tri_uv[:, 0]) + bu[:, 1:] * (tri_uv[:, 2] - tri_uv[:, 0])

    def sample(key):
        return sample_bilinear(tex[key], uv, wrap)

    ts = sample("normal")
    world = from_tangent_space(ts, *frames.at(f, bu))
    view = -hits.direction.astype(np.float64)
    # two-sided, as in training: flip normals of faces seen from behind
    flip = (frames.face_normals[f] * view).sum(1, keepdims=True) < 0
    world = np.where(flip, -world, world)

    def tt(x):
        return torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32)).to(device)

    nn_ = face_viewer(tt(world), tt(view))
    rough = tt(np.clip(sample("roughness"), 0.01, 1.0))
    brdf = brdfs.get(brdf)
    colour, specular = (tt(sample(brdf.texture_of[name])) for name in brdf.parameters[:2])
    return shade_material(nn_, tt(view), Material.of(brdf, colour, specular, rough), light, lobe).rgb


def render_baked_views(
    cache,
    uv_faces,
    tex: dict,
    frames: CornerFrames,
    light,
    device="cpu",
    lobe: str = "isotropic",
    brdf: Brdf | str = "tango",
    wrap: bool = False,
) -> list:
    """:func:`render_baked` for every view of the ray ``cache`` traced on the baked mesh: per view
    the linear radiance ``(N, 3)`` of its hits (in the cache's hit order)."""
    return [
        render_baked(
            BakedHits(cache.view(i), cached_barycentrics(cache, i)), uv_faces, tex, frames, light, device, lobe, brdf, wrap
        )
        for i in range(len(cache))
    ]


def render_texture_sets(
    cache,
    uv_faces,
    sets: list[dict],
    face_set: np.ndarray,
    frames: CornerFrames,
    light,
    device="cpu",
    lobe="isotropic",
    brdf: Brdf | str = "tango",
) -> list:
    """:func:`render_baked_views` of a kept layout (repeating textures) with one decoded texture
    set per group of faces: each hit reads the set of its face (``face_set (F,)``, index into
    ``sets``)."""
    per = [render_baked_views(cache, uv_faces, tex, frames, light, device, lobe, brdf, True) for tex in sets]
    out = []
    for i, rgb in enumerate(per[0]):
        rgb = rgb.clone()
        pick = torch.from_numpy(face_set[cache.view(i).face]).to(rgb.device)
        for k in range(1, len(sets)):
            rgb[pick == k] = per[k][i][pick == k]
        out.append(rgb)
    return out


class BakedHits:
    """The face, ray direction and float barycentrics of one cached view's hits."""

    def __init__(self, hits, bary):
        self.face = hits.face
        self.direction = hits.direction
        self.bary = bary


def cached_barycentrics(cache, i: int) -> np.ndarray:
    lo, hi = cache.arrays["offsets"][i], cache.arrays["offsets"][i + 1]
    return dequantize_bary(cache.arrays["bary"][lo:hi]).astype(np.float64)
