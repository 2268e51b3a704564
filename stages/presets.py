"""Named optimisation presets, after TANGO's published demo scripts (see ``../shared/prompts.yaml``
in a developer checkout): a prompt or a variant names one with ``preset:``.

* ``metal`` (gold shoe, silver candle): low-frequency material encoding (3 Fourier features,
  sigma 0.5), no normal offsets, 64 light lobes, roughness initialised to 0.3.
* ``rough`` (wood, wicker, crochet): NeRF encodings (12 frequencies for the material, 10 for the
  normal network), normal offsets on, 32 light lobes, 4 local crops of scale 0.01-0.2 with object
  coverage at least 0.5.
* ``paper``: the paper's stated defaults (1500 iterations, width 256, 32 lobes, decay 0.7 at 500
  and 1000), i.e. the schema defaults.

Speed/accuracy presets, from the measured sweep (``config/sweep.yaml``, README): its knee is one
view per step; past it, iterations buy the most quality per second, then width and lobes, while
more views per step, larger images and crops bought nothing measurable under image targets.

* ``fast``: 300 iterations, 1 view per step, width 64, 16 lobes, no crops;
* ``balanced``: 600 iterations, 1 view per step, width 128, 32 lobes (crops as the prompt's
  preset or the config say).

The demo scripts also move the camera closer for metals (radius 1.5); the camera radius is a
per-mesh ray-cache setting, so set ``raycache: {radius: ...}`` on the mesh if wanted.
"""

from __future__ import annotations

PRESETS: dict[str, dict] = {
    "metal": {
        "material_encoding": "fourier",
        "material_fourier_count": 3,
        "material_fourier_sigma": 0.5,
        "normal_network": False,
        "light_lobes": 64,
        "init_roughness": 0.3,
    },
    "rough": {
        "material_encoding": "nerf",
        "material_frequencies": 12,
        "normal_network": True,
        "normal_encoding": "nerf",
        "normal_frequencies": 10,
        "light_lobes": 32,
        "crops": 4,
        "crop_scale": [0.01, 0.2],
        "crop_coverage": 0.5,
    },
    "paper": {},
    "fast": {
        "iterations": 300,
        "milestones": [180, 255],
        "views_per_step": 1,
        "width": 64,
        "light_lobes": 16,
        "crops": 0,
    },
    "balanced": {
        "iterations": 600,
        "milestones": [360, 510],
        "views_per_step": 1,
        "width": 128,
        "light_lobes": 32,
    },
}
