"""Write a synthetic results tree for exercising the report at scale, without optimising anything.

    python scripts/synthetic_results.py OUT [--meshes 10] [--prompts 3] [--decimated 2]

Every cell gets what the real stages would leave for the report: the optimisation's metadata
(resolved settings, origin, contact-sheet layout, wall time), its renders and loss curve, a real
binary glTF (a textured sphere written by the export's own writer), the learned light as
``light.hdr``, texture maps, the bake's, relighting's and metrics' metadata and images, and each
mesh's normalize (and decimate) metadata. The figures are generated, not measured: every output is
marked TEST ONLY (origin "synthetic report data") so nothing made from it can pass for a result.

The variants cover what the report compares: ``base`` (the reference), ``base_seed1`` (a seed
replicate), ``it100`` (a sweep of the iterations: faster and worse), ``no_normal`` and ``no_spec``
(ablations: the normal network and the specular lobe switched off). The last ``--decimated``
meshes are decimated versions of the first ones (for the robustness figure). Prints the cells,
one ``mesh/prompt/variant`` per line, and writes ``cells.txt`` and ``decimated.json`` beside them.
"""

from __future__ import annotations

import argparse
import colorsys
import json
import math
import shutil
import sys
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stages.assets.formats import AssetInfo, ExportMesh  # noqa: E402
from stages.assets.formats.gltf import write_glb  # noqa: E402
from stages.config.brdfs import brdf_spec  # noqa: E402
from stages.config.guidance_modes import guidance_mode  # noqa: E402
from stages.config.layout import RENDER_KINDS, TEXTURES  # noqa: E402
from stages.config.sections import OptimizeSettings  # noqa: E402
from stages.render.hdrio import write_hdr  # noqa: E402

PROMPTS = ("wood", "metal", "plaster", "marble", "brick", "wicker", "gold", "jade")
#: variant -> (optimize overrides, quality change in dB, time factor)
VARIANTS = {
    "base": ({}, 0.0, 1.0),
    "base_seed1": ({"seed": 1}, -0.3, 1.02),
    "it100": ({"iterations": 100, "milestones": [60, 85]}, -2.5, 0.25),
    "no_normal": ({"normal_network": False}, -1.2, 0.8),
    "no_spec": ({"specular": False, "brdf": "tango"}, -1.8, 0.9),
}
TILE = 64
COLUMNS = 4
VIEWS = 8


def sphere(n_lat: int = 16, n_lon: int = 32) -> ExportMesh:
    """A UV sphere with normals, UVs and tangents (seam duplicated), radius 0.5."""
    lat = np.linspace(0, math.pi, n_lat + 1)
    lon = np.linspace(0, 2 * math.pi, n_lon + 1)
    t, p = np.meshgrid(lat, lon, indexing="ij")
    n = np.stack([np.sin(t) * np.cos(p), np.cos(t), np.sin(t) * np.sin(p)], -1).reshape(-1, 3)
    uv = np.stack([p / (2 * math.pi), t / math.pi], -1).reshape(-1, 2)
    tan = np.stack([-np.sin(p), np.zeros_like(p), np.cos(p)], -1).reshape(-1, 3)
    tan[np.linalg.norm(tan, axis=1) < 1e-6] = (1.0, 0.0, 0.0)
    idx = []
    w = n_lon + 1
    for i in range(n_lat):
        for j in range(n_lon):
            a, b, c, d = i * w + j, i * w + j + 1, (i + 1) * w + j, (i + 1) * w + j + 1
            idx += [(a, c, b), (b, c, d)]
    return ExportMesh(
        (0.5 * n).astype(np.float32),
        n.astype(np.float32),
        uv.astype(np.float32),
        np.concatenate([tan, np.ones((len(tan), 1))], 1).astype(np.float32),
        np.array(idx, dtype=np.int64),
    )


def shaded(rgb: tuple[float, float, float], size: int, azimuth: float, kind: str) -> np.ndarray:
    """A lit sphere on white, as the renders would show it."""
    y, x = np.mgrid[-1 : 1 : size * 1j, -1 : 1 : size * 1j]
    inside = x**2 + y**2 < 0.8**2
    z = np.sqrt(np.clip(0.64 - x**2 - y**2, 0, None)) / 0.8
    light = np.array([math.cos(azimuth), 0.6, math.sin(azimuth) + 1.0])
    light /= np.linalg.norm(light)
    shade = np.clip((x / 0.8) * light[0] + (-y / 0.8) * light[1] + z * light[2], 0.05, 1)
    colour = np.array(rgb if kind in ("rgb", "diffuse") else (0.5, 0.5, 0.5) if kind != "normal" else (0.5, 0.5, 1.0))
    img = np.ones((size, size, 3))
    img[inside] = (shade[..., None] * colour)[inside] if kind == "rgb" else colour
    return (np.clip(img, 0, 1) * 255).astype(np.uint8)


def sheet(rgb, kind: str) -> Image.Image:
    rows = math.ceil(VIEWS / COLUMNS)
    canvas = np.full((rows * TILE, COLUMNS * TILE, 3), 255, np.uint8)
    for k in range(VIEWS):
        r, c = divmod(k, COLUMNS)
        canvas[r * TILE : (r + 1) * TILE, c * TILE : (c + 1) * TILE] = shaded(rgb, TILE, 2 * math.pi * k / VIEWS, kind)
    return Image.fromarray(canvas)


def loss_image(loss: np.ndarray, title: str) -> Image.Image:
    img = Image.new("RGB", (360, 200), "white")
    d = ImageDraw.Draw(img)
    lo, hi = float(loss.min()), float(loss.max())
    pts = [(20 + 330 * i / (len(loss) - 1), 180 - 150 * (v - lo) / max(hi - lo, 1e-9)) for i, v in enumerate(loss)]
    d.line(pts, fill=(31, 119, 180), width=1)
    d.text((20, 4), title, fill="black")
    return img


def write_json(path: Path, data) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=1))


def make(out: Path, meshes: int = 10, prompts: int = 3, decimated: int = 2, seed: int = 0) -> list[tuple[str, str, str]]:
    rng = np.random.default_rng(seed)
    out = Path(out)
    full = [f"shape{i:02d}" for i in range(meshes - decimated)]
    pairs = {f"{full[i]}_5k": full[i] for i in range(decimated)}
    mesh_ids = full + list(pairs)
    prompt_ids = PROMPTS[:prompts]
    origin = guidance_mode("image").origin_record("synthetic report data", test_only=True)
    geom = sphere()
    faces = {m: int(rng.integers(8_000, 60_000)) for m in full}
    faces.update({d: 5_000 for d in pairs})
    cells = []
    for m in mesh_ids:
        norm = {"stats": {"faces": faces[pairs.get(m, m)]}, "timings_s": {"total": 0.2}}
        write_json(out / m / "normalize" / "meta.json", norm)
        if m in pairs:
            dec = {"faces_after": 5_000, "target_faces": 5_000, "target_reached": True, "target_shortfall_reason": None}
            write_json(out / m / "decimate" / "meta.json", {"stats": dec, "timings_s": {"total": 1.5}})
    for mi, m in enumerate(mesh_ids):
        base_quality = 24 + 4 * rng.random() - (1.0 if m in pairs else 0.0)
        base_seconds = 300 * (1 + rng.random())
        for pi, p in enumerate(prompt_ids):
            rgb = colorsys.hsv_to_rgb((pi / max(len(prompt_ids), 1) + 0.07 * mi) % 1, 0.6, 0.9)
            model_dir = out / ".models" / f"{m}_{p}"
            if not (model_dir / "model.glb").is_file():
                tex = model_dir / "textures"
                tex.mkdir(parents=True, exist_ok=True)
                u = np.linspace(0, 1, 64)
                stripes = (0.75 + 0.25 * np.sin(2 * math.pi * 6 * u))[None, :, None]
                base = (np.array(rgb)[None, None] * stripes * np.ones((64, 64, 1)) * 255).astype(np.uint8)
                Image.fromarray(base).save(tex / "basecolor.png")
                Image.fromarray(np.full((64, 64, 3), (0, 128, 0), np.uint8)).save(tex / "metallic_roughness.png")
                Image.fromarray(np.full((64, 64, 3), (128, 128, 255), np.uint8)).save(tex / "normal.png")
                Image.fromarray(np.full((64, 64, 3), 60, np.uint8)).save(tex / "specular.png")
                write_glb(model_dir / "model.glb", geom, tex, AssetInfo(1.0, f"{m}_{p}", origin, brdf_spec("tango")))
                sky = np.ones((32, 64, 3), np.float32) * np.linspace(2.0, 0.3, 32)[:, None, None] * np.array([0.9, 0.95, 1.1])
                write_hdr(model_dir / "light.hdr", sky.astype(np.float32))
                sheet(rgb, "rgb").crop((0, 0, TILE, TILE)).resize((256, 256)).save(model_dir / "preview.png")
            for v, (overrides, dq, ft) in VARIANTS.items():
                cell = out / m / p / v
                settings = {**OptimizeSettings().to_dict(), "guidance": "image", "target_material": "wood", **overrides}
                seconds = base_seconds * ft * (1 + 0.05 * rng.standard_normal())
                quality = base_quality + dq + 0.3 * rng.standard_normal()
                iters = settings["iterations"]
                loss = 0.2 * np.exp(-np.arange(0, iters, 10) / (iters / 4)) + 0.02 + 0.005 * rng.random(len(range(0, iters, 10)))
                opt = cell / "optimize"
                (opt / "renders").mkdir(parents=True, exist_ok=True)
                for kind in (*RENDER_KINDS, "target"):
                    sheet(rgb, kind).save(opt / "renders" / f"{kind}.png")
                (opt / "loss.csv").write_text("iteration,loss\n" + "".join(f"{10 * i},{x:.6f}\n" for i, x in enumerate(loss)))
                loss_image(loss, f"{m}/{p}/{v}").save(opt / "loss.png")
                write_json(
                    opt / "meta.json",
                    {
                        "prompt": f"a {m} made of {p}",
                        "guidance": "image",
                        "test_only_weights": True,
                        "weights": "synthetic report data",
                        "settings": settings,
                        "origin": origin,
                        "sheet": {"columns": COLUMNS, "tile": TILE, "front_view": 0},
                        "timings_s": {"total": seconds},
                        "eval_psnr_db": quality,
                    },
                )
                exp = cell / "export"
                (exp / "textures").mkdir(parents=True, exist_ok=True)
                for name in ("model.glb", "light.hdr", "preview.png"):
                    shutil.copyfile(model_dir / name, exp / name)
                for name in TEXTURES:
                    shutil.copyfile(model_dir / "textures" / f"{name}.png", exp / "textures" / f"{name}.png")
                stats = {"bake_psnr_db": 38 + rng.random(), "texture_size": 64}
                write_json(cell / "bake" / "meta.json", {"origin": origin, "stats": stats, "timings_s": {"total": 20.0}})
                write_json(exp / "meta.json", {"origin": origin, "stats": {}, "timings_s": {"total": 2.0}})
                rel = cell / "relight"
                rel.mkdir(parents=True, exist_ok=True)
                sheet(tuple(0.7 * c for c in rgb), "rgb").save(rel / "relit.png")
                sheet(rgb, "rgb").crop((0, 0, 3 * TILE, 3 * TILE)).save(rel / "material_edit.png")
                write_json(rel / "meta.json", {"origin": origin, "timings_s": {"total": 5.0}})
                metrics = {"origin": origin, "image_target": {"psnr_db": quality, "ssim": 0.8, "target_renderer": "sg"}}
                write_json(cell / "metrics" / "metrics.json", metrics)
                write_json(cell / "metrics" / "meta.json", {"origin": origin, "timings_s": {"total": 3.0}})
                cells.append((m, p, v))
    shutil.rmtree(out / ".models")
    (out / "cells.txt").write_text("".join("/".join(c) + "\n" for c in cells))
    write_json(out / "decimated.json", pairs)
    return cells


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", type=Path)
    parser.add_argument("--meshes", type=int, default=10)
    parser.add_argument("--prompts", type=int, default=3, help=f"at most {len(PROMPTS)}")
    parser.add_argument("--decimated", type=int, default=2, help="of the meshes, how many are decimated versions of others")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if not 0 <= args.decimated <= args.meshes // 2 or not 1 <= args.prompts <= len(PROMPTS):
        parser.error(f"need 0 <= --decimated <= --meshes / 2 and 1 <= --prompts <= {len(PROMPTS)}")
    for c in make(args.out, args.meshes, args.prompts, args.decimated, args.seed):
        print("/".join(c))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
