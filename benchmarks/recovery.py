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

    python benchmarks/recovery.py                                  # every mesh, fast and balanced
    python benchmarks/recovery.py --presets paper --meshes vase,shared:lamp
    python benchmarks/recovery.py --meshes builtin --presets fast --specular-lobe isotropic,split_sum
    python benchmarks/recovery.py --decimate 5000 --shading-normals flat,smooth   # the robustness study
    python benchmarks/recovery.py --meshes shared --presets fast --decimate none,budget,budget:4  # face budgets
    python benchmarks/recovery.py --meshes builtin --presets fast --precision float32,bf16  # bfloat16 networks
    python benchmarks/recovery.py --meshes builtin --presets balanced --set light_prune_after=200  # light "auto"
    python benchmarks/recovery.py --meshes builtin --material metal \
        --variant "before:light_init=broad,light_lr=null" --variant after: --variant "gltf:brdf=gltf"
    python benchmarks/recovery.py --meshes builtin --presets fast --visibility on \
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
import dataclasses
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
SHARED_MESHES = REPO.parent / "shared" / "meshes"
sys.path[:0] = [str(REPO), str(REPO / "benchmarks")]

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


def mesh_sources(spec: str) -> list[tuple[str, str]]:
    """``(name, source)`` for each mesh named in ``spec``: ``builtin`` (every built-in mesh),
    ``shared`` (every ``.obj`` of ../shared/meshes), a built-in name, or ``shared:<stem>``."""
    from stages.geometry.shapes import BUILTIN_NAMES

    out: list[tuple[str, str]] = []
    for item in filter(None, (s.strip() for s in spec.split(","))):
        if item == "builtin":
            out += [(n, f"builtin:{n}") for n in BUILTIN_NAMES]
        elif item == "shared":
            if not SHARED_MESHES.is_dir():
                print(f"no {SHARED_MESHES}: the shared meshes are skipped (a developer checkout has them)", flush=True)
                continue
            out += [(f"shared:{p.stem}", str(p)) for p in sorted(SHARED_MESHES.glob("*.obj"))]
        elif item.startswith("shared:"):
            path = SHARED_MESHES / f"{item.split(':', 1)[1]}.obj"
            if not path.is_file():
                names = ", ".join(p.stem for p in SHARED_MESHES.glob("*.obj"))
                raise SystemExit(f"{path}: no such mesh (the shared meshes are {names})")
            out.append((item, str(path)))
        elif item in BUILTIN_NAMES:
            out.append((item, f"builtin:{item}"))
        else:
            raise SystemExit(f"unknown mesh {item!r}: use builtin, shared, one of {', '.join(BUILTIN_NAMES)} or shared:<name>")
    return out


def prepare(
    work: Path, source: str, material: str, decimate: int | str | None = None, resolution: int = 96, visibility: str = "off"
) -> tuple[int, int, float]:
    """Normalise ``source`` (and decimate it to ``decimate`` faces, or with ``"budget"`` to the
    face budget of the recovery cache, the decimate stage's ``mode: budget``), build the recovery
    cache on the mesh to fit and render the Mitsuba targets of the full-resolution mesh into
    ``work`` (the cache with ``raycache.visibility`` = ``visibility``); returns the fitted and the
    full-resolution face counts and the fitted mesh's median self-occlusion."""
    from protocols import MITSUBA_TARGET, RECOVERY_CACHE

    from stages import target as target_stage
    from stages.config.sections import DecimateSettings, NormalizeSettings
    from stages.geometry.decimation import decimate_mesh, mesh_face_budget
    from stages.geometry.meshio import save_ply
    from stages.geometry.normalization import normalize_mesh
    from stages.raycache import run as raycache_run

    full = normalize_mesh(source, NormalizeSettings()).mesh
    save_ply(work / "full.ply", full)
    mesh = full
    sizes = {k: resolution for k in ("resolution", "eval_resolution", "metrics_resolution")}
    cache = dataclasses.replace(RECOVERY_CACHE, **sizes, visibility=visibility)
    if isinstance(decimate, str) and decimate.startswith("budget"):  # "budget" or "budget:<pixels per face>"
        per_face = float(decimate.split(":", 1)[1]) if ":" in decimate else 1.0
        decimate = mesh_face_budget(full, cache, per_face).faces
    if decimate is not None and decimate < len(full.faces):
        mesh = decimate_mesh(full, DecimateSettings(enabled=True, target_faces=decimate)).mesh
    save_ply(work / "mesh.ply", mesh)
    raycache_run(work / "mesh.ply", work / "train.npz", work / "eval.npz", work / "rc.json", cache, work / "metrics.npz")
    target_stage.run(work / "train.npz", work / "metrics.npz", material, work / "target", MITSUBA_TARGET, work / "full.ply")
    occlusion = json.loads((work / "rc.json").read_text())["self_occlusion"]["median"]
    return len(mesh.faces), len(full.faces), occlusion


def fit(
    work: Path,
    material: str,
    preset: str,
    lobe: str = "fitted",
    normals: str = "smooth",
    resolution: int = 96,
    precision: str = "float32",
    overrides: dict | None = None,
) -> dict:
    """Optimise with ``preset`` under image guidance on the prepared targets and grade the field on
    the held-out metric views; returns one row of the table."""
    import torch

    from stages import metrics, optimize
    from stages.config.presets import PRESETS
    from stages.config.sections import MetricsSettings, OptimizeSettings

    settings = OptimizeSettings(
        **{
            **PRESETS[preset],
            "guidance": "image",
            "target_material": material,
            "target_renderer": "mitsuba",
            "image_size": resolution,
            "eval_width": resolution,
            "checkpoint_every": 100_000,
            "specular_lobe": lobe,
            "shading_normals": normals,
            "bf16_networks": "on" if precision == "bf16" else "off",
            **(overrides or {}),
        }
    )
    torch.set_num_threads(int(os.environ.get("TANGO_THREADS", "2")))
    out = work / f"{preset}-{lobe}-{normals}-{precision}"
    t0 = time.perf_counter()
    optimize.run(work / "train.npz", work / "eval.npz", "", out, settings, "cpu", targets_path=work / "target" / "train.npz")
    seconds = time.perf_counter() - t0
    meta = json.loads((out / "meta.json").read_text())
    targets = work / "target" / "metrics.npz"
    graded = MetricsSettings(clip=False)
    m = metrics.run(out / "field.pt", work / "metrics.npz", "", [""], out / "metrics", graded, "cpu", targets)
    m = m["image_target"]
    mat = m["material"]
    return {
        "preset": preset,
        "specular_lobe": lobe,
        "shading_normals": normals,
        "precision": meta["network_precision"],
        "iterations": settings.iterations,
        "psnr_db": round(m["psnr_db"], 2),
        "ssim": round(m["ssim"], 3),
        "target_noise_psnr_db": round(m["target_noise_psnr_db"], 1),
        "albedo_rmse": round(mat["albedo_rmse"], 3),
        "albedo_rmse_scaled": None if mat["albedo_rmse_scaled"] is None else round(mat["albedo_rmse_scaled"], 3),
        "roughness_mae": round(mat.get("roughness_mae", float("nan")), 3),
        "normal_angle_deg_mean": round(mat["normal_angle_deg_mean"], 1),
        "light_energy_ratio": "/".join(f"{x:.2f}" for x in mat["light_energy_ratio"]),
        "light_lobes": meta["light_lobes"],
        "shadows": meta["shadows"]["cast"],
        "optimize_s": round(seconds, 1),
    }


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
    parser.add_argument("--out", type=Path, default=REPO / "results" / "benchmarks" / "recovery.csv")
    args = parser.parse_args()
    from stages.config.presets import PRESETS

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
                faces, full_faces, occlusion = prepare(work, source, args.material, decimate, args.resolution, args.visibility)
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
                        **fit(work, args.material, preset, lobe, normals, args.resolution, precision, {**overrides, **extra}),
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


if __name__ == "__main__":
    main()
