"""The relighting error budget of every graded cell of a results folder: which recovered component
costs how many dB, under the training light and under each relight environment.

A cell is graded when its relight stage had Mitsuba's relit ground truth (image-guided cells with
``target.relight_environments``); the stage's ``meta.json`` names the field, the metric views'
ray cache, their targets (which carry the true material) and the relit truth. Per cell and light
(:func:`stages.imaging.relit.relight_budget`): the field's render against Mitsuba's truth over the
fully covered object pixels of the held-out metric views, raw and after one scale per channel,
then with recovered components replaced by their truth, each alone and cumulatively in the order
printed (under the training light the learned light first, replaced by the SG fit of the training
environment; a relit render already takes the new environment's fit). With everything replaced
the render is the ceiling, the relight stage's ``ceiling_psnr_db``. A cell trained with one bounce
(``optimize.bounces``) bounces in every render of its budget, off the surface that render shows.

    python -m benchmarks.quality.relight_budget results/demo-offline
    python -m benchmarks.quality.relight_budget results/demo-offline --cells vase/wood --out budget.json
    python -m benchmarks.quality.relight_budget results/demo-offline --shadow-rays 64   # a sharp sun's shadows traced

Columns: ``alone`` is the figure with that component alone replaced (and its gain over the
recovered render), ``cumulative`` the figure with it and every component above replaced (and its
gain over the row above: the cumulative gains add up to the gap to the ceiling). Figures in dB,
``raw / scaled``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


def graded_cells(results: Path, only: list[str] | None) -> list[tuple[str, dict]]:
    """``(cell name, relight meta)`` of every relight stage under ``results`` that was graded."""
    found = []
    for meta_path in sorted(results.rglob("relight/meta.json")):
        meta = json.loads(meta_path.read_text())
        if "truth" not in meta.get("inputs", {}):
            continue
        name = str(meta_path.parent.parent.relative_to(results))
        if only and not any(name == c or name.startswith(c + "/") for c in only):
            continue
        found.append((name, meta))
    return found


def cell_budget(meta: dict, device: str, shadow_rays: int = 0) -> list[dict]:
    """The budget of one graded cell from its relight stage's metadata; ``shadow_rays`` > 0: lobes
    too sharp for the cache's visibility directions take that many shadow rays per point (the
    relight stage's grading, like training, takes the quadrature's nearest directions for them)."""
    import torch

    from stages.geometry.raycache import RayCache
    from stages.imaging.relit import BudgetCase, relight_budget
    from stages.imaging.targets import TargetSet, load_relit
    from stages.imaging.views import ViewStore
    from stages.model.checkpoint import load_field

    inputs = {k: Path(v["path"]) for k, v in meta["inputs"].items()}
    field, _ = load_field(inputs["field"], torch.device(device))
    field.eval()
    cache = RayCache(inputs["metrics_cache"])
    store = ViewStore(cache, torch.device(device), field.normals, shadows=field.shadows)
    for i in range(len(store) if shadow_rays and store.shadows else 0):
        store[i].shadows.samples = shadow_rays
    truth = TargetSet(inputs["targets"], cache)
    target_meta = json.loads((inputs["targets"].parent / "meta.json").read_text())
    cases = [
        BudgetCase(
            target_meta["settings"]["environment"],
            "training",
            truth.arrays["radiance"].astype("float32"),
            truth.arrays["coverage"].astype("float32"),
            target_meta["views"]["metrics"]["noise_psnr_db"],
        )
    ]
    relit = load_relit(inputs["truth"], cache)
    cases += [BudgetCase(r.environment, "relit", r.radiance, r.coverage, r.noise_psnr_db) for r in relit]
    s = meta["settings"]
    return relight_budget(field, store, truth, cases, s["lobes"], s["fit_iterations"])


def _pair(fig: dict, key: str = "psnr") -> str:
    return f"{fig[f'{key}_db']:6.2f} / {fig[f'{key}_scaled_db']:6.2f}"


def print_budget(name: str, budget: list[dict]) -> None:
    for case in budget:
        scale = ", ".join(f"{x:.2f}" for x in case["recovered"]["scale"])
        noise = f"truth's noise {case['noise_psnr_db']:.1f} dB"
        bounce = case["bounce"]
        transport = "one bounce" if bounce["bounces"] else "direct light" + (f": {bounce['why']}" if "why" in bounce else "")
        print(f"\n{name}: {case['role']} light {case['environment']} ({case['pixels']:,} pixels, {noise}, {transport})")
        print(f"  {'component':<10} {'alone':>17} {'gain':>17}   {'cumulative':>17} {'gain':>17}   scale (cumulative)")
        print(f"  {'recovered':<10} {_pair(case['recovered']):>17} {'':>17}   {'':>17} {'':>17}   {scale}")
        for sw in case["swaps"]:
            a, c = sw["alone"], sw["cumulative"]
            sc = ", ".join(f"{x:.2f}" for x in c["scale"])
            print(f"  {sw['component']:<10} {_pair(a):>17} {_pair(a, 'gain'):>17}   {_pair(c):>17} {_pair(c, 'gain'):>17}   {sc}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("results", type=Path, help="a results folder (the experiment's results.dir/<experiment>)")
    ap.add_argument("--cells", default=None, help="comma-separated cells (mesh/prompt or mesh/prompt/variant); default all")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", type=Path, default=None, help="write the budgets as JSON")
    ap.add_argument(
        "--shadow-rays",
        type=int,
        default=0,
        help="shadow rays per point for lobes too sharp for the visibility directions (0: the quadrature, as graded)",
    )
    args = ap.parse_args()
    only = args.cells.split(",") if args.cells else None
    cells = graded_cells(args.results, only)
    if not cells:
        raise SystemExit(
            f"{args.results}: no relight stage graded against Mitsuba's relit truth "
            "(image-guided cells with target.relight_environments)"
        )
    out = {}
    for name, meta in cells:
        t0 = time.perf_counter()
        out[name] = cell_budget(meta, args.device, args.shadow_rays)
        print_budget(name, out[name])
        print(f"  ({time.perf_counter() - t0:.1f} s)")
    if args.out:
        args.out.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
