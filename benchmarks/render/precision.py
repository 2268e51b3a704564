"""Float32 and bfloat16 against float64 at the extremes: values and gradients of every shading
term, the shadows' visible shares, the light's parametrisation and a mesh's path to the renderer.

The grid, the terms and the measure are ``stages.testing.precision`` (the tests check the measure
and hold the renderer's float32 errors on the quick grid, ``tests/render/test_precision.py``):
every term on the same inputs in float64 (the reference), in float32 and as training runs
bfloat16; per term and precision the worst relative error of the values, of the gradients to each
point's inputs and of the gradients to the light, where each occurs, how far float64 itself moves
there when the input directions turn by float32's roundoff, and the inputs of negligible norm
reported apart. Last line: ``worst_grad_rel_f32=... worst_grad_rel_bf16=...``.

    python -m benchmarks.render.precision             # the full grid (about 90 s on 2 cores)
    python -m benchmarks.render.precision --quick     # a coarser grid (the tests')
"""

from __future__ import annotations

import argparse

import torch

from stages.testing.precision import FULL, QUICK, all_measurements, summary_lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a coarser grid (seconds)")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    for line in summary_lines(all_measurements(QUICK if args.quick else FULL)):
        print(line)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
