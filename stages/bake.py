"""bake: unwrap the mesh with xatlas and bake the trained field into PBR textures.

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
``v = (row + 0.5) / S`` (glTF's texture coordinates). USD's ``st = (u, 1 - v)``. The tangent
frame is per face, computed from positions and ``st`` (``T = dP/ds``, ``B = dP/dt``),
Gram-Schmidt-orthonormalised against the flat face normal, with handedness
``w = sign((N x T) . B)`` and bitangent ``w (N x T)``: the frame that MikkTSpace produces on a mesh
whose faces do not share vertices (the exported meshes are faceted, as TANGO shades them), and the
one the exporters hand to glTF viewers as the TANGENT attribute. The normal texture stores
``((n.T, n.B, n.N) + 1) / 2`` (+X right, +Y up: OpenGL/glTF/USD convention).
"""

from __future__ import annotations

import argparse
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .errors import ConfigError, StageInputError, stage_errors
from .hdrio import write_exr, write_hdr
from .meshio import TriMesh, load_ply
from .networks import equirect_directions
from .provenance import (
    ORIGIN_KEY,
    Timer,
    add_torch_arguments,
    apply_torch_arguments,
    atomic_path,
    metadata,
    staged_outputs,
    write_json_atomic,
)
from .settings import Settings

log = logging.getLogger(__name__)

TEXTURES = ("basecolor", "metallic_roughness", "specular", "normal")


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
    #: width of the equirectangular light image (height = width / 2)
    light_width: int = 512
    #: resolution of the fidelity renders (evaluation views)
    eval_width: int = 256

    def __post_init__(self) -> None:
        if self.texture_size is not None and not 16 <= self.texture_size <= 16384:
            raise ConfigError(f"bake.texture_size must be in [16, 16384], got {self.texture_size}")
        if not 16 <= self.min_size <= self.max_size:
            raise ConfigError("bake: need 16 <= min_size <= max_size")

    def size_for(self, faces: int) -> int:
        """Texture size: the configured one, or the power of two nearest to
        ``sqrt(faces * texels_per_face / 0.75)`` (xatlas packs about 75%), clamped."""
        if self.texture_size is not None:
            return int(self.texture_size)
        want = math.sqrt(faces * self.texels_per_face / 0.75)
        size = 2 ** round(math.log2(max(want, 1.0)))
        return int(min(max(size, self.min_size), self.max_size))


@dataclass
class Atlas:
    """``uv (F, 3, 2)`` per-corner texture coordinates (glTF convention), ``size`` in texels."""

    uv: np.ndarray
    size: int
    charts: int
    utilization: float


def unwrap(mesh: TriMesh, size: int, padding: int) -> Atlas:
    """xatlas parametrisation packed for a ``size x size`` texture."""
    try:
        import xatlas
    except ImportError as exc:  # pragma: no cover
        raise ImportError("the bake stage needs xatlas: pip install xatlas") from exc
    atlas = xatlas.Atlas()
    atlas.add_mesh(mesh.vertices.astype(np.float32), mesh.faces.astype(np.uint32))
    pack = xatlas.PackOptions()
    pack.resolution = size
    pack.padding = padding
    pack.bilinear = True
    atlas.generate(xatlas.ChartOptions(), pack)
    vmapping, indices, uvs = atlas[0]
    if not np.array_equal(vmapping[indices], mesh.faces):
        raise RuntimeError("xatlas changed the face order; cannot map faces to the atlas")
    # xatlas packs into its own width x height; rescale to the square texture
    uv = uvs[indices].astype(np.float64)
    scale = max(atlas.width, atlas.height)
    uv = uv * np.array([atlas.width, atlas.height]) / scale
    return Atlas(uv, size, int(atlas.chart_count), float(atlas.utilization))


def rasterize_atlas(uv: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Face id ``(S, S) int32`` (-1 = empty) and barycentrics ``(S, S, 2) float32`` (Embree's
    ``(u, v)``: point = (1-u-v) p0 + u p1 + v p2) of every texel centre, by casting one ray per
    texel at the UV-space triangles."""
    from .raycache import EmbreeTracer

    tri2d = np.concatenate([uv * size, np.zeros(uv.shape[:2] + (1,))], axis=-1)  # (F, 3, 3)
    flat = TriMesh(tri2d.reshape(-1, 3), np.arange(3 * len(uv)).reshape(-1, 3))
    tracer = EmbreeTracer(flat)
    c = np.arange(size) + 0.5
    cols, rows = np.meshgrid(c, c)  # texel (row, col) -> (u, v) = (col, row) / S
    origins = np.stack([cols.ravel(), rows.ravel(), np.ones(size * size)], axis=1)
    dirs = np.broadcast_to(np.array([0.0, 0.0, -1.0]), origins.shape)
    hits = tracer.trace(origins, dirs)
    return hits.face.reshape(size, size), hits.bary.reshape(size, size, 2)


def face_frames(mesh: TriMesh, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-face unit tangent ``T``, bitangent ``B = w (N x T)`` and normal ``N``, ``(F, 3)`` each,
    and handedness ``w (F,)`` folded into ``B``; see the module docstring. Faces with a degenerate
    UV or 3D triangle get an arbitrary orthonormal frame around ``N``."""
    p = mesh.vertices[mesh.faces]
    n = mesh.face_normals
    st = np.stack([uv[..., 0], 1.0 - uv[..., 1]], axis=-1)
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    d1, d2 = st[:, 1] - st[:, 0], st[:, 2] - st[:, 0]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    ok = np.abs(det) > 1e-20
    r = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)[:, None]
    t = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) * r
    b = (e2 * d1[:, 0:1] - e1 * d2[:, 0:1]) * r
    t = t - n * (n * t).sum(1, keepdims=True)
    tn = np.linalg.norm(t, axis=1, keepdims=True)
    bad = ~ok | (tn[:, 0] < 1e-20) | (np.linalg.norm(n, axis=1) < 0.5)
    fallback = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    fallback = fallback - n * (n * fallback).sum(1, keepdims=True)
    t = np.where(bad[:, None], fallback, t)
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-30)
    w = np.where((np.cross(n, t) * b).sum(1) < 0, -1.0, 1.0)
    w[bad] = 1.0
    return t, np.cross(n, t) * w[:, None], n, w


def dilate(values: np.ndarray, filled: np.ndarray, passes: int) -> np.ndarray:
    """Grow ``values (S, S, C)`` from ``filled (S, S) bool`` texels into empty neighbours
    (8-neighbourhood mean), ``passes`` times; remaining empty texels take the filled mean."""
    v = values.copy()
    f = filled.copy()
    for _ in range(passes):
        acc = np.zeros_like(v)
        cnt = np.zeros(f.shape, np.float64)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                if dy == dx == 0:
                    continue
                sv = np.roll(np.roll(v, dy, 0), dx, 1)
                sf = np.roll(np.roll(f, dy, 0), dx, 1)
                acc += sv * sf[..., None]
                cnt += sf
        grow = ~f & (cnt > 0)
        if not grow.any():
            break
        v[grow] = acc[grow] / cnt[grow][:, None]
        f |= grow
    if (~f).any() and filled.any():
        v[~f] = values[filled].mean(0)
    return v


def srgb_encode(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def srgb_decode(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.04045, x / 12.92, np.power((x + 0.055) / 1.055, 2.4))


def to_u8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(x * 255.0), 0, 255).astype(np.uint8)


@dataclass
class BakeResult:
    atlas: Atlas
    textures: dict[str, np.ndarray]  # uint8 (S, S, 3) images as written
    tangents: np.ndarray  # (F, 3)
    handedness: np.ndarray  # (F,)
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
    t, b, n, w = face_frames(mesh, atlas.uv)
    normals = n[fi]
    albedo, spec, rough, pred = [], [], [], []
    p_t = torch.from_numpy(points.astype(np.float32)).to(device)
    n_t = torch.from_numpy(normals.astype(np.float32)).to(device)
    for lo in range(0, len(p_t), chunk):
        p, nn_ = p_t[lo : lo + chunk], n_t[lo : lo + chunk]
        ps = field.symmetric_points(p)
        mat = field.svbrdf(ps)
        albedo.append(mat.albedo)
        if mat.specular is not None:
            spec.append(mat.specular)
            rough.append(mat.roughness)
        pred.append(field.normal_net(ps, nn_) if field.normal_net is not None else nn_)
    s = size
    base = np.zeros((s, s, 3))
    base[filled] = torch.cat(albedo).cpu().double().numpy()
    spc = np.zeros((s, s, 3))
    rgh = np.ones((s, s, 1))
    if spec:
        spc[filled] = torch.cat(spec).cpu().double().numpy()
        rgh[filled] = torch.cat(rough).cpu().double().numpy()
    pn = torch.cat(pred).cpu().double().numpy()
    ts = np.stack([(pn * t[fi]).sum(1), (pn * b[fi]).sum(1), (pn * n[fi]).sum(1)], axis=1)
    nrm = np.zeros((s, s, 3))
    nrm[..., 2] = 1.0
    nrm[filled] = ts / np.linalg.norm(ts, axis=1, keepdims=True)
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
    return BakeResult(atlas, textures, t, w, float(filled.mean()), env)


# ------------------------------------------------------------------------ texture sampling / fidelity
def sample_bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup of ``img (S, S, C)`` at glTF-convention ``uv (N, 2)`` (clamped at edges)."""
    s = img.shape[0]
    x = np.clip(uv[:, 0] * s - 0.5, 0, s - 1)
    y = np.clip(uv[:, 1] * s - 0.5, 0, s - 1)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    x1, y1 = np.minimum(x0 + 1, s - 1), np.minimum(y0 + 1, s - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    im = img.astype(np.float64)
    return im[y0, x0] * (1 - fx) * (1 - fy) + im[y0, x1] * fx * (1 - fy) + im[y1, x0] * (1 - fx) * fy + im[y1, x1] * fx * fy


def decode_textures(textures: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The 8-bit textures as float arrays in the renderer's units (linear)."""
    return {
        "albedo": srgb_decode(textures["basecolor"] / 255.0),
        "specular": srgb_decode(textures["specular"] / 255.0),
        "roughness": textures["metallic_roughness"][..., 1:2] / 255.0,
        "normal": textures["normal"] / 255.0 * 2.0 - 1.0,
    }


@torch.no_grad()
def render_baked(hits, uv_faces, tex: dict, frames, light, device="cpu"):
    """Shade cached hits (a :class:`~stages.raycache.ViewHits`) from the decoded textures.
    Returns ``(N, 3)`` linear radiance."""
    from .render.shading import face_viewer, shade

    t, b, n = frames
    f = hits.face
    tri_uv = uv_faces[f]
    # barycentrics of the hit from its point (cache stores quantised Embree barycentrics)
    bu = hits.bary
    uv = tri_uv[:, 0] + bu[:, :1] * (tri_uv[:, 1] - tri_uv[:, 0]) + bu[:, 1:] * (tri_uv[:, 2] - tri_uv[:, 0])
    ts = sample_bilinear(tex["normal"], uv)
    world = ts[:, :1] * t[f] + ts[:, 1:2] * b[f] + ts[:, 2:3] * n[f]
    world /= np.linalg.norm(world, axis=1, keepdims=True)
    view = -hits.direction.astype(np.float64)
    # two-sided, as in training: flip normals seen from behind
    flip = (n[f] * view).sum(1, keepdims=True) < 0
    world = np.where(flip, -world, world)

    def tt(x):
        return torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32)).to(device)

    nn_ = face_viewer(tt(world), tt(view))
    spec = tt(sample_bilinear(tex["specular"], uv))
    rough = tt(np.clip(sample_bilinear(tex["roughness"], uv), 0.01, 1.0))
    return shade(nn_, tt(view), tt(sample_bilinear(tex["albedo"], uv)), light, spec, rough).rgb


def run(
    mesh_path: Path,
    field_path: Path,
    eval_path: Path,
    out_dir: Path,
    settings: BakeSettings,
    device: str = "cpu",
) -> dict:
    """Bake ``field_path`` onto ``mesh_path`` and write textures, light, atlas and metadata."""
    from PIL import Image

    from .imaging import linear_to_srgb
    from .optimize import ViewStore, load_field, psnr
    from .raycache import RayCache

    timer = Timer()
    for p in (mesh_path, field_path, eval_path):
        if not Path(p).is_file():
            raise StageInputError(p, "file not found", "Run the earlier stages first.")
    with timer("load"):
        mesh = load_ply(mesh_path)
        field, opt_settings = load_field(field_path, device)
    with timer("bake"):
        res = bake_field(mesh, field, settings, device)
    out_dir = Path(out_dir)
    with staged_outputs(out_dir) as staging:
        with timer("write"):
            for name, img in res.textures.items():
                with atomic_path(staging / "textures" / f"{name}.png") as tmp:
                    Image.fromarray(img).save(tmp, format="PNG")
            write_exr(staging / "light.exr", res.light_equirect)
            write_hdr(staging / "light.hdr", res.light_equirect)
            with atomic_path(staging / "atlas.npz") as tmp:
                with open(tmp, "wb") as fh:
                    np.savez(fh, uv=res.atlas.uv.astype(np.float32), tangent=res.tangents, handedness=res.handedness)
        # fidelity: baked asset vs neural field from the evaluation views
        with timer("fidelity"):
            evalc = RayCache(eval_path)
            store = ViewStore(evalc, torch.device(device))
            tex = decode_textures(res.textures)
            t, b, n, _ = face_frames(mesh, res.atlas.uv)
            light = field.light()
            preds, refs = [], []
            for i in range(len(evalc)):
                hits = evalc.view(i)
                hits_bary = _bary_of(evalc, i)
                baked = render_baked(_Hits(hits, hits_bary), res.atlas.uv, tex, (t, b, n), light, device)
                v = store[i]
                with torch.no_grad():
                    ref = field(v.points, v.normals, v.view).shading.rgb
                preds.append(linear_to_srgb(baked))
                refs.append(linear_to_srgb(ref))
            bake_psnr = psnr(torch.cat(preds), torch.cat(refs))
            # the preview: the baked asset from the evaluation view nearest TANGO's front view
            from .imaging import compose, gather_points, global_spec
            from .optimize import save_png
            from .relight import _front_view

            front = _front_view(store)
            spec = global_spec(store.width, settings.eval_width)
            needed, (lookup,) = gather_points([spec], store[front].index)
            bg = torch.ones(3, settings.eval_width, settings.eval_width)
            img = compose(preds[front][torch.from_numpy(needed)], lookup, spec, bg)
            save_png(staging / "preview.png", to_u8(img.permute(1, 2, 0).cpu().numpy()))
        stats = {
            "texture_size": res.atlas.size,
            "charts": res.atlas.charts,
            "atlas_utilization": res.atlas.utilization,
            "texel_coverage": res.coverage,
            "faces": len(mesh.faces),
            "bake_psnr_db": bake_psnr,
            "bake_psnr_pixels": "object pixels of the evaluation views, sRGB, baked textures vs neural field",
        }
        log.info(
            "baked %d faces into %d^2 textures (%.0f%% texels used), fidelity %.1f dB",
            len(mesh.faces),
            res.atlas.size,
            100 * res.coverage,
            bake_psnr,
        )
        write_json_atomic(
            staging / "meta.json",
            metadata(
                stage="bake",
                settings=settings.to_dict(),
                inputs={"mesh": mesh_path, "field": field_path, "eval": eval_path},
                outputs={
                    "textures": out_dir / "textures",
                    "light": out_dir / "light.exr",
                    "atlas": out_dir / "atlas.npz",
                },
                timings={**timer.seconds, "total": timer.total()},
                extra={"stats": stats, "optimize_settings": opt_settings.to_dict(), ORIGIN_KEY: field.origin},
            ),
        )
    return stats


class _Hits:
    def __init__(self, hits, bary):
        self.face = hits.face
        self.direction = hits.direction
        self.bary = bary


def _bary_of(cache, i: int) -> np.ndarray:
    from .raycache import dequantize_bary

    lo, hi = cache.arrays["offsets"][i], cache.arrays["offsets"][i + 1]
    return dequantize_bary(cache.arrays["bary"][lo:hi]).astype(np.float64)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m stages.bake", description=__doc__.split("\n")[0])
    parser.add_argument("--mesh", required=True, type=Path, help="the traced mesh (.ply)")
    parser.add_argument("--field", required=True, type=Path, help="trained field (field.pt)")
    parser.add_argument("--eval", required=True, type=Path, help="evaluation ray cache (.npz)")
    parser.add_argument("--out-dir", required=True, type=Path)
    parser.add_argument("--settings", default="{}", help="JSON of the bake settings")
    add_torch_arguments(parser, "cpu")
    args = parser.parse_args(argv)
    apply_torch_arguments(args)
    with stage_errors("bake") as status:
        run(args.mesh, args.field, args.eval, args.out_dir, BakeSettings.from_json(args.settings), args.device)
    return status.code


if __name__ == "__main__":
    raise SystemExit(main())
