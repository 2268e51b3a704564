"""Recovery on Mitsuba's ground truth across meshes and presets: the built-in meshes and, in a
developer checkout, every mesh of ``../shared/meshes``, each fitted with the speed/accuracy
presets (``fast``, ``balanced``) and the defaults (``paper``: the schema's defaults, TANGO's
settings), all under image guidance.

Per mesh, once: normalise, the ray cache (32 training views and 24 held-out metric views at 96
pixels, the recovery test's cache), Mitsuba's path-traced targets of one procedural material
(16 spp for training, 128 spp on the metric views, the recovery test's target settings). Per
mesh and preset: the optimisation with the preset's settings (96-pixel images, or
``--resolution``, which also sets the cache's; the preset never sets the image size) and the
metrics stage on the held-out views. Printed per row and written to ``--out`` (CSV): PSNR and
SSIM over fully covered object pixels, the targets' own noise, albedo RMSE (as is and after the
one scale albedo and light share), roughness MAE, the normal's angle, the light's energy against
the environment's, and the optimisation's wall time.

    python -m benchmarks.quality.recovery                                  # every mesh, fast and balanced
    python -m benchmarks.quality.recovery --presets paper --meshes vase,shared:lamp
    python -m benchmarks.quality.recovery --meshes builtin --presets fast --specular-lobe isotropic,split_sum
    python -m benchmarks.quality.recovery --decimate 5000 --shading-normals flat,smooth   # the robustness study
    python -m benchmarks.quality.recovery --meshes shared --presets fast --decimate none,budget,budget:4  # face budgets
    python -m benchmarks.quality.recovery --meshes builtin --presets fast --precision float32,bf16  # bfloat16 networks
    python -m benchmarks.quality.recovery --meshes builtin --presets balanced --set light_prune_after=200  # light "auto"
    python -m benchmarks.quality.recovery --meshes builtin --material metal \
        --variant "before:light_init=broad,light_lr=null" --variant after: --variant "gltf:brdf=gltf"
    python -m benchmarks.quality.recovery --meshes builtin --presets fast --visibility on \
        --variant "off:shadows=false" --variant on:        # shadows off and on, on the same cache

``--visibility`` is the cache's ``raycache.visibility`` (``off`` by default): with ``on`` the cache
carries the visibility bits and a variant ``shadows=false`` fits the same cache without shadows,
so off and on differ only in the shading; ``auto``'s outcome for any threshold follows from the
``self_occlusion`` column.

With ``--decimate N`` (or ``budget``: the face budget of the cache, as the decimate stage's
``mode: budget`` computes it, ``budget:P`` with ``P`` pixels per face; a comma-separated list
fits each level in turn) each mesh is fitted
on its N-face version (MeshLab's quadric collapse, the decimate stage) while Mitsuba renders the
targets from the full-resolution mesh, as the workflow's target stage does: TANGO's robustness
study, graded against the object rather than its approximation.
"""

from __future__ import annotations

import argparse
import csv
import sys
import tempfile
import time
from pathlib import Path

import yaml

from benchmarks.common import RESULTS, fit_recovery, mesh_sources, prepare_recovery
from stages.config.presets import PRESETS

COLUMNS = (
    "mesh",
    "self_occlusion",
    "variant",
    "decimate",
    "faces",
    "full_faces",
    "preset",
    "specular_lobe",
    "shading_normals",
    "precision",
    "iterations",
    "psnr_db",
    "ssim",
    "target_noise_psnr_db",
    "albedo_rmse",
    "albedo_rmse_scaled",
    "roughness_mae",
    "normal_angle_deg_mean",
    "light_energy_ratio",
    "light_lobes",
    "shadows",
    "optimize_s",
)


def parse_variants(specs: list[str]) -> list[tuple[str, dict]]:
    """``--variant NAME:KEY=VALUE[,KEY=VALUE]`` as ``(name, settings)`` (YAML values); none given:
    one unnamed variant without settings."""
    out = []
    for spec in specs:
        name, _, items = spec.partition(":")
        pairs = [item.split("=", 1) for item in items.split(",") if item.strip()]
        out.append((name, {k.strip(): yaml.safe_load(v) for k, v in pairs}))
    return out or [("", {})]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", default="builtin,shared", help="builtin, shared, a built-in, shared:<name>; comma-separated")
    parser.add_argument("--presets", default="fast,balanced", help="comma-separated presets (fast, balanced, paper)")
    parser.add_argument(
        "--specular-lobe", default="fitted", help="comma-separated specular models (isotropic, split_sum, fitted)"
    )
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="optimize settings for every fit (YAML values)")
    parser.add_argument(
        "--variant",
        action="append",
        default=[],
        metavar="NAME:KEY=VALUE[,KEY=VALUE]",
        help="a named set of optimize settings on top of --set; repeat to fit each in turn (default: one, unnamed)",
    )
    parser.add_argument("--precision", default="float32", help="comma-separated network precisions (float32, bf16)")
    parser.add_argument("--shading-normals", default="smooth", help="comma-separated shading normals (flat, smooth)")
    parser.add_argument(
        "--decimate",
        default="none",
        help="comma-separated: none, N (fit each mesh's N-face version) or budget[:P] (its face budget for the "
        "cache, P pixels per face, default 1); full-resolution targets",
    )
    parser.add_argument("--resolution", type=int, default=96, help="pixels of the cached views and of the fitted images")
    parser.add_argument("--visibility", default="off", help="the cache's raycache.visibility (off, auto, on)")
    parser.add_argument("--material", default="wood", help="the procedural target material (wood, metal, chrome, plaster)")
    parser.add_argument("--out", type=Path, default=RESULTS / "recovery.csv")
    parser.add_argument(
        "--preset-costs",
        type=Path,
        help="also write the presets' PSNR and optimisation seconds per mesh as the plan and the quick command read "
        "them (benchmarks/figures/preset_costs.json)",
    )
    args = parser.parse_args()
    presets = [p.strip() for p in args.presets.split(",") if p.strip()]
    for p in presets:
        if p not in PRESETS:
            raise SystemExit(f"unknown preset {p!r}; choose from {', '.join(PRESETS)}")
    rows: list[dict] = []
    args.out.parent.mkdir(parents=True, exist_ok=True)
    for name, source in mesh_sources(args.meshes):
        for level in (x.strip() for x in args.decimate.split(",") if x.strip()):
            decimate = None if level == "none" else level if level.startswith("budget") else int(level)
            with tempfile.TemporaryDirectory() as d:
                work = Path(d)
                t0 = time.perf_counter()
                faces, full_faces, occlusion = prepare_recovery(
                    work, source, args.material, decimate, args.resolution, args.visibility
                )
                took = time.perf_counter() - t0
                print(f"{name}: {faces} faces fitted ({full_faces} rendered), cache and targets in {took:.0f} s", flush=True)
                lobes, normals_list = args.specular_lobe.split(","), args.shading_normals.split(",")
                precisions = args.precision.split(",")
                overrides = {k: yaml.safe_load(v) for k, v in (item.split("=", 1) for item in args.set)}
                combos = [
                    (p, lb, nm, pr, v)
                    for p in presets
                    for v in parse_variants(args.variant)
                    for lb in lobes
                    for nm in normals_list
                    for pr in precisions
                ]
                for preset, lobe, normals, precision, (variant, extra) in combos:
                    row = {
                        "mesh": name,
                        "self_occlusion": round(occlusion, 3),
                        "decimate": level,
                        "faces": faces,
                        "full_faces": full_faces,
                        "variant": variant,
                        **fit_recovery(
                            work, args.material, preset, lobe, normals, args.resolution, precision, {**overrides, **extra}
                        ),
                    }
                    rows.append(row)
                    print(
                        f"  {preset:9s} {variant:8s} {lobe:9s} {normals:6s} {precision:8s} PSNR {row['psnr_db']:.2f} dB  "
                        f"SSIM {row['ssim']:.3f}  (noise {row['target_noise_psnr_db']} dB)  "
                        f"albedo {row['albedo_rmse']:.3f} ({row['albedo_rmse_scaled']})  roughness {row['roughness_mae']:.3f}  "
                        f"normal {row['normal_angle_deg_mean']} deg  light {row['light_energy_ratio']} "
                        f"({row['light_lobes']} lobes)  shadows {row['shadows']}  {row['optimize_s']:.0f} s",
                        flush=True,
                    )
        # the table so far, rewritten whole after each mesh (temp file + rename)
        tmp = args.out.with_suffix(".csv.part")
        with tmp.open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=COLUMNS)
            w.writeheader()
            w.writerows(rows)
        tmp.replace(args.out)
    print(f"wrote {args.out}", flush=True)
    if args.preset_costs:
        write_preset_costs(args.preset_costs, rows, args)
        print(f"wrote {args.preset_costs}", flush=True)


def write_preset_costs(path: Path, rows: list[dict], args) -> None:
    """The presets' held-out PSNR and optimisation seconds per mesh (``preset_costs.json``: what the
    plan quotes for faster presets and the quick command's help), with the command, date, machine
    and conditions they were measured under."""
    import datetime
    import json
    import shlex

    from benchmarks.records import machine

    meshes = list(dict.fromkeys(r["mesh"] for r in rows))
    presets = {}
    for preset in dict.fromkeys(r["preset"] for r in rows):
        by_mesh = {r["mesh"]: r for r in rows if r["preset"] == preset}
        presets[preset] = {
            "psnr_db": [round(float(by_mesh[m]["psnr_db"]), 2) for m in meshes],
            "seconds": [round(float(by_mesh[m]["optimize_s"])) for m in meshes],
        }
    record = {
        "what": "held-out PSNR (object pixels) and optimisation wall time of the presets on the same meshes",
        "command": "python -m benchmarks.quality.recovery " + shlex.join(sys.argv[1:]),
        "measured": f"{datetime.datetime.now(datetime.UTC):%Y-%m-%d}, {machine()}",
        "conditions": f"image guidance (Mitsuba {args.material} targets, {args.resolution}-pixel images, seed 0, "
        f"visibility {args.visibility}, networks {args.precision}): under CLIP guidance the quality cost is not measured",
        "meshes": meshes,
        "presets": presets,
    }
    tmp = path.with_suffix(".part")
    tmp.write_text(json.dumps(record, indent=1) + "\n")
    tmp.replace(path)
    record_preset_costs(record)


def record_preset_costs(costs: dict) -> None:
    """The headline record of the presets' cost (``presets.costs``) from ``preset_costs.json``'s figures."""
    from benchmarks.records import write_record

    meshes = costs["meshes"]
    parts = [
        f"`{name}` {', '.join(f'{s} s' for s in p['seconds'])} ({', '.join(f'{q:.2f}' for q in p['psnr_db'])} dB)"
        for name, p in costs["presets"].items()
    ]
    what = f"the presets' optimisation ({', '.join(meshes)}; {costs['conditions'].split(':')[0]})"
    page = "recovery.md#across-meshes-and-presets"
    write_record("presets.costs", what, "; ".join(parts), f"`{costs['command']}`", page)


if __name__ == "__main__":
    main()
