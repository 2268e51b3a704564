"""One optimisation run's state and step (TANGO Sec. 3.3), its checkpoints and its loss records.

Per step: pick ``views_per_step`` views of the cached pool, build one global image per view and
``crops`` local crops with enough object coverage (:mod:`stages.imaging.images`), shade only the
cached hits those images need through the field, and minimise the objective
(:mod:`stages.guidance.objective`). AdamW with step decay. The state (networks, light, optimiser,
scheduler, RNG states, loss history) round-trips through :meth:`Optimizer.state` and
:meth:`Optimizer.load`, so a resumed run ends with the same parameters as an uninterrupted one.
"""

from __future__ import annotations

import csv
import dataclasses
import io
from pathlib import Path

import numpy as np
import torch
from torch.nn.utils import get_total_norm

from ..config.sections import OptimizeSettings
from ..core.allocator import keep_freed_memory
from ..core.provenance import Timer, atomic_path
from ..core.safefiles import atomic_stream
from ..geometry.normals import NormalSpec
from ..geometry.raycache import RayCache
from ..guidance.objective import ImageBatch, choose_guidance
from ..imaging.images import ImageSpec, background, compose, gather_points, global_spec, sample_crops
from ..imaging.targets import TargetSet
from ..imaging.views import CachedView, ViewStore
from ..model.bounce import bounce_table, field_shading, resolve_bounces
from ..model.compiled import CompiledField
from ..model.field import StyleField
from ..model.lights.sun import resolve_suns
from ..model.networks import cat_materials, material_variation, normal_tilt
from ..render.color import linear_to_srgb
from ..render.products import onednn_products, run_choice


def _rng_state(np_rng: np.random.Generator, tgen: torch.Generator) -> dict:
    return {"numpy": np_rng.bit_generator.state, "torch": tgen.get_state()}


def save_checkpoint(path: Path, **state) -> None:
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


#: the most loss-history rows kept (in memory, in every checkpoint, in loss.csv): a longer run keeps
#: every other row and records at twice the stride, so a run of any length stores at most this many
HISTORY_ROWS = 4096


def keep_history(history: list[dict], stride: int, row: dict, limit: int = HISTORY_ROWS) -> int:
    """Record iteration ``row["iteration"]`` (counted from 1) in ``history`` (in place) and return
    the stride: the row is kept when its iteration is 1 plus a multiple of ``stride``; past
    ``limit`` rows every other row is dropped and the stride doubles (the rows kept are exactly
    those at the new stride, so a resumed run records what an uninterrupted one does)."""
    if (int(row["iteration"]) - 1) % stride == 0:
        history.append(row)
    if len(history) > limit:
        history[:] = history[::2]
        stride *= 2
    return stride


class Optimizer:
    """One optimisation run: state, step function, checkpointing."""

    def __init__(
        self, settings: OptimizeSettings, train: RayCache, prompt: str, device, guide=None, targets: TargetSet | None = None
    ) -> None:
        """``targets``: the Mitsuba image targets of ``train`` (``target_renderer: mitsuba``).
        ``optimize.suns: auto`` is decided here (:func:`~stages.model.lights.sun.resolve_suns`, on
        the fixed light's map or the targets' environment), and ``optimize.bounces: auto``
        (:func:`~stages.model.bounce.resolve_bounces`, on the training views' shadows);
        :attr:`settings` hold the counts."""
        environment = settings.light_map if settings.light == "fixed" else (targets.environment if targets else None)
        suns, self.suns_record = resolve_suns(
            settings.suns, environment, train.visibility_directions if settings.shadows else 0, settings.suns_share
        )
        self.device = torch.device(device)
        normals = NormalSpec(settings.shading_normals, settings.crease_angle_deg, settings.normal_weighting)
        views = ViewStore(train, self.device, normals, targets, shadows=settings.shadows)
        bounces, self.bounces_record = resolve_bounces(settings.bounces, views, settings.bounce_auto_median)
        settings = dataclasses.replace(settings, suns=suns, bounces=bounces)
        self.settings = settings
        self.field = StyleField(settings.field_settings()).to(self.device)
        if suns and settings.light == "learn" and environment is not None:  # the suns start where the targets' are
            self.suns_record["start"] = self.field.light.sun.start_at(environment)
        #: the field as a step runs it: compiled, padded and in bfloat16 where the levers say
        self.compiled = CompiledField(self.field)
        #: the light's mode for the metadata: learned, or the fixed fit of a known map (``light: fixed``)
        self.light_record: dict = {"mode": settings.light}
        if settings.light == "fixed":
            self.light_record.update(self.field.light.hold(settings.light_map))
        #: what the C allocator does with the memory a step frees, for the metadata
        self.allocator = keep_freed_memory(settings.keep_freed_memory)[1]
        #: what the networks' products ran in during training, for the metadata
        self.network_precision = self.compiled.use_bf16(settings.bf16_networks, self.device)
        self.views = views
        #: the face sides that send the bounce (where the run models one), and its refreshes
        self.senders = views.senders if bounces else None
        self.bounce_refreshes = 0
        self.compiled.use_compiled_shading(
            settings.compile_shading,
            self.device,
            settings.iterations,
            self.views.shadows,
            settings.compile_networks,
            settings.compile_static,
            self.views.largest,
            self.views.global_points(settings.image_size, settings.supersample),
        )
        self.prompt = prompt
        # fused: every parameter's update in one operation (on a GPU a few kernels, where the multi-tensor
        # form launched 80 a step; on a CPU 0.3 ms against 1.1 ms a step), the same update to rounding
        self.adamw = torch.optim.AdamW(self.param_groups(), lr=settings.lr, weight_decay=settings.weight_decay, fused=True)
        self.lr_schedule = torch.optim.lr_scheduler.MultiStepLR(
            self.adamw, milestones=list(settings.milestones), gamma=settings.gamma
        )
        self.np_rng = np.random.default_rng(settings.seed)
        self.tgen = torch.Generator().manual_seed(settings.seed)
        self.iteration = 0
        self.history: list[dict] = []
        self.history_stride = 1
        self.guidance = choose_guidance(settings, prompt, self.device, guide, targets.description if targets else None)
        #: whether a step's float32 linear layers (the networks', CLIP's) run by oneDNN, and what ran,
        #: for the metadata
        self.onednn, self.float32_products = self.products_choice()
        #: the transposes of CLIP's frozen weights oneDNN's path keeps for this run's steps
        self.transposes: dict = {}
        self.points_last = 0
        #: points shaded and steps taken by this process (the mean per step for the metadata)
        self.points_total, self.steps_taken = 0, 0
        #: when the light was pruned (``light_prune_after``): iteration, lobes kept and dropped
        self.light_pruned: dict | None = None

    def products_choice(self) -> tuple[bool, str]:
        """:func:`~stages.render.products.run_choice` for this run's networks and CLIP as built."""
        clip = getattr(self.guidance, "guide", None)
        return run_choice(self.settings.onednn_products, self.device, self.field.bf16, clip and (clip.bf16, clip.tower))

    @property
    def shading_path(self) -> str:
        """What shades while training, and why (the field's decision), for the metadata."""
        return self.compiled.shading_path

    def param_groups(self) -> list[dict]:
        """The optimiser's two groups: the networks at ``lr`` (with ``weight_decay``), then the
        light at ``light_lr`` without weight decay (its parameters are logarithms and directions:
        decay would pull every lobe towards sharpness 1 and energy 1)."""
        light = list(self.field.light.parameters())
        ids = {id(p) for p in light}
        rest = [p for p in self.field.parameters() if id(p) not in ids]
        light_lr = self.settings.light_lr if self.settings.light_lr is not None else self.settings.lr
        return [{"params": rest}, {"params": light, "lr": light_lr, "weight_decay": 0.0}]

    # -- checkpoints
    def state(self) -> dict:
        return {
            "digest": self.settings.digest(),
            "iteration": self.iteration,
            "field": self.field.state_dict(),
            "optimizer": self.adamw.state_dict(),
            "scheduler": self.lr_schedule.state_dict(),
            "rng": _rng_state(self.np_rng, self.tgen),
            "history": self.history,
            "history_stride": self.history_stride,
            "light_pruned": self.light_pruned,
            "light": self.light_record,
            "bounce_refreshes": self.bounce_refreshes,
        }

    def load(self, state: dict) -> None:
        lobes = self.field.light.lobes
        self.field.load_state_dict(state["field"])
        if self.field.light.lobes != lobes:  # pruned before the checkpoint: the light's parameters are new
            self.adamw.param_groups[1]["params"] = list(self.field.light.parameters())
            self.compiled.lobes_changed()
        # a checkpoint written before the optimiser was fused says so in its groups, which loading
        # would take over: the same update, so it resumes fused (its steps moved to the device)
        saved = state["optimizer"]
        self.adamw.load_state_dict({**saved, "param_groups": [{**g, "fused": True} for g in saved["param_groups"]]})
        self.light_pruned = state.get("light_pruned")
        self.bounce_refreshes = int(state.get("bounce_refreshes", 0))
        self.lr_schedule.load_state_dict(state["scheduler"])
        self.np_rng.bit_generator.state = state["rng"]["numpy"]
        self.tgen.set_state(state["rng"]["torch"])
        self.iteration = int(state["iteration"])
        self.history = list(state["history"])
        self.history_stride = int(state.get("history_stride", 1))

    # -- the scene's needs
    def prune_light(self) -> int:
        """Drop the light's negligible parts (:meth:`~stages.model.lights.base.LightModule.prune` at
        ``light_prune_share``: the SG lobes', :meth:`~stages.model.lights.sg.SGLightModule.negligible`),
        carrying the optimiser's moments of the kept ones; returns how many were dropped."""
        parts = self.field.light.prune(self.settings.light_prune_share)
        group = self.adamw.param_groups[1]["params"]
        for part in parts:
            for old, new in part.pairs:
                moments = self.adamw.state.pop(old, None)
                if moments is not None:
                    self.adamw.state[new] = {
                        k: v[part.index] if torch.is_tensor(v) and v.dim() > 0 and v.shape[0] == old.shape[0] else v
                        for k, v in moments.items()
                    }
                group[next(i for i, p in enumerate(group) if p is old)] = new
        dropped = sum(part.dropped for part in parts)
        self.light_pruned = {"iteration": self.iteration, "kept": sum(part.kept for part in parts), "dropped": dropped}
        if dropped:
            self.compiled.lobes_changed()
        return dropped

    # -- one step
    def image_specs(self, v: CachedView) -> list[ImageSpec]:
        """The images of one view in a step: the global image, then ``crops`` random crops with
        enough object coverage (drawn from the run's RNG)."""
        settings = self.settings
        specs = [global_spec(self.views.width, settings.image_size, settings.supersample)]
        specs += sample_crops(
            v.mask_sums,
            settings.crops,
            scale=settings.crop_scale,
            min_coverage=settings.crop_coverage,
            max_tries=settings.crop_max_tries,
            out_size=settings.image_size,
            rng=self.np_rng,
            supersample=settings.supersample,
        )
        return specs

    def priors(self, materials: list, stats: dict, points: list | None = None, normals: list | None = None) -> torch.Tensor:
        """The weighted priors of this step (each recorded in ``stats`` when on): the learned
        light's colour spread (``light_neutral``, :meth:`~stages.model.lights.base.LightModule.colour_spread`),
        glTF's metallic away from 0 and 1 (``metallic_binary``: the mean of ``m (1 - m)`` over
        the step's shaded points ``materials``), the material's change over a small jitter of the
        step's hit ``points`` (``material_smooth``, :func:`material_variation`) and the predicted
        normals' tilt from the geometric ones (``normal_tilt``, :func:`normal_tilt`; ``normals``:
        pairs of predicted and geometric normals). The surface priors need the step's ``points`` and
        ``normals`` (:meth:`step` passes them); without them only the others are taken."""
        settings = self.settings
        total = torch.zeros((), device=self.device)
        if settings.material_smooth > 0 and points:
            x = torch.cat(points)
            jitter = torch.randn(x.shape, generator=self.tgen).to(x.device) * settings.material_smooth_radius
            variation = material_variation(cat_materials(materials), self.field.material(x + jitter))
            total = total + settings.material_smooth * variation
            stats["material_variation"] = float(variation.detach())
        if settings.normal_tilt > 0 and self.field.normal_net is not None and normals:  # (no normal network: nothing to hold)
            tilt = normal_tilt(torch.cat([p for p, _ in normals]), torch.cat([g for _, g in normals]))
            total = total + settings.normal_tilt * tilt
            stats["normal_tilt"] = float(tilt.detach())
        if settings.light_neutral > 0:
            spread = self.field.light.colour_spread()
            total = total + settings.light_neutral * spread
            stats["light_colour_spread"] = float(spread.detach())
        if settings.metallic_binary > 0:
            m = torch.cat([mat.metallic for mat in materials])
            between = (m * (1.0 - m)).mean()
            total = total + settings.metallic_binary * between
            stats["metallic_between"] = float(between.detach())
        return total

    def check_finite(self, loss: torch.Tensor) -> None:
        """Stop before a non-finite loss or gradient reaches the parameters: one NaN would spread to
        every later step and checkpoint. The last checkpoint holds the state before this step."""
        grads = [p.grad for p in self.field.parameters() if p.grad is not None]
        # the largest |gradient| over all of them (NaN where any is NaN), in one multi-tensor pass
        largest = get_total_norm(grads, float("inf")) if grads else torch.zeros((), device=loss.device)
        if bool(torch.isfinite(torch.stack([loss.detach().float().reshape(()), largest.float()])).all()):
            return
        bad = [name for name, p in self.field.named_parameters() if p.grad is not None and not torch.isfinite(p.grad).all()]
        what = "the loss" if not torch.isfinite(loss.detach()).all() else "the gradient of " + ", ".join(bad)
        raise FloatingPointError(
            f"step {self.iteration + 1}: {what} is not finite; the parameters were left as they were after step "
            f"{self.iteration}. This is a numerical bug: please report it with the settings and the checkpoint; "
            "a resumed run repeats the step"
        )

    def step(self, timer: Timer) -> dict:
        """One optimisation step (its float32 linear layers by oneDNN where :attr:`onednn`), the
        bounce's table refreshed first every ``bounce_every`` steps (from the first)."""
        if self.senders is not None and self.iteration % self.settings.bounce_every == 0:
            with timer("bounce"):
                self.refresh_bounce()
        with onednn_products(self.onednn, self.transposes):
            return self._step(timer)

    @torch.no_grad()
    def refresh_bounce(self) -> None:
        """The bounce's table from the field as it is (:func:`~stages.model.bounce.bounce_table`:
        each face side's diffuse radiance under the learned light's other components)."""
        module = self.field.light.bounce
        shade = field_shading(self.field, self.senders, self.device)
        module.set_table(bounce_table(self.senders, shade, self.field.light(), module.samples).table)
        self.bounce_refreshes += 1

    def _step(self, timer: Timer) -> dict:
        settings = self.settings
        self.compiled.begin_step()
        with timer("gather"):
            ids = self.np_rng.choice(
                len(self.views), size=settings.views_per_step, replace=len(self.views) < settings.views_per_step
            )
            batches = []
            for i in ids:
                v = self.views[int(i)]
                specs = self.image_specs(v)
                needed, lookups = gather_points(specs, v.index)
                sel = torch.from_numpy(needed).to(self.device)
                bgs = [background(settings.background, settings.image_size, self.tgen, self.device) for _ in specs]
                batches.append((v, sel, specs, lookups, bgs))
        with timer("networks+shading"):
            rendered, target = ImageBatch(), ImageBatch()
            npts = 0
            materials, points, normals = [], [], []
            for v, sel, specs, lookups, bgs in batches:
                npts += len(sel)
                out = v.shade(self.compiled, sel)
                materials.append(out.material)
                if settings.material_smooth > 0:  # (the gathers only where a prior reads them)
                    points.append(v.points[sel])
                if settings.normal_tilt > 0:
                    normals.append((out.normal, v.normals[sel]))
                color = linear_to_srgb(out.shading.rgb)
                rendered.add([compose(color, lk, sp, bg) for lk, sp, bg in zip(lookups, specs, bgs, strict=True)])
                with torch.no_grad():
                    tcol = self.guidance.target_colors(v, sel)
                if tcol is not None:
                    tcol = linear_to_srgb(tcol)
                    target.add([compose(tcol, lk, sp, bg) for lk, sp, bg in zip(lookups, specs, bgs, strict=True)])
        with timer("guidance"):
            loss, stats = self.guidance.loss(rendered, target if target.globals else None)
            loss = loss + self.priors(materials, stats, points, normals)
        with timer("backward"):
            self.adamw.zero_grad(set_to_none=True)
            loss.backward()
            self.check_finite(loss)
        with timer("optimizer"):
            lr = self.lr_schedule.get_last_lr()[0]
            self.adamw.step()
            self.lr_schedule.step()
        self.iteration += 1
        self.points_last = npts
        self.points_total, self.steps_taken = self.points_total + npts, self.steps_taken + 1
        row = {"iteration": self.iteration, "loss": float(loss.detach()), "lr": lr, "points": npts, **stats}
        row["light_lobes"] = self.field.light.lobes
        if self.iteration == settings.light_prune_after:
            self.prune_light()
        self.history_stride = keep_history(self.history, self.history_stride, row)
        return row


def write_loss_csv(path: Path, history: list[dict]) -> None:
    """The loss history (every iteration up to :data:`HISTORY_ROWS` of them, then evenly thinned:
    :func:`keep_history`), atomically."""
    keys = sorted({k for row in history for k in row}, key=lambda k: (k != "iteration", k))
    with atomic_stream(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        w.writerows(history)


#: the most characters of the prompt the loss plot shows as its title
TITLE_CHARS = 100


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
    # the prompt is data: never parsed as mathtext ("a $\\wood$ vase" would raise at savefig, after
    # the whole run), and cut to one line of the figure
    ax.set_title(title if len(title) <= TITLE_CHARS else title[: TITLE_CHARS - 1] + "…", fontsize=9, parse_math=False)
    ax.legend(fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.getvalue())
