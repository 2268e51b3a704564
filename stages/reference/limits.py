"""What the SG model cannot represent, measured: the same scene rendered by Mitsuba with and
without the effects TANGO's renderer leaves out, and by our SG renderer with the true material.

Rungs, each compared with the full path-traced target on the held-out metric views (fully
covered object pixels, sRGB), so each step's loss of PSNR is the share of the error that effect
accounts for:

1. ``direct``: Mitsuba's path tracer stopped after one bounce (``max_depth 2``): no
   interreflection, shadows kept;
2. ``unshadowed``: direct light with no visibility test (:func:`unshadowed_integrator`, MIS of
   light and BSDF sampling, the test ray never cast): no shadows either; what is left differs
   from our model only by the BRDF model (Mitsuba's principled against TANGO's sum) and the light;
3. ``sg_exact_material``: our closed-form SG renderer with the *true* material and normals
   (:meth:`~stages.reference.targets.GroundTruth.at_hits`) under the ``lobes``-lobe SG light
   fitted to the target's pixels through that renderer (:func:`fit_light_to_image`): what a
   perfect optimisation of TANGO's model could reach; the step from rung 2 is the BRDF model,
   the SG light and the closed-form shading together (the last alone is measured by
   ``benchmarks/render/shading_vs_mitsuba.py``).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, fields

import numpy as np
import torch

from ..geometry.meshio import TriMesh
from ..geometry.raycache import RayCache
from ..geometry.tracing import EmbreeTracer
from ..geometry.visibility import self_occlusion, viewer_side_normals
from ..imaging.quality import psnr
from ..imaging.targets import FULL_COVERAGE
from ..model.field import shade_material
from ..model.lights.sg import SGLightModule
from ..model.networks import Material
from ..model.shadows import ShadowCache
from ..render import brdf as brdfs
from ..render.brdf import Brdf
from ..render.color import linear_to_srgb, srgb_encode
from ..render.light import Light
from ..render.shading import face_viewer
from .targets import TargetRenderer


def unshadowed_integrator(mi):
    """A Mitsuba integrator (the imported module's variant) for direct light *without
    visibility*: at the first hit, one light sample (the emitter's importance sampling, the
    shadow ray never traced) and one BSDF sample (the environment looked up in the sampled
    direction without tracing it), combined by the balance heuristic. Emitters are hidden from
    the camera; alpha is 1 on a hit."""
    import drjit  # installed with mitsuba

    class Unshadowed(mi.SamplingIntegrator):
        def __init__(self, props=None):
            super().__init__(props if props is not None else mi.Properties())

        def sample(self, scene, sampler, ray, medium=None, active=True):
            si = scene.ray_intersect(ray, active=active)
            valid = si.is_valid() & active
            if isinstance(valid, bool) and not valid:  # scalar variants: a miss has no BSDF (si.bsdf() would crash)
                return mi.Spectrum(0.0), False, []
            bsdf = si.bsdf(ray)
            ctx = mi.BSDFContext()
            result = mi.Spectrum(0.0)
            # light sampling, no visibility test
            ds, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(valid), False, valid)
            wo = si.to_local(ds.d)
            value, pdf_bsdf = bsdf.eval_pdf(ctx, si, wo, valid)
            w_light = drjit.select(ds.delta, 1.0, ds.pdf / (ds.pdf + pdf_bsdf))
            result += drjit.select(valid & (ds.pdf > 0), em_weight * value * w_light, 0.0)
            # BSDF sampling: the environment in the sampled direction, unoccluded
            bs, weight = bsdf.sample(ctx, si, sampler.next_1d(valid), sampler.next_2d(valid), valid)
            d = si.to_world(bs.wo)
            far = drjit.zeros(mi.SurfaceInteraction3f)
            far.wi = -d
            far.t = drjit.inf
            env = scene.environment()
            ok = valid & (bs.pdf > 0) & (env is not None)
            ds_env = mi.DirectionSample3f(scene, far, si)
            pdf_light = scene.pdf_emitter_direction(si, ds_env, ok)
            w_bsdf = bs.pdf / (bs.pdf + pdf_light)
            result += drjit.select(ok, weight * env.eval(far, ok) * w_bsdf, 0.0)
            return result, valid, []

    return Unshadowed()


#: hits per step of the light fit (a random batch each step)
FIT_BATCH = 8192


@dataclass
class TruthAtHits:
    """The true surface at hits, as our renderer shades it: ``normal`` and ``view`` ``(N, 3)``, the
    true ``material`` (TANGO's terms, or glTF's with its base colour and metallic: the model's BRDF)
    and the hits' ``shadows`` (a :class:`~stages.model.shadows.ShadowCache`; None: unshadowed)."""

    normal: torch.Tensor
    view: torch.Tensor
    material: Material
    shadows: ShadowCache | None = None

    def at(self, index: torch.Tensor) -> TruthAtHits:
        """The hits ``index`` (the shadows stay the whole set's: they are looked up by index)."""
        picked = {
            f.name: None if getattr(self.material, f.name) is None else getattr(self.material, f.name)[index]
            for f in fields(Material)
        }
        return TruthAtHits(self.normal[index], self.view[index], dataclasses.replace(self.material, **picked), self.shadows)

    def radiance(self, light: Light, index: torch.Tensor | None = None, shadowed: bool = True) -> torch.Tensor:
        """Linear radiance ``(N, 3)`` of the hits (``index``: of those hits) under ``light``, by the
        specular model that stands for the material's BRDF (``brdf.model_lobe``: glTF's BRDF
        through the fitted lobe, TANGO's sum through its closed form); shadowed by the hits'
        shadows unless ``shadowed`` is false."""
        part = self if index is None else self.at(index)
        visibility = None if not shadowed or self.shadows is None else light.shadowed_by(self.shadows, index)
        lobe = self.material.brdf.model_lobe
        return shade_material(part.normal, part.view, part.material, light, lobe, visibility).rgb


def fit_light_to_image(
    truth: TruthAtHits, target: torch.Tensor, lobes: int, energy, seed: int = 0, iterations: int = 400, init: str = "broad"
):
    """The ``lobes``-lobe SG light that makes our renderer, given the ``truth`` at hits, best match
    the sRGB ``target (N, 3)`` (mean squared error over random batches of hits, Adam at 0.02 on the
    light's logarithmic parametrisation, lobes started as ``init``,
    :data:`~stages.config.sections.LIGHT_INITS`; ``broad`` by default: with the material known and
    only the light to fit, broad lobes find a 5-degree disc and sharpen onto it where lobes started
    sharp stay where they began, measured in ``tests/reference/test_sharp_light.py``). A glTF
    material gives the light a perfect optimisation of glTF's model would find. Returns the light
    and the seconds taken."""
    t0 = time.perf_counter()
    gen = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    module = SGLightModule(lobes, rgb=True, total_energy=float(np.mean(energy)), init=init)
    adam = torch.optim.Adam(module.parameters(), lr=0.02)
    n = len(truth.normal)
    for _ in range(iterations):
        b = torch.randint(n, (min(FIT_BATCH, n),), generator=gen)
        loss = torch.nn.functional.mse_loss(linear_to_srgb(truth.radiance(Light.of(module()), b)), target[b])
        adam.zero_grad()
        loss.backward()
        adam.step()
    with torch.no_grad():
        light = module()
    return light.detach(), time.perf_counter() - t0


def _per_hit(img: np.ndarray, cache: RayCache, i: int) -> tuple[np.ndarray, np.ndarray]:
    flat = img.reshape(-1, img.shape[-1])[cache.view(i).pixel]
    alpha = flat[:, 3] if flat.shape[1] > 3 else np.ones(len(flat))
    return np.where(alpha[:, None] > 0, flat[:, :3] / np.maximum(alpha[:, None], 1e-8), 0.0), alpha


def measure_limits(
    renderer: TargetRenderer,
    cache: RayCache,
    spp: int,
    lobes: tuple[int, ...] = (16, 32),
    seed: int = 0,
    brdf: Brdf | str = "tango",
    visibility: bool = False,
    directions: int = 1024,
    shadow_samples: int = 64,
) -> dict:
    """The error budget of the best our model can do on ``cache``'s views (see the module
    docstring), in mean squared sRGB error over fully covered object pixels, each Mitsuba
    render's own noise measured (two independent renders of the target) and taken out.

    For each lobe count, the SG model with the true material is fitted (its light only) to each
    rung's image: the full target, direct light only, and unshadowed direct light. Its error
    against the full target is the error budget; removing interreflection from the target lowers
    it by the interreflection's share, removing shadows too by the shadows' share, and what
    remains against the unshadowed image is the BRDF model, SG light and closed-form shading
    together. The three shares add up to one by construction. Also, model-free:
    ``interreflection_mse`` (target against direct) and ``shadows_mse`` (direct against
    unshadowed). ``brdf``: the model's BRDF (TANGO's sum, or glTF's from the truth's base colour
    and metallic).

    ``visibility``: our renderer casts shadows (:class:`~stages.model.shadows.ShadowCache` of the
    hits: ``directions`` stored directions, ``shadow_samples`` rays per lobe too sharp for them)
    when fitted to the target and to the direct image; the unshadowed image is still fitted
    without. The shadows' share is then what our shadows leave of them, and ``agreement_db`` holds
    the two comparisons of like with like: ours shadowed against Mitsuba's direct light, ours
    unshadowed against its unshadowed light. Also
    ``self_occlusion`` (the blocked share of the hits' hemispheres: mean, median, 95th percentile)."""
    mi = renderer.mi
    unshadowed = unshadowed_integrator(mi)
    direct = mi.load_dict({"type": "path", "max_depth": 2, "hide_emitters": True})
    images = {"target": [], "second_target": [], "direct": [], "unshadowed": []}
    cover = []
    for i in range(len(cache)):
        h = cache.view(i)
        cam = mi.load_dict(renderer.sensor_dict(h.c2w, cache.fov_deg, cache.width, spp))
        for name, integrator, s in (
            ("target", None, seed + 4 * i),
            ("second_target", None, seed + 4 * i + 1),
            ("direct", direct, seed + 4 * i + 2),
            ("unshadowed", unshadowed, seed + 4 * i + 3),
        ):
            kwargs = {"integrator": integrator} if integrator is not None else {}
            img = np.array(mi.render(renderer.scene, sensor=cam, seed=s, spp=spp, **kwargs), dtype=np.float64)
            rgb, alpha = _per_hit(img, cache, i)
            images[name].append(rgb)
            if name == "target":
                cover.append(alpha)
    truth, met = renderer.truth_at_hits(cache)
    full = (np.concatenate(cover) >= FULL_COVERAGE) & met
    hits = {k: np.concatenate(v)[full] for k, v in images.items()}
    srgb = {k: srgb_encode(v) for k, v in hits.items()}

    def mse(a, b):
        return float(((srgb[a] - srgb[b]) ** 2).mean())

    # each Mitsuba render carries its own noise of variance `noise`; differences of two renders
    # carry twice that, which is taken out so each effect is measured above the noise
    noise = mse("target", "second_target") / 2.0
    out = {
        "pixels": int(full.sum()),
        "spp": spp,
        "noise_mse": noise,
        "interreflection_mse": max(mse("direct", "target") - 2 * noise, 0.0),
        "shadows_mse": max(mse("unshadowed", "direct") - 2 * noise, 0.0),
    }
    shadows = _hit_shadows(cache, full, directions, shadow_samples, seed) if visibility else None
    if shadows is not None:
        out["visibility"] = {"directions": directions, "samples": shadows.samples, "seconds": shadows.seconds}
        out["self_occlusion"] = self_occlusion(shadows.blocked_share())
    surface = _truth_surface(cache, truth, full, brdfs.get(brdf), shadows)
    for k in lobes:
        out[f"lobes_{k}"] = _lobe_budget(surface, srgb, k, renderer.env_energy, noise, seed)
    return out


def _truth_surface(cache: RayCache, truth: dict, full: np.ndarray, brdf: Brdf, shadows: ShadowCache | None) -> TruthAtHits:
    """The true surface at the fully covered hits, in the model's BRDF (TANGO's, or glTF's from
    the truth's base colour and metallic)."""
    direction = np.concatenate([cache.view(i).direction for i in range(len(cache))])
    view = torch.from_numpy(-direction[full]).double()
    normal = face_viewer(torch.from_numpy(truth["normal"][full]).double(), view)

    def at(key):
        return torch.from_numpy(truth[key][full]).float()

    rough = at("roughness").clamp(0.01, 1.0)
    colour, specular = (at(name) for name in brdf.parameters[:2])
    material = Material.of(brdf, colour, specular, rough)
    return TruthAtHits(normal.float(), view.float(), material, shadows)


def _lobe_budget(surface: TruthAtHits, srgb: dict, lobes: int, energy, noise: float, seed: int) -> dict:
    """One lobe count's error budget: the SG light fitted to each rung's image (with the surface's
    shadows, but for the unshadowed rung), its error above the target's noise, and the shares."""
    errors, psnrs, seconds = {}, {}, 0.0
    for rung in ("target", "direct", "unshadowed"):
        goal = torch.from_numpy(srgb[rung]).float()
        truth = surface if rung != "unshadowed" else dataclasses.replace(surface, shadows=None)
        light, sec = fit_light_to_image(truth, goal, lobes, energy, seed)
        with torch.no_grad():
            ours = linear_to_srgb(truth.radiance(Light.of(light)))
        # each Mitsuba image carries its noise; ours is noise-free
        errors[rung] = max(float(((ours - goal) ** 2).mean()) - noise, 0.0)
        psnrs[rung] = psnr(ours, goal)
        seconds += sec
    total = max(errors["target"], 1e-12)
    budget = {
        "psnr_db": psnrs,
        "error_mse": errors,
        "share": {
            "interreflection": (errors["target"] - errors["direct"]) / total,
            "shadows": (errors["direct"] - errors["unshadowed"]) / total,
            "brdf_light_and_closed_form": errors["unshadowed"] / total,
        },
        "fit_seconds": seconds,
    }
    if surface.shadows is not None:
        budget["agreement_db"] = {"shadowed": psnrs["direct"], "unshadowed": psnrs["unshadowed"]}
    return budget


def _hit_shadows(cache: RayCache, full: np.ndarray, directions: int, samples: int, seed: int) -> ShadowCache:
    """A shadow cache of the cache's hits where ``full``, each oriented to its viewer's side."""
    views = [cache.view(i) for i in range(len(cache))]
    points = np.concatenate([h.point for h in views])[full]
    faces = np.concatenate([h.face_normal for h in views])[full]
    rays = np.concatenate([h.direction for h in views])[full]
    mesh = TriMesh(cache.arrays["vertices"].astype(np.float64), cache.arrays["faces"].astype(np.int64))
    return ShadowCache(mesh, points, viewer_side_normals(faces, rays), EmbreeTracer(mesh), directions, samples, seed=seed)
