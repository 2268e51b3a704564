"""Image-target recovery on the built-in vase: object-pixel PSNR on the held-out evaluation views
for a light the model represents exactly and for one it cannot, with and without the normal
network. Uses the very fit of ``tests/training/test_optimize.py`` (300 iterations, the sweep's base
settings), so the README's table and the tests' thresholds come from one definition.

    python benchmarks/image_targets.py
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO), str(REPO / "tests"), str(REPO / "tests" / "training")]

CASES = (
    ("studio light (4 lobes, representable), no normal network", {}),
    ("sky light (97 lobes), normal network on", {"target_light": "sky", "normal_network": True}),
    ("sky light (97 lobes), no normal network", {"target_light": "sky"}),
)


def main() -> None:
    from test_optimize import _recover

    for name, overrides in CASES:
        with tempfile.TemporaryDirectory() as d:
            t0 = time.perf_counter()
            meta = _recover(Path(d), **overrides)
            print(f"{name}: {meta['eval_psnr_db']:.2f} dB object-pixel PSNR, {time.perf_counter() - t0:.0f} s", flush=True)


if __name__ == "__main__":
    main()
