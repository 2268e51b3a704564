"""optimize: learn material, normal map and light so renders of a mesh match a prompt (TANGO).

Per step: pick ``views_per_step`` views of the cached pool, build one global image per view and
``crops`` local crops with enough object coverage (:mod:`stages.imaging`), shade only the cached
hits those images need (:class:`~stages.field.StyleField`), and minimise minus the cosine
similarity between CLIP's averaged image embedding and the prompt's, for the global images and
the crops, summed. AdamW with step decay. With ``guidance: image`` the loss is instead the mean
squared error against renders of a known procedural material and light (:mod:`stages.procedural`),
which verifies the whole optimisation without CLIP weights.

Atomic checkpoints every ``checkpoint_every`` iterations (networks, light, optimiser, scheduler,
RNG states, loss history); a rerun after a kill resumes from the last one and ends with the same
parameters as an uninterrupted run. Outputs (in ``--out-dir``): ``field.pt``, ``loss.csv``,
``loss.png``, ``renders/*.png`` from the evaluation views, ``light.npz`` and ``meta.json``.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import io
import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F

from .errors import ConfigError, StageInputError, stage_errors
from .field import StyleField
from .imaging import background, compose, gather_points, global_spec, index_map, linear_to_srgb, sample_crops
from .networks import equirect_directions
from .procedural import LIGHTS, MATERIALS, procedural_light, procedural_material
from .provenance import (
    ORIGIN_KEY,
    Timer,
    add_torch_arguments,
    apply_torch_arguments,
    atomic_path,
    checked_origin,
    metadata,
    origin_record,
    staged_outputs,
    write_json_atomic,
)
from .raycache import RayCache
from .render.shading import face_viewer, shade
from .settings import Settings

log = logging.getLogger(__name__)

RENDER_KINDS = ("rgb", "diffuse", "specular", "roughness", "normal", "normal_original")


@dataclass(frozen=True, kw_only=True)
class OptimizeSettings(Settings):
    """Settings of the optimize stage (config section ``optimize``; presets and variants override).

    Defaults follow TANGO's paper and demo scripts where they state a value.
    """

    section = "optimize"
    # schedule
    iterations: int = 1500
    lr: float = 5e-4
    weight_decay: float = 0.0
    milestones: tuple[int, ...] = (500, 1000)
    gamma: float = 0.7
    seed: int = 0
    # images per step
    views_per_step: int = 1
    image_size: int = 224
    supersample: int = 1
    crops: int = 4
    crop_scale: tuple[float, float] = (0.01, 0.2)
    crop_coverage: float = 0.3
    crop_max_tries: int = 20
    background: str = "black"
    # networks
    symmetry: bool = False
    width: int = 256
    material_encoding: str = "nerf"
    material_frequencies: int = 12
    material_fourier_count: int = 128
    material_fourier_sigma: float = 0.5
    specular: bool = True
    init_specular: float | None = None
    init_roughness: float | None = None
    min_roughness: float = 0.01
    normal_network: bool = True
    normal_encoding: str = "nerf"
    normal_frequencies: int = 10
    normal_fourier_count: int = 128
    normal_fourier_sigma: float = 0.5
    normal_max_delta: float = 0.3
    light_lobes: int = 32
    light_rgb: bool = True
    light_energy: float = 6.25
    light_init_sharpness: float | None = None
    # guidance
    guidance: str = "clip"
    clip_model: str = "ViT-B-32"
    clip_pretrained: str = "openai"
    clip_checkpoint: str | None = None
    clip_tiny_test: bool = False
    bf16: bool = False
    target_material: str = "wood"
    target_light: str = "studio"
    # outputs
    checkpoint_every: int = 100
    eval_width: int = 256

    def __post_init__(self) -> None:
        p = []
        if self.iterations < 1:
            p.append(f"iterations must be >= 1, got {self.iterations}")
        if self.guidance not in ("clip", "image"):
            p.append(f"guidance must be 'clip' or 'image', got {self.guidance!r}")
        for name in ("material_encoding", "normal_encoding"):
            if getattr(self, name) not in ("nerf", "fourier", "none"):
                p.append(f"{name} must be nerf, fourier or none, got {getattr(self, name)!r}")
        if self.background not in ("black", "white", "noise"):
            p.append(f"background must be black, white or noise, got {self.background!r}")
        lo, hi = self.crop_scale
        if not 0 < lo <= hi <= 1:
            p.append(f"crop_scale must satisfy 0 < lo <= hi <= 1, got {self.crop_scale}")
        if not 0 < self.min_roughness < 1:
            p.append(f"min_roughness must be in (0, 1), got {self.min_roughness}")
        if self.target_material not in MATERIALS:
            p.append(f"target_material must be one of {MATERIALS}, got {self.target_material!r}")
        if self.target_light not in LIGHTS:
            p.append(f"target_light must be one of {LIGHTS}, got {self.target_light!r}")
        if self.views_per_step < 1 or self.crops < 0 or self.supersample < 1 or self.checkpoint_every < 1:
            p.append("views_per_step, supersample and checkpoint_every must be >= 1 and crops >= 0")
        if p:
            raise ConfigError("optimize settings: " + "; ".join(p))

    def digest(self) -> str:
        """Hash of the settings that shape training (a checkpoint resumes only under the same)."""
        d = {k: v for k, v in self.to_dict().items() if k not in ("checkpoint_every", "eval_width")}
        return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


# --------------------------------------------------------------------------------- view access
@dataclass
class CachedView:
    """Tensors of one cached view on the device: hit ``points``, flat ``normals`` and unit
    ``view`` directions (surface -> eye) ``(N, 3)``, plus the ``(W, W)`` hit-index map."""

    points: torch.Tensor
    normals: torch.Tensor
    view: torch.Tensor
    index: np.ndarray
    mask: np.ndarray


class ViewStore:
    def __init__(self, cache: RayCache, device) -> None:
        self.cache = cache
        self.device = device
        self._views: dict[int, CachedView] = {}

    def __len__(self) -> int:
        return len(self.cache)

    @property
    def width(self) -> int:
        return self.cache.width

    def __getitem__(self, i: int) -> CachedView:
        if i not in self._views:
            h = self.cache.view(i)
            idx = index_map(h.pixel, self.cache.width)
            self._views[i] = CachedView(
                torch.from_numpy(h.point).to(self.device),
                torch.from_numpy(h.normal).to(self.device),
                torch.from_numpy(-h.direction).to(self.device),
                idx,
                idx >= 0,
            )
        return self._views[i]


# ------------------------------------------------------------------------------------ the loop
@dataclass
class History:
    rows: list[dict] = field(default_factory=list)


class Objective:
    """The guidance: CLIP similarity, or image error against a procedural target."""

    def __init__(self, settings: OptimizeSettings, prompt: str, device, guide=None) -> None:
        """``guide``: an already loaded :class:`~stages.guidance.ClipGuide` (else loaded from
        the settings)."""
        self.s = settings
        self.device = device
        self.guide = None
        self.weights_id = None
        self.test_only = False
        if settings.guidance == "clip":
            from .guidance import ClipSpec, load_clip

            self.guide = guide or load_clip(
                ClipSpec(
                    model=settings.clip_model,
                    pretrained=settings.clip_pretrained,
                    checkpoint=settings.clip_checkpoint,
                    tiny_test=settings.clip_tiny_test,
                ),
                device=device,
                bf16=settings.bf16,
            )
            if self.guide.image_size != settings.image_size:
                raise ConfigError(
                    f"optimize.image_size is {settings.image_size} but CLIP {self.guide.weights_id} "
                    f"takes {self.guide.image_size}x{self.guide.image_size} images"
                )
            self.text = self.guide.embed_text(prompt)
            self.weights_id = self.guide.weights_id
            self.test_only = self.guide.test_only
        else:
            self.target_light = procedural_light(settings.target_light, device=device)
            self.weights_id = f"image targets: procedural {settings.target_material} under {settings.target_light} light"
        self.origin = origin_record(guidance=settings.guidance, weights=self.weights_id, test_only=self.test_only, prompt=prompt)

    def target_colors(self, points, normals, view) -> torch.Tensor:
        flip = (normals * view).sum(-1, keepdim=True) < 0
        n = face_viewer(torch.where(flip, -normals, normals), view)
        m = procedural_material(self.s.target_material, points)
        return shade(n, view, m.albedo, self.target_light, m.specular, m.roughness).rgb

    def loss(self, globals_, crops, globals_t=None, crops_t=None) -> tuple[torch.Tensor, dict]:
        if self.guide is not None:
            sim_g = self.guide.similarity(torch.stack(globals_), self.text)
            loss = -sim_g
            stats = {"similarity_global": float(sim_g.detach())}
            if crops:
                sim_c = self.guide.similarity(torch.stack(crops), self.text)
                loss = loss - sim_c
                stats["similarity_crops"] = float(sim_c.detach())
            return loss, stats
        loss = F.mse_loss(torch.stack(globals_), torch.stack(globals_t))
        if crops:
            loss = loss + F.mse_loss(torch.stack(crops), torch.stack(crops_t))
        return loss, {}


def _rng_state(np_rng: np.random.Generator, tgen: torch.Generator) -> dict:
    return {"numpy": np_rng.bit_generator.state, "torch": tgen.get_state()}


def _save_checkpoint(path: Path, **state) -> None:
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


class Optimizer:
    """One optimisation run: state, step function, checkpointing."""

    def __init__(self, settings: OptimizeSettings, train: RayCache, prompt: str, device, guide=None) -> None:
        self.s = settings
        self.device = torch.device(device)
        self.views = ViewStore(train, self.device)
        self.prompt = prompt
        self.field = StyleField(settings).to(self.device)
        self.opt = torch.optim.AdamW(self.field.parameters(), lr=settings.lr, weight_decay=settings.weight_decay)
        self.sched = torch.optim.lr_scheduler.MultiStepLR(self.opt, milestones=list(settings.milestones), gamma=settings.gamma)
        self.np_rng = np.random.default_rng(settings.seed)
        self.tgen = torch.Generator().manual_seed(settings.seed)
        self.iteration = 0
        self.history: list[dict] = []
        self.objective = Objective(settings, prompt, self.device, guide)
        self.points_last = 0

    # -- checkpoints
    def state(self) -> dict:
        return {
            "digest": self.s.digest(),
            "iteration": self.iteration,
            "field": self.field.state_dict(),
            "optimizer": self.opt.state_dict(),
            "scheduler": self.sched.state_dict(),
            "rng": _rng_state(self.np_rng, self.tgen),
            "history": self.history,
        }

    def load(self, state: dict) -> None:
        self.field.load_state_dict(state["field"])
        self.opt.load_state_dict(state["optimizer"])
        self.sched.load_state_dict(state["scheduler"])
        self.np_rng.bit_generator.state = state["rng"]["numpy"]
        self.tgen.set_state(state["rng"]["torch"])
        self.iteration = int(state["iteration"])
        self.history = list(state["history"])

    # -- one step
    def step(self, timer: Timer) -> dict:
        s = self.s
        with timer("gather"):
            ids = self.np_rng.choice(len(self.views), size=s.views_per_step, replace=len(self.views) < s.views_per_step)
            batches = []
            for i in ids:
                v = self.views[int(i)]
                specs = [global_spec(self.views.width, s.image_size, s.supersample)]
                specs += sample_crops(
                    v.mask,
                    s.crops,
                    scale=s.crop_scale,
                    min_coverage=s.crop_coverage,
                    max_tries=s.crop_max_tries,
                    out_size=s.image_size,
                    rng=self.np_rng,
                    supersample=s.supersample,
                )
                needed, lookups = gather_points(specs, v.index)
                sel = torch.from_numpy(needed).to(self.device)
                bgs = [background(s.background, s.image_size, self.tgen, self.device) for _ in specs]
                batches.append((v, sel, specs, lookups, bgs))
        with timer("networks+shading"):
            globals_, crops, globals_t, crops_t = [], [], [], []
            npts = 0
            for v, sel, specs, lookups, bgs in batches:
                pts, nrm, view = v.points[sel], v.normals[sel], v.view[sel]
                npts += len(sel)
                color = linear_to_srgb(self.field(pts, nrm, view).shading.rgb)
                imgs = [compose(color, lk, sp, bg) for lk, sp, bg in zip(lookups, specs, bgs, strict=True)]
                globals_.append(imgs[0])
                crops.extend(imgs[1:])
                if self.objective.guide is None:
                    with torch.no_grad():
                        tcol = linear_to_srgb(self.objective.target_colors(pts, nrm, view))
                    timgs = [compose(tcol, lk, sp, bg) for lk, sp, bg in zip(lookups, specs, bgs, strict=True)]
                    globals_t.append(timgs[0])
                    crops_t.extend(timgs[1:])
        with timer("guidance"):
            loss, stats = self.objective.loss(globals_, crops, globals_t, crops_t)
        with timer("backward"):
            self.opt.zero_grad(set_to_none=True)
            loss.backward()
        with timer("optimizer"):
            lr = self.sched.get_last_lr()[0]
            self.opt.step()
            self.sched.step()
        self.iteration += 1
        self.points_last = npts
        row = {"iteration": self.iteration, "loss": float(loss.detach()), "lr": lr, "points": npts, **stats}
        self.history.append(row)
        return row


# ---------------------------------------------------------------------------------- renderings
@torch.no_grad()
def render_view(field_: StyleField, v: CachedView, width: int, out_width: int, chunk: int = 65536) -> dict:
    """All render kinds of one cached view at ``out_width`` (nearest sampling), black background.
    Returns ``{kind: (3, out, out)}`` in display space (sRGB for radiance, [0, 1] for data)."""
    spec = global_spec(width, out_width)
    needed, (lookup,) = gather_points([spec], v.index)
    sel = torch.from_numpy(needed).to(v.points.device)
    outs = {k: [] for k in RENDER_KINDS}
    for lo in range(0, len(sel), chunk):
        idx = sel[lo : lo + chunk]
        pts, nrm, view = v.points[idx], v.normals[idx], v.view[idx]
        o = field_(pts, nrm, view)
        outs["rgb"].append(linear_to_srgb(o.shading.rgb))
        outs["diffuse"].append(linear_to_srgb(o.shading.diffuse))
        outs["specular"].append(linear_to_srgb(o.shading.specular))
        r = o.material.roughness if o.material.roughness is not None else torch.ones_like(pts[:, :1])
        outs["roughness"].append(r.expand(-1, 3))
        outs["normal"].append(0.5 + 0.5 * o.normal)
        flip = (nrm * view).sum(-1, keepdim=True) < 0
        outs["normal_original"].append(0.5 + 0.5 * torch.where(flip, -nrm, nrm))
    bg = torch.zeros(3, out_width, out_width, device=v.points.device)
    empty = torch.zeros(0, 3, device=v.points.device)
    return {k: compose(torch.cat(c) if c else empty, lookup, spec, bg) for k, c in outs.items()}


def contact_sheet(images: list[torch.Tensor], columns: int) -> np.ndarray:
    """Tile ``(3, h, w)`` images row-major into one ``(H, W, 3) uint8`` array."""
    rows = math.ceil(len(images) / columns)
    _, h, w = images[0].shape
    sheet = np.zeros((rows * h, columns * w, 3), np.uint8)
    for k, img in enumerate(images):
        r, c = divmod(k, columns)
        sheet[r * h : (r + 1) * h, c * w : (c + 1) * w] = (img.clamp(0, 1).permute(1, 2, 0).cpu().numpy() * 255).round()
    return sheet


def save_png(path: Path, array: np.ndarray) -> None:
    from PIL import Image

    with atomic_path(path) as tmp:
        Image.fromarray(array).save(tmp, format="PNG")


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    """Peak signal-to-noise ratio in dB of values in [0, 1], over every element given: callers
    pass object pixels only (``img[mask]``), never a frame with its background."""
    mse = float(F.mse_loss(a, b))
    return float("inf") if mse == 0 else 10.0 * math.log10(1.0 / mse)


def plot_loss(path: Path, history: list[dict], title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=100)
    it = [r["iteration"] for r in history]
    ax.plot(it, [r["loss"] for r in history], lw=0.8, label="loss")
    if history and "similarity_global" in history[0]:
        ax.plot(it, [-r["similarity_global"] for r in history], lw=0.8, label="-similarity (global)")
    ax.set_xlabel("iteration")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.getvalue())


# ------------------------------------------------------------------------------------- the run
def pick_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def run(
    train_path: Path,
    eval_path: Path,
    prompt: str,
    out_dir: Path,
    settings: OptimizeSettings,
    device: str = "auto",
    stop_after: int | None = None,
) -> dict:
    """Optimise (resuming from ``out_dir/checkpoint.pt`` when it matches) and write the outputs.

    ``stop_after`` ends the process's work after that many iterations *of this call* without
    writing final outputs, as a kill would (used by tests of resumption).
    """
    timer = Timer()
    dev = pick_device(device)
    for p in (train_path, eval_path):
        if not Path(p).is_file():
            raise StageInputError(p, "file not found", "Run the raycache stage first.")
    out_dir = Path(out_dir)
    ckpt = out_dir / "checkpoint.pt"
    with timer("setup"):
        opt = Optimizer(settings, RayCache(train_path), prompt, dev)
    resumed_from = None
    if ckpt.is_file():
        state = torch.load(ckpt, map_location=dev, weights_only=False)
        if state.get("digest") == settings.digest():
            opt.load(state)
            resumed_from = opt.iteration
            log.info("resumed from %s at iteration %d", ckpt, opt.iteration)
        else:
            log.warning("ignoring %s: written under other settings", ckpt)
    from tqdm import tqdm

    bar = tqdm(
        total=settings.iterations,
        initial=opt.iteration,
        desc="optimize",
        mininterval=2.0,
        unit="it",
        dynamic_ncols=False,
    )
    done_here = 0
    t_loop = time.perf_counter()
    while opt.iteration < settings.iterations:
        row = opt.step(timer)
        bar.update(1)
        bar.set_postfix(loss=f"{row['loss']:.4f}", refresh=False)
        done_here += 1
        if opt.iteration % settings.checkpoint_every == 0 and opt.iteration < settings.iterations:
            with timer("checkpoint"):
                _save_checkpoint(ckpt, **opt.state())
        if stop_after is not None and done_here >= stop_after:
            bar.close()
            return {"stopped_at": opt.iteration}
    bar.close()
    loop_s = time.perf_counter() - t_loop
    # every output is staged and moved into place together, the metadata last; the checkpoint
    # goes only after that, so a kill at any point leaves either a resumable run or finished outputs
    with staged_outputs(out_dir) as staging:
        with timer("outputs"):
            result = write_outputs(opt, eval_path, staging, settings, prompt)
        timings = {**timer.seconds, "loop": loop_s, "total": timer.total()}
        iters_here = max(done_here, 1)
        meta = metadata(
            stage="optimize",
            settings=settings.to_dict(),
            seed=settings.seed,
            inputs={"train": train_path, "eval": eval_path},
            outputs={k: out_dir / v for k, v in OUTPUT_FILES.items()},
            timings=timings,
            extra={
                "prompt": prompt,
                "device": str(dev),
                "guidance": settings.guidance,
                "weights": opt.objective.weights_id,
                "test_only_weights": opt.objective.test_only,
                ORIGIN_KEY: opt.objective.origin,
                "resumed_from_iteration": resumed_from,
                "seconds_per_iteration": loop_s / iters_here,
                "points_per_iteration": opt.points_last,
                "parameters": sum(p.numel() for p in opt.field.parameters()),
                "light_energy": opt.field.light.energy().tolist(),
                **result,
            },
        )
        write_json_atomic(staging / "meta.json", meta)
    ckpt.unlink(missing_ok=True)
    return meta


OUTPUT_FILES = {
    "field": "field.pt",
    "loss_csv": "loss.csv",
    "loss_png": "loss.png",
    "light": "light.npz",
    **{f"render_{k}": f"renders/{k}.png" for k in (*RENDER_KINDS, "light")},
}


def write_outputs(opt: Optimizer, eval_path: Path, out_dir: Path, settings: OptimizeSettings, prompt: str) -> dict:
    field_ = opt.field.eval()
    evalc = ViewStore(RayCache(eval_path), opt.device)
    renders = {k: [] for k in RENDER_KINDS}
    targets = []
    sims = []
    for i in range(len(evalc)):
        v = evalc[i]
        r = render_view(field_, v, evalc.width, settings.eval_width)
        for k in RENDER_KINDS:
            renders[k].append(r[k])
        if opt.objective.guide is not None:
            size = opt.objective.guide.image_size
            img = F.interpolate(r["rgb"][None], size=(size, size), mode="bilinear", align_corners=False)
            with torch.no_grad():
                sims.append(float(opt.objective.guide.similarity(img, opt.objective.text)))
        else:
            targets.append(render_target(opt.objective, v, evalc.width, settings.eval_width))
    columns = len(settings_eval_azimuths(evalc))
    for k, imgs in renders.items():
        save_png(out_dir / "renders" / f"{k}.png", contact_sheet(imgs, columns))
    from .relight import _front_view

    result: dict = {
        "eval_views": len(evalc),
        "sheet": {"columns": int(columns), "tile": settings.eval_width, "front_view": _front_view(evalc)},
    }
    if sims:
        result["final_similarity"] = float(np.mean(sims))
        result["final_similarity_per_view"] = sims
    if targets:
        save_png(out_dir / "renders" / "target.png", contact_sheet([t for t, _ in targets], columns))
        pred = torch.stack(renders["rgb"])
        tgt = torch.stack([t for t, _ in targets])
        masks = torch.stack([m for _, m in targets])
        # object pixels only: the background is black in both and would inflate the figure
        result["eval_psnr_db"] = psnr(pred[masks.expand_as(pred)], tgt[masks.expand_as(tgt)])
        result["eval_psnr_pixels"] = "object pixels of the evaluation views, sRGB"
    # the light: equirectangular radiance (linear, float32) and a tone-mapped preview
    with torch.no_grad():
        light = field_.light()
        dirs = equirect_directions(128, 256).to(opt.device)
        radiance = light.radiance(dirs.reshape(-1, 3)).reshape(128, 256, 3)
    with atomic_path(out_dir / "light.npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez(
                fh,
                equirect=radiance.cpu().numpy().astype(np.float32),
                axis=light.axis.cpu().numpy(),
                sharpness=light.sharpness.cpu().numpy(),
                amplitude=light.amplitude.cpu().numpy(),
            )
    preview = linear_to_srgb(radiance / radiance.max().clamp(min=1e-12))
    save_png(out_dir / "renders" / "light.png", (preview.cpu().numpy() * 255).round().astype(np.uint8))
    # the field and the loss curve
    with atomic_path(out_dir / "field.pt") as tmp:
        torch.save(
            {
                "format": 1,
                "settings": settings.to_dict(),
                "prompt": prompt,
                ORIGIN_KEY: opt.objective.origin,
                "state_dict": field_.state_dict(),
            },
            tmp,
        )
    keys = sorted({k for row in opt.history for k in row}, key=lambda k: (k != "iteration", k))
    with atomic_path(out_dir / "loss.csv") as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=keys)
            w.writeheader()
            w.writerows(opt.history)
    title = f"{prompt} ({opt.objective.weights_id})"
    plot_loss(out_dir / "loss.png", opt.history, title)
    return result


def settings_eval_azimuths(store: ViewStore) -> np.ndarray:
    """Distinct azimuths of the evaluation grid (its contact sheets have one column each)."""
    return np.unique(np.round(store.cache.arrays["azimuth"], 9))


@torch.no_grad()
def render_target(objective: Objective, v: CachedView, width: int, out_width: int, background: float = 0.0):
    """The procedural target of one cached view ``(3, out, out)`` and its object mask ``(1, out, out)``."""
    from .imaging import render_cached_view

    img = render_cached_view(v, width, out_width, lambda p, n, d: linear_to_srgb(objective.target_colors(p, n, d)), background)
    spec = global_spec(width, out_width)
    mask = torch.as_tensor(v.index[spec.rows, spec.cols] >= 0, device=v.points.device)[None]
    return img, mask


def load_field(path: str | Path, device="cpu") -> tuple[StyleField, OptimizeSettings]:
    """Rebuild a trained :class:`StyleField` from ``field.pt``; ``field.origin`` is the record of
    the guidance and weights that trained it (:func:`~stages.provenance.origin_record`), which
    every stage that uses the field copies into its own outputs."""
    data = torch.load(path, map_location=device, weights_only=False)
    origin = checked_origin(data.get(ORIGIN_KEY), path, "the optimize stage")
    settings = OptimizeSettings.from_dict(data["settings"])
    f = StyleField(settings).to(device)
    f.load_state_dict(data["state_dict"])
    f.origin = origin
    return f.eval(), settings


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m stages.optimize", description=__doc__.split("\n")[0])
    parser.add_argument("--train", required=True, type=Path, help="training ray cache (.npz)")
    parser.add_argument("--eval", required=True, type=Path, help="evaluation ray cache (.npz)")
    parser.add_argument("--prompt", required=True, help="text prompt (CLIP guidance)")
    parser.add_argument("--out-dir", required=True, type=Path)
    parser.add_argument("--settings", default="{}", help="JSON of the optimize settings")
    add_torch_arguments(parser, "auto")
    args = parser.parse_args(argv)
    apply_torch_arguments(args)
    from .guidance import ClipWeightsUnavailable

    with stage_errors("optimize") as status:
        try:
            run(
                args.train,
                args.eval,
                args.prompt,
                args.out_dir,
                OptimizeSettings.from_json(args.settings),
                args.device,
            )
        except ClipWeightsUnavailable as exc:
            raise StageInputError(None, str(exc)) from exc
    return status.code


if __name__ == "__main__":
    raise SystemExit(main())
