"""The bake against the size of xatlas's charts (``bake.max_chart_share``): time and fidelity.

xatlas grows charts as large as its cost function allows; on a large smooth mesh (a tube, a
scanned statue) they cover thousands of faces each, and parametrising and packing them is most of
the bake (``benchmarks.assets.xatlas_options``: 88-135 s for the 81,920-face knot at 1024 texels, no
option of xatlas's near 20 s). Bounding a chart's area to a share of the surface trades seams for
time, and more charts lose more texels to the padding between them (``bake.padding``). For each
mesh (the generated 81,920-face knot tube and, in a developer checkout, the shared meshes named),
each share and each padding, this runs the bake's own code (``bake_field``: unwrap, rasterise,
evaluate the field at every covered texel, dilate) at one texture size and prints the unwrap's
and the whole bake's seconds, charts, atlas utilisation, covered texels and the fidelity (PSNR of
the baked textures rendered from 24 evaluation views at 256 pixels against the neural field, over
object pixels: what the bake stage records as ``bake_psnr_db``). The field has detail at texel
scale: the ``fast`` preset's networks (width 64, 6 NeRF frequencies) with their SVBRDF weights
perturbed by seeded noise (std 0.3), whose albedo varies by 0.2 across the object and by about
0.08 over 0.01 units (a few texels of a 1024 atlas). Side by side in one run.

    python -m benchmarks.assets.bake_charts [--size 1024] [--shares none,0.01,0.003] [--paddings 4,1]
        [--meshes knot80k,shared:person]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from benchmarks.common import SHARED_MESHES, knot_mesh, perturbed_field


def load(name: str):
    from stages.config.sections import NormalizeSettings
    from stages.geometry.normalization import normalize_mesh

    if name == "knot80k":
        return knot_mesh()
    if name.startswith("shared:"):
        path = SHARED_MESHES / f"{name.split(':', 1)[1]}.obj"
        if not path.is_file():
            return None
        return normalize_mesh(str(path), NormalizeSettings()).mesh
    raise SystemExit(f"unknown mesh {name!r}: knot80k or shared:<stem>")


def main() -> None:
    import torch

    from stages.assets import baking
    from stages.config.sections import BakeSettings, RaycacheSettings
    from stages.geometry.meshio import save_ply
    from stages.geometry.raycache import RayCache
    from stages.imaging.quality import psnr
    from stages.imaging.views import ViewStore, radiance_at_hits
    from stages.raycache import run as raycache_run
    from stages.render.color import linear_to_srgb

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--shares", default="none,0.01,0.003")
    parser.add_argument("--paddings", default="4,1", help="xatlas's padding between charts, texels (the bake's default 4)")
    parser.add_argument("--meshes", default="knot80k,shared:person,shared:horse")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    shares = [None if s == "none" else float(s) for s in args.shares.split(",")]
    paddings = [int(p) for p in args.paddings.split(",")]
    field, _ = perturbed_field()
    unwrap_s: list[float] = []
    inner = baking.unwrap

    def timed_unwrap(*a, **kw):
        t0 = time.perf_counter()
        out = inner(*a, **kw)
        unwrap_s.append(time.perf_counter() - t0)
        return out

    baking.unwrap = timed_unwrap
    print(f"# texture {args.size}, dilation 8; a field with texel-scale detail; fidelity over 24 views at 256 px")
    head = f"{'mesh':<14}{'faces':>7}{'share':>8}{'pad':>4}{'unwrap s':>10}{'bake s':>8}"
    print(f"{head}{'charts':>8}{'util':>6}{'texels':>8}{'PSNR dB':>9}")
    kv = {}
    for name in args.meshes.split(","):
        mesh = load(name)
        if mesh is None:
            print(f"{name}: not here (a developer checkout has ../shared/meshes)", flush=True)
            continue
        with tempfile.TemporaryDirectory() as d:
            d = Path(d)
            save_ply(d / "mesh.ply", mesh)
            cache = RaycacheSettings(views=2, resolution=32, eval_resolution=256, metrics_resolution=32)
            raycache_run(d / "mesh.ply", d / "train.npz", d / "eval.npz", d / "rc.json", cache, d / "metrics.npz")
            eval_cache = RayCache(d / "eval.npz")
            with torch.no_grad():
                store = ViewStore(eval_cache, torch.device("cpu"), field.normals)
                refs = torch.cat([linear_to_srgb(r) for r in radiance_at_hits(field, store)])
                light = field.light()
                for share, pad in ((s, p) for s in shares for p in paddings):
                    t0 = time.perf_counter()
                    bake = BakeSettings(texture_size=args.size, max_chart_share=share, padding=pad)
                    res = baking.bake_field(mesh, field, bake)
                    bake_s = time.perf_counter() - t0
                    tex = baking.decode_textures(res.textures)
                    baked = baking.render_baked_views(
                        eval_cache, res.atlas.uv, tex, res.frames, light, "cpu", field.specular_lobe
                    )
                    fidelity = psnr(torch.cat([linear_to_srgb(b) for b in baked]), refs)
                    label = "none" if share is None else f"{share:g}"
                    print(
                        f"{name:<14}{len(mesh.faces):>7}{label:>8}{pad:>4}{unwrap_s[-1]:>10.1f}{bake_s:>8.1f}{res.atlas.charts:>8}"
                        f"{res.atlas.utilization:>6.2f}{res.coverage:>8.3f}{fidelity:>9.2f}",
                        flush=True,
                    )
                    kv[f"bake_s_{name}_{label}_pad{pad}"] = bake_s
                    kv[f"psnr_{name}_{label}_pad{pad}"] = fidelity
    print(" ".join(f"{k}={v:.4g}" for k, v in kv.items()))


if __name__ == "__main__":
    main()
