"""Each target's ceiling under each transport: the true material in our renderer, under the light
that brings the environment into it, against Mitsuba's truth on the held-out metric views.

For every target stage of a results folder (``meshes/<mesh>/<key>/target/<material>/``, with its
metric views' ray cache) and every environment it was rendered under (the training environment
and each of ``target.relight_environments``): our renderer given the true material and shading
normals (the BRDF ``--brdf``, its model lobe), shadowed by the cache's stored visibility, under
the environment's fit with ``--suns`` suns each (``0``: SG lobes alone; ``auto``: as many as the
environment holds by ``optimize.suns: auto``'s criterion; a count), against the truth over the
fully covered object pixels, raw and after one scale per channel. What a perfect recovery of the
material could reach with that transport. ``--bounces 0,1`` adds one bounce of the mesh's own light
(:mod:`stages.render.light.bounce`): each face side's diffuse radiance under the same light, the
true material at its centroid (the target's procedural material baked again on the cache's mesh),
reflected once at every hit through ``--bounce-samples`` first hits.

``--depths 2,3`` says which part of the transport holds what is left: Mitsuba renders the metric
views again with its paths cut at each ``max_depth`` (2: direct light only, 3: one bounce; the
target stage's own scene, material and seeds, so the renders differ by the cut paths alone), and
each row is also graded against those renders (``vs depth D``: our renderer's error on the light
it models) and each cut render against the full truth (``depth D vs full``: the light of the
later bounces, which no ceiling with D - 1 bounces can reach).

    python -m benchmarks.quality.ceilings results/demo-offline
    python -m benchmarks.quality.ceilings results/demo-offline --suns 0,auto --lobes 32 --brdf gltf
    python -m benchmarks.quality.ceilings results/demo-offline --suns auto --bounces 0,1 --depths 2,3
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


def target_dirs(results: Path, only: list[str] | None) -> list[Path]:
    """Every finished target stage under ``results`` (a ``meta.json`` beside its files)."""
    found = []
    for meta in sorted(results.rglob("target/*/meta.json")):
        d = meta.parent
        name = f"{d.parents[2].name}/{d.name}"  # meshes/<mesh>/<key>/target/<material>
        if (d / "metrics.npz").is_file() and (not only or name in only):
            found.append(d)
    return found


def sender_shading(target: Path, cache, meta: dict, brdf: str):
    """The face sides of the cache's mesh as senders (:class:`~stages.model.bounce.FaceSides`) and
    their shading under a light (:func:`~stages.imaging.relit.surface_shading`): the target's true
    material, baked again from its procedural material and settings, at each side's centroid
    (:func:`~stages.reference.targets.truth_at_senders`)."""
    from stages.config.sections import TargetSettings
    from stages.imaging.relit import surface_shading
    from stages.model.bounce import FaceSides
    from stages.reference.targets import ground_truth, truth_at_senders
    from stages.render import brdf as brdfs

    mesh = cache.mesh()
    truth = ground_truth(mesh, target.name, TargetSettings.from_dict(meta["settings"]))
    senders = FaceSides(mesh, cache.visibility_directions)
    maps = truth_at_senders(truth, mesh, mesh)
    model = brdfs.get(brdf)
    parts = {k: maps[k][senders.rows] for k in (*model.parameters, "normal")}
    return senders, surface_shading(senders, parts, model, model.model_lobe, "cpu")


def cut_truths(target: Path, meta: dict, cache, depths: tuple[int, ...]) -> list[dict[int, object]]:
    """Mitsuba's renders of the metric views of ``cache`` with the paths cut at each of ``depths``
    (``max_depth``), as the target stage rendered the full truths
    (:func:`~stages.reference.target_job.render_targets`: its mesh, material, spp and seeds), one
    per truth in its order (the training environment, then each relit one): ``[{depth: radiance
    (N, 3)}]``.

    Raises:
        SystemExit: the mesh the target stage rendered is not where its record says."""
    import dataclasses

    from stages.config.sections import TargetSettings
    from stages.geometry.meshio import load_ply
    from stages.reference.target_job import metric_seeds
    from stages.reference.targets import TargetRenderer

    settings = TargetSettings.from_dict(meta["settings"])
    rendered = Path(meta.get("rendered_mesh", {}).get("path", ""))
    if rendered.suffix != ".ply" or not rendered.is_file():
        raise SystemExit(
            f"{target}: --depths renders the mesh the target stage rendered, and its meta.json names "
            f"{str(rendered) or 'none'} (run from the folder the workflow ran in, or rerun the target stage)"
        )
    mesh = load_ply(rendered)
    lights = metric_seeds(settings)
    out: list[dict[int, object]] = [{} for _ in lights]
    truth = None
    for depth in depths:
        cut = dataclasses.replace(settings, max_depth=depth)
        for i, (env, light_seed) in enumerate(lights):
            renderer = TargetRenderer(mesh, target.name, cut, environment=env, truth=truth)
            truth = renderer.truth
            out[i][depth] = renderer.render_cache(cache, settings.metric_spp, light_seed).radiance
    return out


def ceilings(
    target: Path,
    suns: list[str],
    lobes: int,
    iterations: int,
    brdf: str,
    samples: int,
    bounces=(0,),
    bounce_samples: int = 32,
    depths: tuple[int, ...] = (),
) -> list[dict]:
    """The ceilings of one target stage's metric views, per environment and transport."""
    import torch

    from stages.config.sections import OptimizeSettings
    from stages.geometry.normals import NormalSpec
    from stages.geometry.raycache import RayCache
    from stages.imaging.relit import graded_figures, truth_radiance
    from stages.imaging.targets import FULL_COVERAGE, TargetSet, load_relit
    from stages.imaging.views import ViewStore
    from stages.model.bounce import bounce_table, with_bounce
    from stages.model.lights import fit_environment
    from stages.model.lights.sun import resolve_suns
    from stages.render import brdf as brdfs

    meta = json.loads((target / "meta.json").read_text())
    cache = RayCache(Path(meta["inputs"]["metrics"]["path"]))  # the metric views' cache it was rendered for
    truth = TargetSet(target / "metrics.npz", cache)
    store = ViewStore(cache, torch.device("cpu"), NormalSpec("smooth"), shadows=True)
    cases = [(meta["settings"]["environment"], truth.arrays["radiance"], truth.arrays["coverage"])]
    if (target / "relit.npz").is_file():
        cases += [(r.environment, r.radiance, r.coverage) for r in load_relit(target / "relit.npz", cache)]
    share = OptimizeSettings().suns_share
    model = brdfs.get(brdf)
    senders = shade = None
    cut = cut_truths(target, meta, cache, depths) if depths else [{} for _ in cases]
    rows = []
    for (environment, radiance, coverage), renders in zip(cases, cut, strict=True):
        full = torch.from_numpy(coverage.astype("float32") >= FULL_COVERAGE)
        goal = torch.from_numpy(radiance.astype("float32"))[full]
        goals = {d: torch.from_numpy(r.astype("float32"))[full] for d, r in renders.items()}
        later = {d: graded_figures(g, goal) for d, g in goals.items()}  # each cut render against the full truth
        for setting in suns:
            count, _ = resolve_suns(
                setting if setting == "auto" else int(setting), environment, cache.visibility_directions, share
            )
            t0 = time.perf_counter()
            light, record = fit_environment(environment, lobes, iterations, count, samples)
            for bounce in bounces:
                t1 = time.perf_counter()
                lit = light
                if bounce:
                    if senders is None:
                        senders, shade = sender_shading(target, cache, meta, brdf)
                    lit = with_bounce(light, bounce_table(senders, shade, light, bounce_samples))
                with torch.no_grad():
                    ours = truth_radiance(truth, store, lit, model.model_lobe, model)[full]
                rows.append(
                    {
                        "target": f"{target.parents[2].name}/{target.name}",
                        "environment": environment,
                        "suns": setting,
                        "count": count,
                        "bounces": bounce,
                        **graded_figures(ours, goal),
                        "against_depth": {d: graded_figures(ours, g) for d, g in goals.items()},
                        "depth_vs_full": later,
                        "seconds": time.perf_counter() - t1 + (t1 - t0 if bounce == bounces[0] else 0.0),
                        "fit": record,
                    }
                )
    return rows


def _line(row: dict, depths: tuple[int, ...]) -> str:
    """One printed row: its figures raw and scaled, then against each cut render and each cut
    render against the full truth (raw / scaled)."""
    sun = f"{row['suns']}:{row['count']}" if row["suns"] == "auto" else row["suns"]
    line = (
        f"{row['target']:<22} {row['environment']:<18} {sun:>5} {row['bounces']:>6} {row['psnr_db']:8.2f} "
        f"{row['psnr_scaled_db']:10.2f} {row['seconds']:6.1f}"
    )
    for d in depths:
        a, b = row["against_depth"][d], row["depth_vs_full"][d]
        line += f" {a['psnr_db']:7.2f}/{a['psnr_scaled_db']:<7.2f} {b['psnr_db']:8.2f}/{b['psnr_scaled_db']:<8.2f}"
    return line


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", type=Path)
    parser.add_argument("--targets", nargs="*", help="mesh/material names (all when left out)")
    parser.add_argument("--suns", default="0,auto", help="transports: comma-separated 0, auto or counts")
    parser.add_argument("--lobes", type=int, default=32)
    parser.add_argument("--iterations", type=int, default=400)
    parser.add_argument("--brdf", default="gltf")
    parser.add_argument("--samples", type=int, default=8, help="directions per sun")
    parser.add_argument("--bounces", default="0", help="transports: comma-separated 0 (direct light) and 1 (one bounce)")
    parser.add_argument("--bounce-samples", type=int, default=32, help="first hits per point of a bounce")
    parser.add_argument(
        "--depths",
        default="",
        help="Mitsuba's max_depth values to grade against too (2: direct light, 3: one bounce), comma-separated",
    )
    parser.add_argument("--out", type=Path, help="write the rows as JSON here")
    args = parser.parse_args()
    rows = []
    bounces = tuple(int(b) for b in args.bounces.split(",") if b)
    depths = tuple(int(d) for d in args.depths.split(",") if d)
    head = f"{'target':<22} {'environment':<18} {'suns':>5} {'bounce':>6} {'raw dB':>8} {'scaled dB':>10} {'s':>6}"
    head += "".join(f" {f'vs depth {d}':>15} {f'depth {d} vs full':>17}" for d in depths)
    print(head, flush=True)
    for d in target_dirs(args.results, args.targets):
        suns = [s for s in args.suns.split(",") if s]
        for row in ceilings(d, suns, args.lobes, args.iterations, args.brdf, args.samples, bounces, args.bounce_samples, depths):
            rows.append(row)
            print(_line(row, depths), flush=True)
    if args.out:
        args.out.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
