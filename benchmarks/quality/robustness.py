"""The robustness study's table: each mesh beside its decimated levels, the drop cause by cause.

Reads a finished run of a robustness config (``config/robustness.yaml``: each mesh at full
resolution and decimated) and prints, per mesh, level, prompt and variant:

* the level: faces, the decimation's two-sided Hausdorff distance (normalised frame, radius 1) and
  its shape (shares of sliver faces and of folds, :func:`stages.geometry.decimation.shape_quality`);
* ``unjudged``: the share of the original's object pixels (held-out metric views) that the level's
  mesh no longer covers: the targets are always the full-resolution object's (the target stage
  renders the normalised mesh for every level), so a cell is graded where its mesh meets the
  object, and a silhouette that shrank leaves these pixels out of its figures;
* ``train``: the recovery's held-out PSNR under the training light (the metrics stage);
* ``relit``/``ceiling``: under the first relighting environment, the recovery's scaled PSNR and
  the ceiling (the true material and normals of the object in our renderer, shadowed by the
  level's own mesh, under the same fitted light; the relight stage);
* the drop of each against the original, and the recovery's own gap (ceiling - relit).

A level whose ceiling stays within 1 dB of the original's and whose recovery falls further has a
recovery problem; a ceiling that falls says that the renderer or the light model reaches less of
Mitsuba's picture of that mesh. The last line: ``worst_drop_5k_db=...`` (the largest relit drop
at 5,000 faces or fewer among meshes whose ceilings agree within 1 dB) and
``worst_ceiling_drop_db=...``.

    python -m benchmarks.quality.robustness --configfile config/robustness.yaml

``--decimation`` measures the decimation's settings instead, without training: for each shared
mesh, face count and setting, the level's Mitsuba truth (wood, the metric views) against the
original's (``geometry``, as above) beside its Hausdorff distance and shape, and the original's own
Monte Carlo noise; the two renders take independent seeds and their measured noise is taken out
of ``geometry`` (the figure is the geometry's change alone):

    python -m benchmarks.quality.robustness --decimation --meshes horse person lamp vase --faces 5000,2000
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from benchmarks.common import REPO, SHARED_MESHES


def _read(path: Path) -> dict:
    return json.loads(path.read_text()) if path.is_file() else {}


def _first(text) -> float:
    return float(str(text).split("/")[0]) if text not in (None, "") else math.nan


def truth_images(cache_npz: Path, target_npz: Path) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per metric view: the truth's linear radiance as a full ``(W*W, 3)`` image (NaN where no
    hit) and the full-coverage mask."""
    from stages.geometry.raycache import RayCache
    from stages.imaging.targets import TargetSet
    from stages.reference.targets import ALPHA_FULL

    cache = RayCache(cache_npz)
    targets = TargetSet(target_npz, cache)
    return _images(cache, targets.arrays["radiance"], targets.arrays["coverage"] >= ALPHA_FULL)


def _images(cache, radiance: np.ndarray, full: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per view of ``cache``: per-hit ``radiance (N, 3)`` and ``full (N,)`` (covered fully) as a
    ``(W*W, 3)`` image (NaN where no hit) and a ``(W*W,)`` mask."""
    images, masks = [], []
    for i in range(len(cache)):
        h, lo, hi = cache.view(i), cache.arrays["offsets"][i], cache.arrays["offsets"][i + 1]
        img = np.full((cache.width * cache.width, 3), np.nan)
        mask = np.zeros(cache.width * cache.width, bool)
        img[h.pixel], mask[h.pixel] = radiance[lo:hi], full[lo:hi]
        images.append(img)
        masks.append(mask)
    return images, masks


def unjudged_share(original: tuple, level: tuple) -> float:
    """The share of the original's fully covered pixels that the level's hits do not cover."""
    ours = sum(int(m.sum()) for m in original[1])
    missed = sum(int((a & ~b).sum()) for a, b in zip(original[1], level[1], strict=True))
    return missed / max(ours, 1)


def geometry_psnr(original: tuple, level: tuple, noise_mse: float = 0.0) -> float:
    """sRGB PSNR of the level's truth against the original's over the pixels both cover fully;
    ``noise_mse``: the two renders' Monte Carlo noise (independent seeds: the sum of their mean
    squared errors), taken out of the difference (infinite where nothing is left)."""
    from stages.render.color import srgb_encode

    errs = []
    for a, ma, b, mb in zip(original[0], original[1], level[0], level[1], strict=True):
        both = ma & mb
        errs.append((srgb_encode(a[both]) - srgb_encode(b[both])) ** 2)
    mse = float(np.concatenate(errs).mean()) - noise_mse
    return 10 * math.log10(1 / mse) if mse > 0 else math.inf


def level_row(cfg, results: Path, mesh: str, prompt: str, variant: str) -> dict:
    from stages.geometry.decimation import shape_quality
    from stages.geometry.meshio import load_ply

    keys = cfg.mesh_work_keys(mesh)
    work = REPO / "results" / "meshes" / mesh
    dec = _read(work / keys.get("decimate", "-") / "decimate" / "meta.json").get("stats") or {}
    ply = (
        work / keys["decimate"] / "decimate" / "mesh.ply"
        if "decimate" in keys
        else work / keys["normalize"] / "normalize" / "mesh.ply"
    )
    cell = results / mesh / prompt / variant
    metrics = _read(cell / "metrics" / "metrics.json").get("image_target") or {}
    relit = (_read(cell / "relight" / "meta.json").get("stats") or {}).get("ground_truth") or [{}]
    mesh_obj = load_ply(ply)
    return {
        "mesh": mesh,
        "faces": len(mesh_obj.faces),
        "hausdorff": dec.get("hausdorff_max", 0.0),
        "shape": shape_quality(mesh_obj),
        "train": metrics.get("psnr_db", math.nan),
        "relit": relit[0].get("psnr_scaled_db", math.nan),
        "ceiling": relit[0].get("ceiling_psnr_db", math.nan),
        "cache": work / keys["raycache"] / "raycache" / "metrics.npz",
        "target": work / keys["target"] / "target" / (cfg.target_material(prompt, variant) or "") / "metrics.npz",
    }


#: the decimation settings --decimation compares (DecimateSettings fields; "default" first)
DECIMATION_OPTIONS = {
    "default": {},
    "quality 0": {"quality_threshold": 0.0},
    "quality 1": {"quality_threshold": 1.0},
    "no normal check": {"preserve_normal": False},
}


def _views(mesh, spp: int, material: str, seed: int = 0):
    """The metric views' truth of ``mesh`` as :func:`truth_images` gives it, and its noise PSNR."""
    import tempfile

    from stages.config.sections import RaycacheSettings, TargetSettings
    from stages.geometry.raycache import RayCache, metric_views, trace_views
    from stages.geometry.tracing import EmbreeTracer
    from stages.reference.targets import ALPHA_FULL, TargetRenderer

    rc = RaycacheSettings()
    arrays, _ = trace_views(mesh, metric_views(rc), EmbreeTracer(mesh))
    with tempfile.TemporaryDirectory() as d:
        np.savez(Path(d) / "m.npz", **arrays)
        cache = RayCache(Path(d) / "m.npz")
        t = TargetRenderer(mesh, material, TargetSettings(texture_size=1024)).render_cache(cache, spp, seed)
        views = _images(cache, t.radiance, t.coverage >= ALPHA_FULL)
    return views, float((t.noise_mse * t.pixels).sum() / max(t.pixels.sum(), 1))


def decimation_study(meshes: list[str], faces: list[int], spp: int) -> None:
    import dataclasses

    from stages.config.sections import DecimateSettings, NormalizeSettings
    from stages.geometry.decimation import decimate_mesh
    from stages.geometry.normalization import normalize_mesh

    print(f"{'mesh':<10}{'faces':>7}  {'setting':<18}{'Hausdorff':>10}{'slivers':>9}{'folds':>8}{'geometry dB':>12}")
    for name in meshes:
        full = normalize_mesh(SHARED_MESHES / f"{name}.obj", NormalizeSettings()).mesh
        truth, noise = _views(full, spp, "wood", seed=0)
        print(f"{name:<10}{len(full.faces):>7}  original: its truth's noise {10 * math.log10(1 / noise):.2f} dB", flush=True)
        for target in faces:
            for label, change in DECIMATION_OPTIONS.items():
                settings = dataclasses.replace(DecimateSettings(target_faces=target, hausdorff_samples=20000), **change)
                result = decimate_mesh(full, settings)
                q = result.stats["shape_after"]
                level, level_noise = _views(result.mesh, spp, "wood", seed=1)  # independent noise, taken out
                geo = geometry_psnr(truth, level, noise + level_noise)
                line = f"{name:<10}{len(result.mesh.faces):>7}  {label:<18}{result.stats['hausdorff_max']:>10.4f}"
                print(line + f"{100 * q['slivers']:>8.1f}%{100 * q['folds']:>7.2f}%{geo:>12.2f}", flush=True)


def main() -> None:
    from stages.config.workflow import experiment_name, load_config_file, read_yaml

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--configfile", type=Path, default=REPO / "config" / "robustness.yaml")
    parser.add_argument("--results", type=Path, help="the run's folder (default: results/<experiment>)")
    parser.add_argument("--decimation", action="store_true", help="compare the decimation's settings (no training)")
    parser.add_argument("--meshes", nargs="*", default=["horse", "person", "lamp", "vase"], help="--decimation: shared meshes")
    parser.add_argument("--faces", default="5000,2000", help="--decimation: face counts, comma-separated")
    parser.add_argument("--spp", type=int, default=64, help="--decimation: Mitsuba's samples per pixel")
    args = parser.parse_args()
    if args.decimation:
        decimation_study(args.meshes, [int(f) for f in args.faces.split(",")], args.spp)
        return
    cfg = load_config_file(args.configfile)
    results = args.results or REPO / "results" / experiment_name(read_yaml(args.configfile), [args.configfile])
    levels: dict[str, list[str]] = {}
    for dec, orig in cfg.decimation_pairs().items():
        levels.setdefault(orig, []).append(dec)
    cells = {(c.mesh, c.prompt, c.variant) for c in cfg.cells}
    head = f"{'mesh':<12}{'variant':<12}{'faces':>7}{'Hausdorff':>10}{'slivers':>8}{'folds':>7}{'unjudged':>9}"
    head += f"{'train':>8}{'drop':>6}{'relit':>8}{'drop':>6}{'ceiling':>8}{'drop':>6}{'gap':>6}"
    print(f"{results}; dB, drops against the original; unjudged: the object's pixels the level's mesh misses")
    print(head)
    worst = {"train": -math.inf, "relit": -math.inf, "ceiling": -math.inf}
    for orig, decs in levels.items():
        for prompt, variant in sorted({(p, v) for m, p, v in cells if m == orig}):
            if not (results / orig / prompt / variant / "relight" / "meta.json").is_file():
                continue
            base = level_row(cfg, results, orig, prompt, variant)
            base_truth = truth_images(base["cache"], base["target"])
            rows = [base] + [level_row(cfg, results, d, prompt, variant) for d in decs if (d, prompt, variant) in cells]
            for r in sorted(rows, key=lambda r: -r["faces"]):
                if not math.isfinite(r["relit"]):
                    print(f"{r['mesh']:<12}{variant:<12}{r['faces']:>7}  (not run yet)")
                    continue
                unjudged = 0.0 if r is base else unjudged_share(base_truth, truth_images(r["cache"], r["target"]))
                drops = {k: base[k] - r[k] for k in ("train", "relit", "ceiling")}
                line = f"{r['mesh']:<12}{variant:<12}{r['faces']:>7}{r['hausdorff']:>10.4f}{100 * r['shape']['slivers']:>7.1f}%"
                line += f"{100 * r['shape']['folds']:>6.2f}%{100 * unjudged:>8.2f}%{r['train']:>8.2f}{drops['train']:>6.2f}"
                line += f"{r['relit']:>8.2f}{drops['relit']:>6.2f}{r['ceiling']:>8.2f}{drops['ceiling']:>6.2f}"
                print(line + f"{r['ceiling'] - r['relit']:>6.2f}", flush=True)
                if r is not base and abs(r["faces"] - 5000) <= 50:  # the 5,000-face levels
                    worst["ceiling"] = max(worst["ceiling"], drops["ceiling"])
                    if abs(drops["ceiling"]) <= 1.0:
                        worst["train"] = max(worst["train"], drops["train"])
                        worst["relit"] = max(worst["relit"], drops["relit"])
    print(" ".join(f"worst_{k}_drop_5k_db={v:.2f}" for k, v in worst.items()))


if __name__ == "__main__":
    main()
