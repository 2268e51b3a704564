"""xatlas's options against its time on a large mesh: the unwrap is most of the bake of an 80k-face
mesh (``benchmarks.assets.bake``), and the speed issue asks whether its chart and pack options get the
bake of 80k faces at 1024 texels to 20 s.

The mesh is the generated torus-knot tube at 81,920 faces (as in ``benchmarks.assets.bake``); each row
runs ``xatlas.Atlas.generate`` (charts, then packing for a 1024-texel texture, padding 4, bilinear)
once with the options named, and prints its seconds, chart count and utilisation.

    python -m benchmarks.assets.xatlas_options [--size 1024] [--rows default,blockAlign,...]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

#: row name -> (chart options, pack options) on top of the defaults the bake uses
ROWS = {
    "default": ({}, {}),
    "blockAlign": ({}, {"blockAlign": True}),
    "max_cost 8": ({"max_cost": 8.0}, {}),
    "max_iterations 0": ({"max_iterations": 0}, {}),
    "no rotation": ({}, {"rotate_charts": False}),
}


def main() -> None:
    import xatlas

    from stages.geometry.shapes import knot

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--rows", default=",".join(ROWS))
    args = parser.parse_args()
    v, f = knot(samples=2048, sides=20)
    v, f = np.asarray(v, np.float32), np.asarray(f, np.uint32)
    print(f"# knot tube, {len(f)} faces, texture {args.size}")
    print(f"{'options':<20}{'seconds':>9}{'charts':>8}{'utilisation':>13}", flush=True)
    for name in args.rows.split(","):
        chart_kw, pack_kw = ROWS[name]
        atlas = xatlas.Atlas()
        atlas.add_mesh(v, f)
        chart = xatlas.ChartOptions()
        for k, val in chart_kw.items():
            setattr(chart, k, val)
        pack = xatlas.PackOptions()
        pack.resolution, pack.padding, pack.bilinear = args.size, 4, True
        for k, val in pack_kw.items():
            setattr(pack, k, val)
        t0 = time.perf_counter()
        atlas.generate(chart, pack)
        print(f"{name:<20}{time.perf_counter() - t0:>9.1f}{atlas.chart_count:>8}{atlas.utilization:>13.3f}", flush=True)


if __name__ == "__main__":
    main()
