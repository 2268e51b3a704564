"""What the benchmarks share, in one module: the meshes and fixtures they measure on, how they
time, the machine's measured matrix-multiply rates and the FLOPs counted on real steps (the floor
of a step is its FLOPs at those rates), the training step split into its parts, the recovery fits
on Mitsuba's targets, a finished run's seconds per rule, and the command that runs a benchmark
again in a fresh process. A benchmark imports ``stages`` and this module, never another benchmark.

* **Meshes and fixtures**: :data:`SHARED_MESHES` (``../shared/meshes`` in a developer checkout;
  each benchmark says what it does without them), :func:`knot_mesh`, :func:`mesh_sources`;
  :func:`build_cache` (the paper's ray cache), :func:`vit_b32_random` (CLIP ViT-B-32 with random
  weights: no weights reach our machines and timing does not depend on them),
  :func:`make_optimizer`, :func:`perturbed_field` (a field with detail at texel scale).
* **Timing**: :func:`best_of` (the best of some runs after an untimed one), :func:`paired_ratios`
  (two ways taken in turns, so that the machine's drift falls on both).
* **Rates and FLOPs**: :func:`matmul_rate`, :func:`peak_matmul_rate` (the machine's measured rate),
  :func:`counted` (matrix and pointwise FLOPs of running a function), :func:`step_flops`,
  :func:`eager_flops`, :func:`at_points`, :func:`lever_floor` (a step's floor).
* **The training step**: :func:`step_time`, :func:`timed_split` (:data:`PARTS`), :func:`clip_backward`.
* **Recovery**: :func:`prepare_recovery` and :func:`fit_recovery` (a preset fitted to Mitsuba's
  targets and graded on the held-out views).
* **Runs and processes**: :func:`rule_seconds`, :func:`module_command`.
"""

from __future__ import annotations

import dataclasses
import json
import os
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils.flop_counter import FlopCounterMode

from stages import metrics, optimize
from stages import target as target_stage
from stages.config.presets import PRESETS
from stages.config.sections import (
    DecimateSettings,
    MetricsSettings,
    NormalizeSettings,
    OptimizeSettings,
    RaycacheSettings,
)
from stages.core.provenance import Timer
from stages.geometry.decimation import decimate_mesh, mesh_face_budget
from stages.geometry.meshio import TriMesh, save_ply
from stages.geometry.normalization import normalization_transform, normalize_mesh
from stages.geometry.raycache import RayCache
from stages.geometry.shapes import BUILTIN_NAMES, knot
from stages.guidance.clip import ClipGuide
from stages.guidance.compat import import_open_clip
from stages.guidance.objective import ImageBatch
from stages.imaging.images import compose, gather_points
from stages.model.field import StyleField
from stages.model.networks import Material
from stages.plan import BENCHMARK_GLOBS, MESH_RULES, benchmark_seconds
from stages.raycache import run as raycache_run
from stages.render.color import linear_to_srgb
from stages.render.products import flop_formulas, linear, onednn_available, onednn_products
from stages.testing.recovery import MITSUBA_TARGET, RECOVERY_CACHE
from stages.training.optimizer import Optimizer

# ------------------------------------------------------------------------------ meshes and fixtures
REPO = Path(__file__).resolve().parents[1]
#: a developer checkout's real meshes (their sources in its own SOURCES.md); absent elsewhere
SHARED_MESHES = REPO.parent / "shared" / "meshes"
#: where benchmarks write the tables they keep (git-ignored, as every results/ folder)
RESULTS = REPO / "results" / "benchmarks"


def knot_mesh(samples: int = 2048, sides: int = 20) -> TriMesh:
    """The generated torus-knot tube, normalised (``2 * samples * sides`` faces: 81,920 by default)."""
    v, f = knot(samples=samples, sides=sides)
    return TriMesh(normalization_transform(v).forward(v), f)


def mesh_sources(spec: str) -> list[tuple[str, str]]:
    """``(name, source)`` for each mesh named in ``spec``: ``builtin`` (every built-in mesh),
    ``shared`` (every ``.obj`` of ../shared/meshes), a built-in name, or ``shared:<stem>``."""
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


def build_cache(tmp: Path) -> tuple[Path, str]:
    """The paper's ray cache (8 views at 512 x 512, one evaluation view) of
    ``../shared/meshes/person.obj`` where present, else of the built-in vase, in ``tmp``: the
    training cache's path and the mesh's name."""
    src = SHARED_MESHES / "person.obj"
    name = "person.obj" if src.is_file() else "builtin:vase"
    save_ply(tmp / "mesh.ply", normalize_mesh(src if src.is_file() else "builtin:vase", NormalizeSettings()).mesh)
    rc = RaycacheSettings(views=8, resolution=512, eval_azimuths=1, eval_elevations_deg=(0.0,), eval_resolution=64)
    raycache_run(tmp / "mesh.ply", tmp / "train.npz", tmp / "eval.npz", tmp / "rc.json", rc)
    return tmp / "train.npz", name


def vit_b32_random(bf16: bool = False, tower: str = "batched", device: str = "cpu") -> ClipGuide:
    """ViT-B-32 with random weights drawn from seed 0 (every call the same weights)."""
    open_clip = import_open_clip()
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        model = open_clip.create_model("ViT-B-32", pretrained=None)
    return ClipGuide(
        model,
        open_clip.get_tokenizer("ViT-B-32"),
        image_size=224,
        weights_id="ViT-B-32 random (timing only)",
        test_only=True,
        device=device,
        bf16=bf16,
        tower=tower,
    )


def make_optimizer(settings: OptimizeSettings, train: Path, guide: ClipGuide) -> Optimizer:
    """The optimiser of ``settings`` on the ray cache ``train`` under ``guide``, on the CPU."""
    return Optimizer(settings, RayCache(train), "a person made of wood", "cpu", guide=guide)


def perturbed_field(**settings) -> tuple[StyleField, OptimizeSettings]:
    """The ``fast`` preset's networks (width 64, 6 NeRF frequencies; ``settings`` on top) with
    their SVBRDF weights perturbed by seeded noise (std 0.3): a field with detail at texel scale,
    untrained. The field (in eval mode) and its settings."""
    s = OptimizeSettings(**{"width": 64, "material_frequencies": 6, "normal_frequencies": 6, **settings})
    field = StyleField(s.field_settings()).eval()
    noise = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for p in field.svbrdf.parameters():
            p.add_(0.3 * torch.randn(p.shape, generator=noise))
    return field, s


# ------------------------------------------------------------------------------------------ timing
def best_of(fn: Callable[[], object], repeats: int = 5) -> float:
    """The best of ``repeats`` timings of ``fn()`` (seconds) after one untimed call."""
    fn()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return min(ts)


def paired_ratios(first: list[float], second: list[float]) -> list[float]:
    """``first[i] / second[i]``: the ratios of two ways timed in turns (pair by pair, so that the
    machine's drift from minute to minute falls on both alike); report their median."""
    return [a / b for a, b in zip(first, second, strict=True)]


# -------------------------------------------------------------------------------- rates and FLOPs
def matmul_rate(
    rows: int, inner: int, cols: int, dtype: torch.dtype = torch.float32, repeats: int = 5, kernels: str = "best"
) -> float:
    """FLOP/s of the best of ``repeats`` ``(rows x inner) @ (inner x cols)`` products in ``dtype``
    by ``kernels``: ``aten`` (``torch.mm``: MKL's for float32), ``onednn`` (float32 only: the
    linear layer of ``stages.render.products``, which training routes there where it is faster) or
    ``best``: the faster of the two (ATen's alone where oneDNN does not apply)."""
    if kernels == "best":
        both = dtype == torch.float32 and onednn_available()
        rates = [matmul_rate(rows, inner, cols, dtype, repeats, k) for k in (("aten", "onednn") if both else ("aten",))]
        return max(rates)
    a, b = torch.randn(rows, inner, dtype=dtype), torch.randn(inner, cols, dtype=dtype)
    bt = b.T.contiguous()

    def product():
        if kernels == "aten":
            return torch.mm(a, b)
        with onednn_products(True):
            return linear(a, bt)

    return 2.0 * rows * inner * cols / best_of(product, repeats)


def peak_matmul_rate(dtype: torch.dtype, n: int = 2048, kernels: str = "best") -> float:
    """The machine's peak matrix-multiply rate for this build and thread count: square ``n x n``
    products in ``dtype`` (oneDNN uses AVX-512 BF16 / AMX for bfloat16 where the CPU has them;
    float32 by the faster of ATen's and oneDNN's kernels, :func:`matmul_rate`)."""
    return matmul_rate(n, n, n, dtype, kernels=kernels)


class PointwiseCounter(TorchDispatchMode):
    """Counts one FLOP per output element of every aten op tagged pointwise (activations, the
    shading's arithmetic, LayerNorm's pieces, the optimizer's update): what ``FlopCounterMode``,
    which counts only matrix products and convolutions, leaves out."""

    def __init__(self) -> None:
        super().__init__()
        self.flops = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        if torch.Tag.pointwise in func.tags:
            for t in out if isinstance(out, tuple | list) else (out,):
                if isinstance(t, torch.Tensor):
                    self.flops += t.numel()
        return out


def counted(fn: Callable[[], object]) -> tuple[int, int]:
    """``(matrix FLOPs, pointwise FLOPs)`` of running ``fn()`` (forward and backward as it runs them;
    oneDNN's linear layers counted as ATen's, ``stages.render.products.flop_formulas``)."""
    with FlopCounterMode(display=False, custom_mapping=flop_formulas()) as mm, PointwiseCounter() as pw:
        fn()
    return mm.get_total_flops(), pw.flops


def mlp_flops_per_point(field) -> float:
    """Forward+backward FLOPs per point of the encodings' MLPs: 2 per MAC forward, 4 backward
    (input and weight gradients), from the Linear layers that run."""
    macs = sum(m.in_features * m.out_features for m in field.modules() if isinstance(m, torch.nn.Linear))
    return 6.0 * macs


# -------------------------------------------------------------------------------- the training step
#: the parts of a step that :func:`timed_split` times
PARTS = ("gather", "mlp", "shading", "clip", "optimizer")
#: nothing compiled (the FLOPs of a lever are counted on such a twin: :func:`eager_flops`)
EAGER = {"compile_shading": "off", "compile_networks": "off", "compile_static": "off"}
#: both bfloat16 levers off (the defaults are auto: bfloat16 where the machine has it natively)
FP32 = {"bf16": "off", "bf16_networks": "off"}


def step_time(opt: Optimizer, steps: int) -> tuple[float, float]:
    """Mean seconds per step and mean points per step over ``steps`` steps after a warm-up
    (steps differ in their view and crops, hence in points: means pair time with work)."""
    opt.step(Timer())  # warm-up
    ts, pts = [], []
    for _ in range(steps):
        t0 = time.perf_counter()
        opt.step(Timer())
        ts.append(time.perf_counter() - t0)
        pts.append(opt.points_last)
    return statistics.mean(ts), statistics.mean(pts)


def clip_backward(guide: ClipGuide, x: torch.Tensor, text: torch.Tensor) -> None:
    """CLIP's part of the step: the similarities of 1 global image and the crops (none where
    ``x`` holds one image), as one batch through the tower (``ClipGuide.similarities``), backward
    to the images."""
    sum(guide.similarities([x[:1], x[1:]] if len(x) > 1 else [x], text)).backward()


def timed_split(opt: Optimizer, steps: int) -> dict[str, float]:
    """Time the parts of a step with the graph cut between them (same functions as the loop); the
    shading includes the shadows' visible shares where the view has them and runs the field's
    BRDF (glTF's from its base colour and metallic, or TANGO's sum), compiled where the step's is;
    a first, untimed pass compiles it. Where the networks are compiled into the renderer's graph
    (``compile_networks``) there is nothing to cut: the ``mlp`` part is both and ``shading`` NaN."""
    s = opt.settings
    together = opt.compiled.field_graph is not None
    parts = {k: [] for k in PARTS}
    for i in range(steps + 1):
        with onednn_products(opt.onednn, opt.transposes):  # as the step routes its float32 linear layers
            times, points = _split_once(opt, together, s)
        if i == 0:
            continue
        t0, t1, t2, t3, t4, t5, t6, t7 = times
        parts["gather"].append(t1 - t0)
        parts["mlp"].append((t2 - t1) + (t6 - t5) + ((t3 - t2) + (t5 - t4) if together else 0.0))
        parts["shading"].append(float("nan") if together else (t3 - t2) + (t5 - t4))
        parts["clip"].append(t4 - t3)
        parts["optimizer"].append(t7 - t6)
    return {k: statistics.mean(v) for k, v in parts.items()} | {"points": points}


def _split_once(opt: Optimizer, together: bool, s: OptimizeSettings) -> tuple[tuple[float, ...], int]:
    """One step of :func:`timed_split`, cut between its parts: the times at each cut, and its points."""
    t0 = time.perf_counter()
    v = opt.views[int(opt.np_rng.integers(len(opt.views)))]
    specs = opt.image_specs(v)
    needed, lookups = gather_points(specs, v.index)
    sel = torch.from_numpy(needed)
    pts, nrm, view = v.points[sel], v.normals[sel], v.view[sel]
    bg = torch.zeros(3, s.image_size, s.image_size)
    t1 = time.perf_counter()
    shadows = v.shadows  # the shading's shadows, as the real step casts them (None: none)
    visibility = None if shadows is None else (lambda lt, sh=shadows, sel=sel: lt.shadowed_by(sh, sel))
    if together:  # one compiled graph: nothing to cut it at; its time is the networks' column
        mlp_out, leaves = [], []
        color = linear_to_srgb(opt.compiled(pts, nrm, view, visibility=visibility).shading.rgb)
    else:  # the field's own forward pass, cut between its networks and its renderer
        mat, normal = opt.field.surface(pts, nrm, view)
        mlp_out = [normal, *mat.parameters().values()]  # the BRDF's parameters, in head order
        leaves = [x if x is None else x.detach().requires_grad_() for x in mlp_out]
    t2 = time.perf_counter()
    if not together:
        color = linear_to_srgb(opt.compiled.shade(Material.of(mat.brdf, *leaves[1:]), leaves[0], view, visibility=visibility).rgb)
    c_leaf = color.detach().requires_grad_()
    t3 = time.perf_counter()
    imgs = [compose(c_leaf, lk, sp, bg) for lk, sp in zip(lookups, specs, strict=True)]
    loss, _ = opt.guidance.loss(ImageBatch(imgs[:1], imgs[1:]), None)
    opt.adamw.zero_grad(set_to_none=True)
    loss.backward()
    t4 = time.perf_counter()
    color.backward(c_leaf.grad)
    t5 = time.perf_counter()
    # no normal network: no grad; glTF's BRDF shades from base and metallic, not albedo and specular
    pairs = [
        (o, x.grad) for o, x in zip(mlp_out, leaves, strict=True) if o is not None and o.requires_grad and x.grad is not None
    ]
    if pairs:
        torch.autograd.backward([o for o, _ in pairs], [g for _, g in pairs])
    t6 = time.perf_counter()
    opt.adamw.step()
    t7 = time.perf_counter()
    return (t0, t1, t2, t3, t4, t5, t6, t7), len(needed)


def step_flops(opt: Optimizer, guide: ClipGuide, steps: int, images: int = 5) -> dict[str, float]:
    """FLOPs of one training step, counted (not estimated) on ``steps`` real steps: the matrix
    products of CLIP (its forward and backward to the step's ``images``, counted alone on random
    images) and of the rest (the MLPs forward and backward), and the pointwise FLOPs of
    everything (shading, activations, normalisations, the optimizer); ``points``: the mean
    points the networks shaded in those steps."""
    total_mm, total_pw, points = 0, 0, 0
    for _ in range(steps):
        mm, pw = counted(lambda: opt.step(Timer()))
        total_mm, total_pw, points = total_mm + mm, total_pw + pw, points + opt.points_last
    text = guide.embed_text("a person")
    x = torch.rand(images, 3, guide.image_size, guide.image_size, requires_grad=True)
    clip_mm, clip_pw = counted(lambda: clip_backward(guide, x, text))
    total_mm, total_pw = total_mm / steps, total_pw / steps
    return {
        "clip": clip_mm,
        "mlp": total_mm - clip_mm,
        "pointwise": total_pw,
        "clip_pointwise": clip_pw,
        "total": total_mm + total_pw,
        "points": points / steps,
    }


def eager_flops(settings: OptimizeSettings, train: Path, guide: ClipGuide, steps: int, points: float) -> dict[str, float]:
    """:func:`step_flops` of ``settings``'s step, counted on a twin with nothing compiled (the same
    arithmetic): a compiled function run under the counters' dispatch modes is skipped by dynamo
    from then on, so that a later compilation of it would run eager (or fail, compiled as one
    graph; torch 2.13). The networks' and the pointwise FLOPs, which grow with the points shaded,
    (but CLIP's pointwise) are scaled from the twin's ``steps`` to the measured steps' mean ``points``."""
    twin = make_optimizer(dataclasses.replace(settings, **EAGER), train, guide)
    return at_points(step_flops(twin, guide, steps), points)


def at_points(counts: dict[str, float], points: float) -> dict[str, float]:
    """:func:`step_flops`'s ``counts`` for a step of ``points`` points: the networks' and the
    pointwise FLOPs scaled from the counted steps' points, but CLIP's pointwise (its norms and
    activations), which does not grow with them."""
    scale = points / counts["points"]
    pointwise = counts["clip_pointwise"] + (counts["pointwise"] - counts["clip_pointwise"]) * scale
    mlp = counts["mlp"] * scale
    return counts | {"mlp": mlp, "pointwise": pointwise, "total": counts["clip"] + mlp + pointwise, "points": points}


def lever_floor(counts: dict[str, float], clip_bf16: bool, networks_bf16: bool, peak: dict[str, float], native: bool) -> float:
    """The FLOP floor of one lever's step: CLIP's counted FLOPs at the peak rate of its precision
    plus the rest's (the networks' products and the pointwise) at the networks'; NaN where a part
    runs bfloat16 on a CPU that only emulates it (no floor: the emulated rate is not a ceiling)."""
    if (clip_bf16 or networks_bf16) and not native:
        return float("nan")
    rate = {True: peak["bf16"], False: peak["fp32"]}
    return counts["clip"] / rate[clip_bf16] + (counts["mlp"] + counts["pointwise"]) / rate[networks_bf16]


# ------------------------------------------------------------------------------------------ recovery
def prepare_recovery(
    work: Path, source: str, material: str, decimate: int | str | None = None, resolution: int = 96, visibility: str = "off"
) -> tuple[int, int, float]:
    """Normalise ``source`` (and decimate it to ``decimate`` faces, or with ``"budget"`` to the
    face budget of the recovery cache, the decimate stage's ``mode: budget``), build the recovery
    cache on the mesh to fit and render the Mitsuba targets of the full-resolution mesh into
    ``work`` (the cache with ``raycache.visibility`` = ``visibility``); returns the fitted and the
    full-resolution face counts and the fitted mesh's median self-occlusion."""
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


def recovery_folder(work: Path, preset: str, lobe: str = "fitted", normals: str = "smooth", precision: str = "float32") -> Path:
    """Where :func:`fit_recovery` writes the optimisation of these settings (its ``field.pt``)."""
    return work / f"{preset}-{lobe}-{normals}-{precision}"


def fit_recovery(
    work: Path,
    material: str,
    preset: str,
    lobe: str = "fitted",
    normals: str = "smooth",
    resolution: int = 96,
    precision: str = "float32",
    overrides: dict | None = None,
) -> dict:
    """Optimise with ``preset`` under image guidance on the targets :func:`prepare_recovery` made and
    grade the field on the held-out metric views; returns one row of the recovery table (the
    torch threads: ``TANGO_THREADS``, default 2)."""
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
    out = recovery_folder(work, preset, lobe, normals, precision)
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


# ----------------------------------------------------------------------------- runs and processes
def rule_seconds(experiment: Path) -> dict[str, list[float]]:
    """rule -> the wall seconds of each of its jobs in ``experiment`` (a ``results/<name>`` folder):
    its cells', the report's, and those of the mesh work its cells used (the ray caches and
    targets their optimisations read; every normalisation and decimation of their meshes)."""
    results = experiment.parent
    metas = [json.loads(p.read_text()) for p in experiment.glob("*/*/*/optimize/meta.json")]
    used = set()  # the mesh work folders, results/meshes/<mesh>/<key>
    for m in metas:
        for item in (m.get("inputs") or {}).values():
            parts = Path(item["path"]).parts
            if "meshes" in parts:
                used.add(results.resolve() / Path(*parts[parts.index("meshes") : parts.index("meshes") + 3]))
    meshes = {d.parent.name for d in used}
    out: dict[str, list[float]] = {}

    def add(rule: str, files) -> None:
        for tsv in files:
            seconds = benchmark_seconds(tsv)
            if seconds is not None:
                out.setdefault(rule, []).append(seconds)

    for rule, pattern in BENCHMARK_GLOBS.items():
        if rule == "raycache":
            add(rule, [f for f in results.glob(pattern) if f.resolve().parents[1] in used])
        elif rule in MESH_RULES:
            add(rule, [f for f in results.glob(pattern) if f.parents[2].name in meshes])
        else:
            add(rule, experiment.glob(pattern.split("/", 1)[1]))
    add("target", [f for f in results.glob("meshes/*/*/benchmarks/target-*.tsv") if f.resolve().parents[1] in used])
    add("optimize", experiment.glob("*/*/*/benchmarks/optimize.tsv"))
    return out


def module_command(module: str, *args: str) -> list[str]:
    """The command that runs the benchmark ``module`` (its ``__spec__.name``, as ``python -m``
    ran it) with ``args`` in a fresh process of this Python; run it with ``cwd=REPO``."""
    return [sys.executable, "-m", module, *args]
