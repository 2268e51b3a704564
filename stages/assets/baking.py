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
5. The learned SG light is written as an equirectangular image (``light.exr`` and ``light.hdr``).
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

from dataclasses import dataclass

import numpy as np
import torch

from ..config.sections import BakeSettings
from ..geometry.atlas import Atlas, dilate, rasterize_atlas, sample_bilinear, unwrap
from ..geometry.meshio import TriMesh
from ..geometry.raycache import dequantize_bary
from ..geometry.tangents import CornerFrames, from_tangent_space, to_tangent_space
from ..render.color import srgb_decode, srgb_encode, to_u8
from ..render.envmap import equirect_directions
from ..render.shading import face_viewer, shade


@dataclass
class BakeResult:
    atlas: Atlas
    textures: dict[str, np.ndarray]  # uint8 (S, S, 3) images as written
    frames: CornerFrames
    coverage: float
    light_equirect: np.ndarray


@torch.no_grad()
def bake_field(mesh: TriMesh, field, settings: BakeSettings, device="cpu", chunk: int = 65536) -> BakeResult:
    """Unwrap ``mesh``, rasterise the atlas and evaluate ``field`` at every covered texel."""
    size = settings.size_for(len(mesh.faces))
    atlas = unwrap(mesh, size, settings.padding)
    face, bary = rasterize_atlas(atlas.uv, size)
    filled = face >= 0
    fi = face[filled].astype(np.int64)
    uvb = bary[filled].astype(np.float64)
    tri = mesh.vertices[mesh.faces[fi]]
    points = tri[:, 0] + uvb[:, :1] * (tri[:, 1] - tri[:, 0]) + uvb[:, 1:] * (tri[:, 2] - tri[:, 0])
    frames = CornerFrames.build(mesh.vertices, mesh.faces, atlas.uv, field.normals)
    t, b, n = frames.at(fi, uvb)
    normals = n / np.linalg.norm(n, axis=1, keepdims=True)
    albedo, spec, rough, pred = [], [], [], []
    p_t = torch.from_numpy(points.astype(np.float32)).to(device)
    n_t = torch.from_numpy(normals.astype(np.float32)).to(device)
    for lo in range(0, len(p_t), chunk):
        mat, normal = field.surface(p_t[lo : lo + chunk], n_t[lo : lo + chunk])
        albedo.append(mat.albedo)
        if mat.specular is not None:
            spec.append(mat.specular)
            rough.append(mat.roughness)
        pred.append(normal)
    s = size
    base = np.zeros((s, s, 3))
    base[filled] = torch.cat(albedo).cpu().double().numpy()
    spc = np.zeros((s, s, 3))
    rgh = np.ones((s, s, 1))
    if spec:
        spc[filled] = torch.cat(spec).cpu().double().numpy()
        rgh[filled] = torch.cat(rough).cpu().double().numpy()
    pn = torch.cat(pred).cpu().double().numpy()
    nrm = np.zeros((s, s, 3))
    nrm[..., 2] = 1.0
    nrm[filled] = to_tangent_space(pn, t, b, n)
    base, spc, rgh, nrm = (dilate(x, filled, settings.dilation) for x in (base, spc, rgh, nrm))
    mr = np.concatenate([np.ones((s, s, 1)), rgh, np.zeros((s, s, 1))], axis=-1)  # R unused, G rough, B metal
    textures = {
        "basecolor": to_u8(srgb_encode(base)),
        "metallic_roughness": to_u8(mr),
        "specular": to_u8(srgb_encode(spc)),
        "normal": to_u8(0.5 + 0.5 * nrm),
    }
    light = field.light()
    h = settings.light_width // 2
    dirs = equirect_directions(h, settings.light_width).to(device)
    env = light.radiance(dirs.reshape(-1, 3)).reshape(h, settings.light_width, 3).cpu().numpy().astype(np.float32)
    return BakeResult(atlas, textures, frames, float(filled.mean()), env)


# ------------------------------------------------------------------------ texture sampling / fidelity
def decode_textures(textures: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The 8-bit textures as float arrays in the renderer's units (linear)."""
    return {
        "albedo": srgb_decode(textures["basecolor"] / 255.0),
        "specular": srgb_decode(textures["specular"] / 255.0),
        "roughness": textures["metallic_roughness"][..., 1:2] / 255.0,
        "normal": textures["normal"] / 255.0 * 2.0 - 1.0,
    }


@torch.no_grad()
def render_baked(hits, uv_faces, tex: dict, frames: CornerFrames, light, device="cpu", lobe: str = "isotropic"):
    """Shade cached hits (a :class:`BakedHits`) from the decoded textures read through the bake's
    ``frames``, with the specular model ``lobe`` (the field's). Returns ``(N, 3)`` linear radiance."""
    f = hits.face
    tri_uv = uv_faces[f]
    # barycentrics of the hit from its point (cache stores quantised Embree barycentrics)
    bu = hits.bary
    uv = tri_uv[:, 0] + bu[:, :1] * (tri_uv[:, 1] - tri_uv[:, 0]) + bu[:, 1:] * (tri_uv[:, 2] - tri_uv[:, 0])
    ts = sample_bilinear(tex["normal"], uv)
    world = from_tangent_space(ts, *frames.at(f, bu))
    view = -hits.direction.astype(np.float64)
    # two-sided, as in training: flip normals of faces seen from behind
    flip = (frames.face_normals[f] * view).sum(1, keepdims=True) < 0
    world = np.where(flip, -world, world)

    def tt(x):
        return torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32)).to(device)

    nn_ = face_viewer(tt(world), tt(view))
    spec = tt(sample_bilinear(tex["specular"], uv))
    rough = tt(np.clip(sample_bilinear(tex["roughness"], uv), 0.01, 1.0))
    return shade(nn_, tt(view), tt(sample_bilinear(tex["albedo"], uv)), light, spec, rough, lobe).rgb


class BakedHits:
    """The face, ray direction and float barycentrics of one cached view's hits."""

    def __init__(self, hits, bary):
        self.face = hits.face
        self.direction = hits.direction
        self.bary = bary


def cached_barycentrics(cache, i: int) -> np.ndarray:
    lo, hi = cache.arrays["offsets"][i], cache.arrays["offsets"][i + 1]
    return dequantize_bary(cache.arrays["bary"][lo:hi]).astype(np.float64)
