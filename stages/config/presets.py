"""Named optimisation presets, after TANGO's published demo scripts (see ``../shared/prompts.yaml``
in a developer checkout): a prompt or a variant names one with ``preset:``.

* ``metal`` (gold shoe, silver candle): low-frequency material encoding (3 Fourier features,
  sigma 0.5), no normal offsets, 64 light lobes, roughness initialised to 0.3.
* ``rough`` (wood, wicker, crochet): NeRF encodings (12 frequencies for the material, 10 for the
  normal network), normal offsets on, 32 light lobes, 4 local crops of scale 0.01-0.2 with object
  coverage at least 0.5.
* ``paper``: the paper's stated settings, written out (1500 iterations, AdamW lr 5e-4 with decay
  0.7 at 500 and 1000, one view per step with one 224-pixel image and 4 crops, width 256, NeRF
  encodings with 12/10 frequencies, normal offsets on, 32 lobes): equal to the schema defaults,
  which a test checks, so that ``preset: paper`` on a variant restores them over a base section.

Speed/accuracy presets: each is a point measured by the speed/accuracy sweep
(``config/sweep.yaml`` runs the variants ``fast`` and ``balanced`` with exactly these presets; the
docs/measurements/sweep.md quotes the figures). The sweep runs under **image guidance** (MSE against procedural target
renders, because no CLIP weights reach our machines), so:

* the presets hold every optimisation setting of the measured point, including the schedule tuned
  there (AdamW lr 5e-3, decay 0.3 at 60% and 85% of the iterations) and the network sizes;
* they leave out, on purpose: the image size (the sweep renders 96-pixel images; CLIP takes the
  size its model was trained at, 224 for ViT-B-32, so the preset keeps whatever the config says),
  the guidance and its target, and the ray-cache settings (per mesh, not per cell);
* the learning rate was tuned under image targets and is ten times the paper's 5e-4 for CLIP
  guidance; whether it suits CLIP guidance is not measured here. Under CLIP, set ``lr: 5.0e-4`` and
  ``gamma: 0.7`` beside the preset to keep the paper's schedule.

* ``fast``: 300 iterations, 1 view per step, width 64, 16 lobes, 6 NeRF frequencies for the
  material, no normal offsets, no crops (the sweep's knee);
* ``balanced``: 600 iterations, 1 view per step, width 128, 32 lobes, otherwise as ``fast``.

On Mitsuba's ground truth the sweep's one mesh cannot choose between them (seeds spread by up to
2 dB there, and the built-in vase is the one mesh where ``balanced`` loses);
``benchmarks/quality/recovery.py`` measures both on the built-in and the shared meshes (``balanced``
ahead by 1.8-3.6 dB on ten of eleven for 2.6x the time, 2026-11-22; docs/measurements/recovery.md).

The demo scripts also move the camera closer for metals (radius 1.5); the camera radius is a
per-mesh ray-cache setting, so set ``raycache: {radius: ...}`` on the mesh if wanted.
"""

from __future__ import annotations

#: the preset of a run that names none (``python -m stages.quick``, the Blender add-on): the measured
#: knee of speed against quality
DEFAULT_PRESET = "fast"

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
    "paper": {
        "iterations": 1500,
        "lr": 5e-4,
        "milestones": [500, 1000],
        "gamma": 0.7,
        "views_per_step": 1,
        "crops": 4,
        "width": 256,
        "material_encoding": "nerf",
        "material_frequencies": 12,
        "normal_network": True,
        "normal_encoding": "nerf",
        "normal_frequencies": 10,
        "light_lobes": 32,
    },
    "fast": {
        "iterations": 300,
        "lr": 5e-3,
        "milestones": [180, 255],
        "gamma": 0.3,
        "views_per_step": 1,
        "crops": 0,
        "width": 64,
        "material_encoding": "nerf",
        "material_frequencies": 6,
        "normal_network": False,
        "light_lobes": 16,
    },
    "balanced": {
        "iterations": 600,
        "lr": 5e-3,
        "milestones": [360, 510],
        "gamma": 0.3,
        "views_per_step": 1,
        "crops": 0,
        "width": 128,
        "material_encoding": "nerf",
        "material_frequencies": 6,
        "normal_network": False,
        "light_lobes": 32,
    },
}
