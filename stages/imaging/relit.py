"""Relighting judged by ground truth: the recovered field under another light against Mitsuba's
render of the *true* material under that light, on the held-out metric views.

A light that is blurred, or shadows painted into the albedo, still fit the training light; under
another light they show. For each environment of the relit ground truth
(:func:`~stages.imaging.targets.load_relit`) the environment is brought into the renderer as the
relight stage brings any map (an SG fit, :func:`~stages.model.lights.sg.fit_sg_light`), the field's
forward pass shades every hit of the metric views under it, and the PSNR is taken over the fully
covered object pixels in sRGB, as the metrics stage grades the training light. Beside it, the
*ceiling*: our renderer given the true material and normals under the same fitted light, with the
shadows the field's views cast (where they do) and the bounce the field models (where it does),
the best the model could reach there (the SG fit of the map, the closed-form BRDF, the
interreflection the field does not model and, without visibility, the missing shadows are what
separates it from Mitsuba).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from ..model.bounce import FaceSides, bounce_samples, bounce_table, field_surface, with_bounce
from ..model.field import shade_material
from ..model.lights import fit_environment_like
from ..model.networks import Material
from ..render import brdf as brdfs
from ..render.brdf import Brdf
from ..render.color import linear_to_srgb
from ..render.light import Light, Visibility, cat_visibility, map_visibility
from ..render.light.bounce import BounceLight
from ..render.shading import face_viewer
from .images import render_cached_view
from .quality import psnr
from .targets import FULL_COVERAGE, RelitTruth, TargetSet
from .views import ViewStore


@torch.no_grad()
def _field_radiance(field, store: ViewStore, light: Light) -> torch.Tensor:
    """Linear radiance ``(N, 3)`` of every hit of ``store``'s views (cache order) under ``light``."""
    parts = []
    for i in range(len(store)):
        v = store[i]
        parts.append(v.shade(field, light=light).shading.rgb)
    return torch.cat(parts)


def budget_components(brdf: Brdf | str) -> tuple[str, ...]:
    """The parts of a surface a relighting budget swaps for their truth, in its cumulative order
    (:func:`relight_budget`; under the training light the learned light comes first): the BRDF's
    parameters (``brdf.parameters``), then the shading normal."""
    return (*brdfs.get(brdf).parameters, "normal")


def true_surface(truth: TargetSet, store: ViewStore, brdf: Brdf | str = "tango") -> dict[str, torch.Tensor]:
    """The true surface at every hit of ``store``'s views (cache order) in the terms of ``brdf``
    (:func:`budget_components`): the material's parts, roughness clamped to ``[0.01, 1]`` as the
    field's, and the unit shading normal turned to the viewer."""
    dev = store.device
    view = torch.cat([store[i].view for i in range(len(store))])
    names = budget_components(brdf)
    a = {k: torch.from_numpy(truth.arrays[k].astype(np.float32)).to(dev) for k in names}
    a["normal"] = face_viewer(torch.nn.functional.normalize(a["normal"], dim=-1), view)
    a["roughness"] = a["roughness"].clamp(0.01, 1.0)
    return a


@torch.no_grad()
def recovered_surface(field, store: ViewStore) -> dict[str, torch.Tensor]:
    """The field's surface at every hit of ``store``'s views (cache order), as its forward pass
    makes it (:meth:`~stages.model.field.StyleField.surface`), in :func:`budget_components` terms."""
    parts: dict[str, list] = {}
    for i in range(len(store)):
        v = store[i]
        material, normal = field.surface(v.points, v.normals, v.view)
        got = {"normal": normal, **material.parameters()}
        for k, x in got.items():
            if x is None:
                raise ValueError("a relighting budget needs a field with specular heads (optimize.specular: true)")
            parts.setdefault(k, []).append(x)
    return {k: torch.cat(x) for k, x in parts.items()}


#: the points :func:`shade_surface` shades at once (large batches run out of the CPU's caches:
#: 340,000 points at once took 3x as long as in pieces of this size)
SHADE_CHUNK = 16384


def shade_surface(
    surface: dict[str, torch.Tensor],
    brdf: Brdf | str,
    view: torch.Tensor,
    light: Light,
    lobe: str,
    visibility: Visibility | None = None,
):
    """Linear radiance ``(N, 3)`` of ``surface`` (:func:`true_surface`'s terms of the BRDF
    ``brdf``) seen along ``view`` under ``light`` with its visibility inputs ``visibility`` (each
    SG lobe's visible share; or none), shaded :data:`SHADE_CHUNK` points at a time."""
    brdf = brdfs.get(brdf)
    out = []
    for lo in range(0, len(view), SHADE_CHUNK):
        part = {k: x[lo : lo + SHADE_CHUNK] for k, x in surface.items()}
        material = Material.of(brdf, *(part[name] for name in brdf.parameters))
        vis = map_visibility(lambda v, lo=lo: v[lo : lo + SHADE_CHUNK], visibility)
        out.append(shade_material(part["normal"], view[lo : lo + SHADE_CHUNK], material, light, lobe, vis).rgb)
    return torch.cat(out) if out else torch.zeros(0, 3, device=view.device)


def _shares(store: ViewStore, light: Light) -> Visibility | None:
    """``light``'s visibility inputs (each SG lobe's visible share) at every hit of ``store``'s
    views, or None without shadows."""
    shadows = [store[i].shadows for i in range(len(store))]
    return None if any(s is None for s in shadows) else cat_visibility([light.shadowed_by(s) for s in shadows])


@torch.no_grad()
def truth_radiance(truth: TargetSet, store: ViewStore, light: Light, lobe: str, brdf: Brdf | str = "tango") -> torch.Tensor:
    """Linear radiance ``(N, 3)`` of our renderer (the BRDF ``brdf``) given the true material and
    shading normals, with the shadows of ``store``'s views when they carry them (as the field's)."""
    view = torch.cat([store[i].view for i in range(len(store))])
    return shade_surface(true_surface(truth, store, brdf), brdf, view, light, lobe, _shares(store, light))


#: the search of :func:`channel_scale`: a factor this many times either side of its first guess,
#: narrowed by golden sections this many times (the bracket shrinks 0.618 per step: 3e-8 of it left)
SCALE_RANGE, SCALE_STEPS = 64.0, 36


def channel_scale(pred: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """The per-channel factor ``(3,)`` that best maps linear ``pred (N, 3)`` onto ``truth`` as the
    figures compare them: the factor ``s`` that minimises the squared error of the sRGB encodings
    (clipped to [0, 1]) of ``s pred`` and ``truth``, so the scaled PSNR is never below the raw one.

    A least-squares factor in linear radiance would be ruled by the brightest hits: a metal's
    mirrored sun, hundreds of times the rest and clipped in the figure, pulled it to 4x on a
    candle whose render it then made worse. The search starts from the linear least-squares factor
    over the hits that neither clips (all hits if none), ``sum(p t) / sum(p p)``, and narrows a
    bracket of :data:`SCALE_RANGE` either side of it in ``log s`` by golden sections; the best of
    the search, that first guess and 1 is returned (1 where ``pred`` is all zero)."""
    p, t = pred.double(), truth.double()
    goal = linear_to_srgb(t)
    plain = (p < 1) & (t < 1)
    use = torch.where(plain.any(0, keepdim=True), plain, torch.ones_like(plain))
    num, den = (p * t * use).sum(0), (p * p * use).sum(0)
    guess = torch.where(den > 0, num / den.clamp(min=1e-300), torch.ones_like(den)).clamp(min=1e-12)

    def error(scale: torch.Tensor) -> torch.Tensor:
        return ((linear_to_srgb(p * scale) - goal) ** 2).mean(0)

    lo, hi = torch.log(guess) - math.log(SCALE_RANGE), torch.log(guess) + math.log(SCALE_RANGE)
    ratio = (math.sqrt(5.0) - 1.0) / 2.0
    x1, x2 = hi - ratio * (hi - lo), lo + ratio * (hi - lo)
    f1, f2 = error(torch.exp(x1)), error(torch.exp(x2))
    for _ in range(SCALE_STEPS):
        # per channel: the minimum lies in [lo, x2] (x1 becomes the new x2) or in [x1, hi]
        left = f1 < f2
        lo, hi = torch.where(left, lo, x1), torch.where(left, x2, hi)
        new = torch.where(left, hi - ratio * (hi - lo), lo + ratio * (hi - lo))
        f_new = error(torch.exp(new))  # one evaluation per step: the other point is kept
        x1, x2 = torch.where(left, new, x2), torch.where(left, x1, new)
        f1, f2 = torch.where(left, f_new, f2), torch.where(left, f1, f_new)
    candidates = torch.stack([torch.exp((lo + hi) / 2), guess, torch.ones_like(guess)])
    errors = torch.stack([error(c) for c in candidates])
    best = candidates.gather(0, errors.argmin(0, keepdim=True))[0]
    best = torch.where((p > 0).any(0), best, torch.ones_like(best))
    return best.to(pred.dtype)


def grade_relighting(
    field,
    store: ViewStore,
    relit: list[RelitTruth],
    truth: TargetSet | None,
    lobes: int,
    iterations: int,
    renders: dict | None = None,
) -> list[dict]:
    """Per environment of ``relit``: ``environment``, ``psnr_db`` (the field relit against Mitsuba's
    truth), ``psnr_scaled_db`` and ``scale`` (the same after one least-squares factor per channel,
    :func:`channel_scale`: an image fit cannot tell an albedo from a light brighter by the same
    factor, so the raw figure also counts that unrecoverable scale; inverse-rendering evaluations
    align it), ``ceiling_psnr_db`` and ``ceiling_psnr_scaled_db`` (the true material in our
    renderer, when ``truth`` carries it), ``pixels``, ``noise_psnr_db`` (the truth's own noise) and
    ``sg_fit_relative_rms`` (the environment's SG fit). ``renders``: a dict that receives, per
    environment, the field's linear radiance at every hit of the views (cache order), for figures
    beside the truth (:func:`comparison_rows`)."""
    out = []
    dev = next(field.parameters()).device
    for r in relit:
        directions = store.cache.visibility_directions
        fitted, record = fit_environment_like(getattr(field, "light", None), r.environment, lobes, iterations, directions)
        light = fitted.to(dev)
        full = torch.from_numpy(r.coverage >= FULL_COVERAGE).to(dev)
        ours_all = _field_radiance(field, store, store.light_of(field, light))  # the field bounces as it trained
        truth_linear = torch.from_numpy(r.radiance).to(dev)[full]
        goal = linear_to_srgb(truth_linear)
        if renders is not None:
            renders[r.environment] = ours_all
        row = {
            "environment": r.environment,
            **graded_figures(ours_all[full], truth_linear),
            "pixels": int(full.sum()),
            "noise_psnr_db": r.noise_psnr_db,
            **record,
        }
        brdf = brdfs.get(getattr(field, "brdf", "tango"))
        if truth is not None and truth.has_truth and all(k in truth.arrays for k in brdf.parameters):
            lit, row["ceiling_bounce"] = ceiling_light(field, store, truth, light, brdf)
            ceiling = truth_radiance(truth, store, lit, field.specular_lobe, brdf)[full]
            row["ceiling_psnr_db"] = psnr(linear_to_srgb(ceiling), goal)
            row["ceiling_psnr_scaled_db"] = psnr(linear_to_srgb(ceiling * channel_scale(ceiling, truth_linear)), goal)
        out.append(row)
    return out


def surface_shading(senders: FaceSides, parts: dict[str, np.ndarray], brdf: Brdf, lobe: str, device) -> Callable:
    """The shading of the face sides ``senders`` with a known surface (``parts``: the BRDF's
    parameters and the shading ``normal`` at each sender, in their order), seen along the side's
    flat normal as :func:`~stages.model.bounce.field_shading` sees a field's, on ``device``: what
    :func:`~stages.model.bounce.bounce_table` takes. Roughness is clamped to ``[0.01, 1]`` as the
    field's; a normal that faces away from its side is the side's flat one."""
    picked = {k: torch.from_numpy(np.asarray(v, np.float32)).to(device) for k, v in parts.items()}
    picked["roughness"] = picked["roughness"].clamp(0.01, 1.0)
    material = Material.of(brdf, *(picked[k] for k in brdf.parameters))
    flat = torch.from_numpy(senders.normals).float().to(device)
    normal = torch.nn.functional.normalize(picked["normal"], dim=-1)
    normal = torch.where((normal * flat).sum(-1, keepdim=True) > 0, normal, flat)

    def shade(direct: Light, visibility):
        return shade_material(normal, flat, material, direct, lobe, visibility(direct))

    return shade


def ceiling_light(field, store: ViewStore, truth: TargetSet, light: Light, brdf: Brdf) -> tuple[Light, dict]:
    """The light a ceiling renders the true material under with ``field``'s transport: ``light``,
    and where the field models a bounce, the true material's bounce under it (its table from the
    truth at the face sides that the targets carry, :meth:`~stages.imaging.targets.TargetSet.senders`).
    Returns the light and the record of its bounce (``bounces`` 0 or 1, and why not)."""
    found, record = sender_truth(field, store, truth, brdf)
    if found is None:
        return light, record
    samples, true = found
    shade = surface_shading(store.senders, true, brdf, field.specular_lobe, store.device)
    return with_bounce(light, bounce_table(store.senders, shade, light, samples)), record


def sender_truth(field, store: ViewStore, truth: TargetSet, brdf: Brdf) -> tuple[tuple[int, dict] | None, dict]:
    """Where ``field`` models a bounce on ``store``'s views: its first hits per point and the truth
    at the views' senders (:attr:`~stages.imaging.views.ViewStore.senders`, their rows of
    :meth:`~stages.imaging.targets.TargetSet.senders`), else None; and the record of the bounce
    (``bounces`` 0 or 1, and why none where the field has one)."""
    samples = bounce_samples(field)
    if samples is None:
        return None, {"bounces": 0}
    if not store.shadows:
        return None, {"bounces": 0, "why": "the views carry no shadows (the ray cache's visibility)"}
    parts = truth.senders(brdf.parameters)
    if parts is None:
        return None, {"bounces": 0, "why": "the targets carry no truth at the face sides (written before they did)"}
    rows = store.senders.rows
    return (samples, {k: v[rows] for k, v in parts.items()}), {"bounces": 1}


@dataclass(frozen=True)
class BudgetBounce:
    """A relighting budget's bounce (:func:`relight_budget`): the face sides ``senders``, the
    field's surface at them (``recovered``, :func:`~stages.model.bounce.field_surface`) and the
    truth's (``true``), read through ``samples`` first hits per point; each swapped component is
    swapped at the senders too, so every render bounces off the surface it shows."""

    senders: FaceSides
    recovered: dict[str, np.ndarray]
    true: dict[str, np.ndarray]
    samples: int
    brdf: Brdf
    lobe: str

    @classmethod
    def of(cls, field, store: ViewStore, truth: TargetSet, brdf: Brdf) -> tuple[BudgetBounce | None, dict]:
        """The bounce of ``field`` on ``store``'s views, or None where it models none (or cannot:
        :func:`sender_truth`), and the record of it (``bounces`` 0 or 1, and why not)."""
        found, record = sender_truth(field, store, truth, brdf)
        if found is None:
            return None, record
        samples, true = found
        recovered = field_surface(field, store.senders, store.device)
        return cls(store.senders, recovered, true, samples, brdf, field.specular_lobe), record

    def light(self, light: Light, swapped: tuple[str, ...], device) -> Light:
        """``light`` with the bounce of the senders' surface under it: each component the truth's
        where ``swapped`` names it, else the field's."""
        parts = {k: (self.true[k] if k in swapped else self.recovered[k]) for k in self.true}
        shade = surface_shading(self.senders, parts, self.brdf, self.lobe, device)
        return with_bounce(light, bounce_table(self.senders, shade, light, self.samples))

    @staticmethod
    def visibility(store: ViewStore, shares: Visibility, light: Light) -> Visibility:
        """``shares`` (the direct components' visibility inputs at every hit of ``store``'s views)
        and the bounce's irradiance there (``light``'s last component)."""
        bounce = light.components[-1]
        return (*shares, torch.cat([store[i].shadows.bounce_irradiance(bounce) for i in range(len(store))]))


@torch.no_grad()
def training_ceiling(field, store: ViewStore, truth: TargetSet, environment: str, lobes: int, iterations: int) -> dict:
    """The training light's ceiling beside the recovered figure, on ``store``'s views (the
    held-out metric views of ``truth``, which carries the true material and Mitsuba's render
    under ``environment``, the targets' own light): our renderer given the true material under
    the environment's fit with the field's transport (:func:`~stages.model.lights.fit_environment_like`:
    SG lobes, and suns where the field has them) and the field under its learned light, both
    against the truth over the fully covered hits (:func:`graded_figures`: raw and scaled).
    A recovered figure above the ceiling absorbed the renderer's error into the material."""
    dev = store.device
    directions = store.cache.visibility_directions
    light, record = fit_environment_like(getattr(field, "light", None), environment, lobes, iterations, directions)
    full = torch.from_numpy(truth.arrays["coverage"].astype(np.float32) >= FULL_COVERAGE).to(dev)
    goal = torch.from_numpy(truth.arrays["radiance"].astype(np.float32)).to(dev)[full]
    brdf = brdfs.get(getattr(field, "brdf", "tango"))
    light, bounce = ceiling_light(field, store, truth, light.to(dev), brdf)
    ceiling = graded_figures(truth_radiance(truth, store, light, field.specular_lobe, brdf)[full], goal)
    recovered = graded_figures(_field_radiance(field, store, field.light())[full], goal)
    return {
        "environment": environment,
        "ceiling_psnr_db": ceiling["psnr_db"],
        "ceiling_psnr_scaled_db": ceiling["psnr_scaled_db"],
        "recovered_psnr_db": recovered["psnr_db"],
        "recovered_psnr_scaled_db": recovered["psnr_scaled_db"],
        "pixels": int(full.sum()),
        "pixels_are": "fully covered hits of the held-out metric views (the relighting's protocol)",
        **record,
        "ceiling_bounce": bounce,
    }


@dataclass(frozen=True)
class BudgetCase:
    """A light a relighting budget grades under: the environment's name (``builtin:<name>`` or a
    path), ``role`` ``"training"`` (the light the field was fitted under: its learned light is one
    of the swapped components) or ``"relit"`` (any other: the relit render already takes the
    environment's SG fit), and Mitsuba's truth at every hit of the store's views, ``radiance
    (N, 3)`` linear and ``coverage (N,)``, with its own noise."""

    environment: str
    role: str
    radiance: np.ndarray
    coverage: np.ndarray
    noise_psnr_db: float | None = None


def graded_figures(pred: torch.Tensor, goal: torch.Tensor) -> dict:
    """PSNR of linear ``pred (N, 3)`` against linear ``goal`` in sRGB, raw and after one scale per
    channel (:func:`channel_scale`), and the scale."""
    scale = channel_scale(pred, goal)
    srgb = linear_to_srgb(goal)
    return {
        "psnr_db": psnr(linear_to_srgb(pred), srgb),
        "psnr_scaled_db": psnr(linear_to_srgb(pred * scale), srgb),
        "scale": scale.tolist(),
    }


@torch.no_grad()
def relight_budget(field, store: ViewStore, truth: TargetSet, cases: list[BudgetCase], lobes: int, iterations: int) -> list[dict]:
    """The relighting error budget of ``field`` on ``store``'s views (the held-out metric views of
    ``truth``, which carries the true material): per case (:class:`BudgetCase`), the field's render
    against Mitsuba's truth over the fully covered hits, then with recovered components replaced by
    their truth, each alone (``alone``) and cumulatively in the order of :func:`budget_components`
    (``cumulative``; under the training light the learned light, replaced by the environment's SG
    fit, comes first). With every component replaced the render is the ceiling, our renderer given
    the true material (:func:`grade_relighting`'s ``ceiling_psnr_db``). Each figure
    (:func:`graded_figures`): ``psnr_db``, ``psnr_scaled_db``, ``scale``; each swap also carries its
    gain in dB over the recovered render (``alone``) and over the previous step (``cumulative``),
    raw and scaled, so the cumulative gains add up to the gap between the recovered render and the
    ceiling. The SG fits are :func:`~stages.model.lights.sg.fit_sg_light`'s (``lobes``,
    ``iterations``), as the relight stage's. Where the field models a bounce, every render bounces
    off the surface it shows (:class:`BudgetBounce`: a swapped component is swapped at the senders
    too, under the render's light; the recovered render's table refreshed under the learned light,
    as the field's last refresh left it); ``bounce`` records whether (without truth at the
    senders, its figures are direct light's)."""
    brdf = brdfs.get(getattr(field, "brdf", "tango"))
    names = budget_components(brdf)
    recovered = recovered_surface(field, store)
    true = true_surface(truth, store, brdf)
    view = torch.cat([store[i].view for i in range(len(store))])
    dev = view.device
    learned = field.light()
    parts = learned.components if isinstance(learned, Light) else (learned,)
    learned = Light(tuple(c for c in parts if c.kind != BounceLight.kind))  # a bounce is the budget's own
    bounce, bounce_record = BudgetBounce.of(field, store, truth, brdf)
    out = []
    for case in cases:
        directions = store.cache.visibility_directions
        fitted, record = fit_environment_like(getattr(field, "light", None), case.environment, lobes, iterations, directions)
        fitted = fitted.to(dev)
        full = torch.from_numpy(case.coverage >= FULL_COVERAGE).to(dev)
        goal = torch.from_numpy(np.asarray(case.radiance, np.float32)).to(dev)[full]
        shares = {"learned": _shares(store, learned) if case.role == "training" else None, "fitted": _shares(store, fitted)}
        components = (("light",) if case.role == "training" else ()) + names

        def render(swapped: tuple[str, ...], full=full, goal=goal, fitted=fitted, shares=shares, role=case.role) -> dict:
            surface = {k: (true[k] if k in swapped else recovered[k]) for k in names}
            which = "fitted" if role == "relit" or "light" in swapped else "learned"
            light, visibility = fitted if which == "fitted" else learned, shares[which]
            if bounce is not None:
                light = bounce.light(light, swapped, dev)
                visibility = bounce.visibility(store, visibility, light)
            visibility = map_visibility(lambda v, full=full: v[full], visibility)
            sel = {k: x[full] for k, x in surface.items()}
            return graded_figures(shade_surface(sel, brdf, view[full], light, field.specular_lobe, visibility), goal)

        base = render(())
        swaps, previous = [], base
        for j, c in enumerate(components):
            alone = render((c,))
            cumulative = dict(alone) if j == 0 else render(components[: j + 1])
            for fig, ref in ((alone, base), (cumulative, previous)):
                fig["gain_db"] = fig["psnr_db"] - ref["psnr_db"]
                fig["gain_scaled_db"] = fig["psnr_scaled_db"] - ref["psnr_scaled_db"]
            swaps.append({"component": c, "alone": alone, "cumulative": cumulative})
            previous = cumulative
        out.append(
            {
                "environment": case.environment,
                "role": case.role,
                "pixels": int(full.sum()),
                "noise_psnr_db": case.noise_psnr_db,
                **record,
                "recovered": base,
                "swaps": swaps,
                "ceiling": previous,
                "bounce": bounce_record,
            }
        )
    return out


@torch.no_grad()
def comparison_rows(store: ViewStore, views: list[int], ours: torch.Tensor, truth: np.ndarray, out: int) -> list[torch.Tensor]:
    """Three rows of images ``(3, out, out)`` of the metric ``views`` (indices into ``store``):
    ``ours (N, 3)`` and Mitsuba's ``truth (N, 3)`` (linear radiance at every hit, cache order) in
    sRGB, then 4 x their absolute difference; the background black."""
    offsets = store.cache.arrays["offsets"]
    goal = torch.from_numpy(np.asarray(truth, np.float32)).to(ours.device)
    rows: list[list[torch.Tensor]] = [[], [], []]
    for i in views:
        lo, hi = int(offsets[i]), int(offsets[i + 1])
        a, b = linear_to_srgb(ours[lo:hi]), linear_to_srgb(goal[lo:hi])
        for row, values in zip(rows, (a, b, (4.0 * (a - b).abs()).clamp(max=1.0)), strict=True):
            row.append(render_cached_view(store[i], store.width, out, lambda v, sel, x=values: x[sel]))
    return [img for row in rows for img in row]
