"""The recovery protocol the benchmarks measure and the tests hold floors for: the Mitsuba targets
(fewer samples than the target stage's default), the ray cache and the 300-iteration fit of the
speed/accuracy sweep's base settings, and the helpers that build a scene and fit it. One home for
both: ``benchmarks.quality.image_targets`` imports it, as does ``benchmarks.common`` (the targets
and cache of ``benchmarks.quality.recovery`` and ``benchmarks.assets.lod``), and so do the recovery
tests of ``tests/training/test_optimize.py``.

``threads``: the torch threads a fit may use (a test worker's share of the cores; None leaves
torch's own choice).
"""

from __future__ import annotations

import torch

from .. import metrics, optimize
from .. import target as target_stage
from ..config.sections import MetricsSettings, NormalizeSettings, OptimizeSettings, RaycacheSettings, TargetSettings
from ..geometry.meshio import save_ply
from ..geometry.normalization import normalize_mesh
from ..raycache import run as raycache_run


def _threads(threads: int | None) -> None:
    if threads is not None:
        torch.set_num_threads(threads)


#: the Mitsuba targets of the recovery test and benchmark (fewer samples than the stage's default;
#: no relit ground truth: these fits are graded under the training light)
MITSUBA_TARGET = TargetSettings(spp=16, metric_spp=128, texture_size=512, relight_environments=())

#: the fit both recovery helpers share (300 iterations, the sweep's base settings)
RECOVERY = {
    "iterations": 300,
    "guidance": "image",
    "lr": 5e-3,
    "milestones": (180, 255),
    "gamma": 0.3,
    "width": 64,
    "image_size": 96,
    "crops": 0,
    "views_per_step": 2,
    "normal_network": False,
    "material_frequencies": 6,
    "light_lobes": 16,
    "eval_width": 96,
    "checkpoint_every": 1000,
}
RECOVERY_CACHE = RaycacheSettings(
    views=32,
    resolution=96,
    std=3.0,
    eval_azimuths=8,
    eval_elevations_deg=(-20.0, 10.0, 35.0),
    eval_resolution=96,
    metrics_resolution=96,
)


def mitsuba_scene(tmp_path, mesh: str = "builtin:vase", material: str = "wood", target=None) -> dict:
    """The mesh's ray caches and Mitsuba's path-traced targets of ``material`` (the target stage
    with ``target`` settings) in ``tmp_path``: what :func:`fit_mitsuba` fits and grades."""
    save_ply(tmp_path / "mesh.ply", normalize_mesh(mesh, NormalizeSettings()).mesh)
    raycache_run(
        tmp_path / "mesh.ply",
        tmp_path / "train.npz",
        tmp_path / "eval.npz",
        tmp_path / "rc.json",
        RECOVERY_CACHE,
        tmp_path / "metrics.npz",
    )
    tdir = tmp_path / "target"
    summary = target_stage.run(tmp_path / "train.npz", tmp_path / "metrics.npz", material, tdir, target or TargetSettings())
    return {"dir": tmp_path, "material": material, "target": summary}


def fit_mitsuba(scene: dict, name: str = "out", threads: int | None = None, **overrides) -> dict:
    """Fit ``scene``'s targets (:func:`mitsuba_scene`), then grade the field with the metrics stage
    on the held-out metric views. Returns ``{"optimize": meta, "metrics": image_target figures,
    "target": summary}``."""
    d, tdir = scene["dir"], scene["dir"] / "target"
    settings = OptimizeSettings(**{**RECOVERY, "target_material": scene["material"], "target_renderer": "mitsuba", **overrides})
    _threads(threads)
    meta = optimize.run(d / "train.npz", d / "eval.npz", "", d / name, settings, "cpu", targets_path=tdir / "train.npz")
    m = metrics.run(
        d / name / "field.pt",
        d / "metrics.npz",
        "",
        [""],
        d / f"{name}-metrics",
        MetricsSettings(clip=False),
        "cpu",
        tdir / "metrics.npz",
    )
    return {"optimize": meta, "metrics": m["image_target"], "target": scene["target"]}


def recover_mitsuba(
    tmp_path, mesh: str = "builtin:vase", material: str = "wood", target=None, threads: int | None = None, **overrides
) -> dict:
    """:func:`mitsuba_scene` and one :func:`fit_mitsuba` of it."""
    return fit_mitsuba(mitsuba_scene(tmp_path, mesh, material, target), threads=threads, **overrides)


def recover_sg(tmp_path, threads: int | None = None, **overrides) -> dict:
    """Fit the image targets of a procedural material under an SG light, rendered by our own SG
    renderer, on the built-in vase (300 iterations, the sweep's base settings) and return the
    optimisation's metadata."""
    save_ply(tmp_path / "vase.ply", normalize_mesh("builtin:vase", NormalizeSettings()).mesh)
    raycache_run(tmp_path / "vase.ply", tmp_path / "train.npz", tmp_path / "eval.npz", tmp_path / "rc.json", RECOVERY_CACHE)
    settings = {
        **RECOVERY,
        "target_material": "wood",
        "target_renderer": "sg",
        **overrides,
    }
    _threads(threads)
    return optimize.run(tmp_path / "train.npz", tmp_path / "eval.npz", "", tmp_path / "out", OptimizeSettings(**settings), "cpu")
