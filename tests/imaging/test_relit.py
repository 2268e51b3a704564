"""Relighting judged by ground truth: the per-channel scale the scaled figures take, and the error
budget (:func:`stages.imaging.relit.relight_budget`) that says which recovered component costs how
many dB. Truth here is our own renderer's, with noise, on a small traced cache, so every figure's
origin is known; tests/reference/test_mitsuba_targets.py grades against Mitsuba's."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from stages.config.sections import RaycacheSettings
from stages.geometry.meshio import TriMesh
from stages.geometry.normalization import normalization_transform
from stages.geometry.normals import NormalSpec
from stages.geometry.raycache import RayCache, metric_views, trace_views
from stages.geometry.shapes import builtin_mesh
from stages.geometry.tracing import EmbreeTracer
from stages.imaging.relit import BudgetCase, budget_components, channel_scale, relight_budget, shade_surface, true_surface
from stages.imaging.targets import TargetSet
from stages.imaging.views import ViewStore
from stages.model.lights.sg import fit_sg_light
from stages.model.networks import Material
from stages.render.envmap import load_env
from stages.render.shading import SGLight

LOBES, ITERATIONS = 8, 30


def _srgb(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1's encoding of ``clip(x, 0, 1)``, written here from the standard."""
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def test_channel_scale_is_the_best_factor_of_the_srgb_figure():
    """Against a brute-force search over 10,001 factors: the factor that minimises the sRGB error
    per channel, also where a mirrored sun (300x the rest, clipped in the figure) pulls the linear
    least-squares factor far off (the mutation: that factor makes the render worse than no scale)."""
    rng = np.random.default_rng(0)
    t = rng.uniform(0.0, 0.8, (1000, 3))
    t[:20] = 300.0
    p = t * np.array([0.5, 0.4, 0.25])
    p[:20] = 2.0
    got = channel_scale(torch.from_numpy(p).float(), torch.from_numpy(t).float()).double().numpy()
    grid = np.exp(np.linspace(math.log(0.1), math.log(20.0), 10001))
    for c in range(3):
        err = ((_srgb(p[:, c, None] * grid) - _srgb(t[:, c, None])) ** 2).mean(0)
        best = grid[err.argmin()]
        assert got[c] == pytest.approx(best, rel=2e-3), (c, got[c], best)
        least_squares = (p[:, c] * t[:, c]).sum() / (p[:, c] ** 2).sum()
        worse = ((_srgb(p[:, c] * least_squares) - _srgb(t[:, c])) ** 2).mean()
        assert worse > ((_srgb(p[:, c]) - _srgb(t[:, c])) ** 2).mean()  # the linear factor is worse than none
    # an exact multiple comes back exactly; a channel that is all zero keeps 1
    q = t[20:] * np.array([2.0, 1.0, 0.0])
    s = channel_scale(torch.from_numpy(q).float(), torch.from_numpy(t[20:]).float())
    assert s[:2].tolist() == pytest.approx([0.5, 1.0], rel=1e-5) and float(s[2]) == 1.0


@pytest.fixture(scope="module")
def scene():
    """A traced cache of the vase (4 metric views, 40 pixels), its store, and a true glTF surface
    at every hit (smooth colours, a mixed metallic, varied roughness, the cache's normals)."""
    import tempfile
    from pathlib import Path

    tmp = Path(tempfile.mkdtemp())
    v, f = builtin_mesh("vase")
    mesh = TriMesh(normalization_transform(v).forward(v), f)
    s = RaycacheSettings(metrics_azimuths=2, metrics_elevations_deg=(0.0, 30.0), metrics_resolution=40)
    arrays, _ = trace_views(mesh, metric_views(s), EmbreeTracer(mesh))
    np.savez(tmp / "metrics.npz", **arrays)
    cache = RayCache(tmp / "metrics.npz")
    store = ViewStore(cache, "cpu", NormalSpec("smooth", 60.0))
    points = torch.cat([store[i].points for i in range(len(store))])
    normals = torch.cat([store[i].normals for i in range(len(store))])
    n = len(points)
    truth = {
        "base": (0.5 + 0.4 * torch.sin(3 * points + torch.tensor([0.0, 1.0, 2.0]))).clamp(0.05, 0.95),
        "metallic": (0.5 + 0.5 * torch.sin(5 * points[:, :1])).clamp(0.0, 1.0),
        "roughness": 0.2 + 0.6 * torch.sigmoid(4 * points[:, 1:2]),
        "normal": normals,
    }
    truth["albedo"] = truth["base"] * (1 - truth["metallic"])
    truth["specular"] = 0.04 + (truth["base"] - 0.04) * truth["metallic"]
    arrays = {k: x.numpy().astype(np.float16) for k, x in truth.items()}
    np.savez(tmp / "targets.npz", offsets=cache.arrays["offsets"], radiance=np.zeros((n, 3), np.float16), **arrays)
    targets = TargetSet(tmp / "targets.npz", cache)
    return store, targets, n


class _StandIn(torch.nn.Module):
    """A field holding a given surface at every hit of the store (cache order) and a given light."""

    brdf = "gltf"
    specular_lobe = "fitted"

    def __init__(self, surface: dict, light: SGLight) -> None:
        super().__init__()
        self.s, self.lit, self.at = surface, light, 0

    def surface(self, points, normals, view):
        sl = slice(self.at, self.at + len(points))
        self.at = (self.at + len(points)) % len(self.s["base"])
        s = self.s
        return Material.gltf(s["base"][sl], s["metallic"][sl], s["roughness"][sl]), s["normal"][sl]

    def light(self):
        return self.lit


def _perturbed(surface: dict, component: str) -> dict:
    out = dict(surface)
    if component == "base":
        out["base"] = surface["base"] * torch.tensor([0.5, 0.8, 1.0])
    elif component == "metallic":
        out["metallic"] = 1.0 - surface["metallic"]
    elif component == "roughness":
        out["roughness"] = (surface["roughness"] * 0.4).clamp(0.01, 1.0)
    elif component == "normal":
        tilt = torch.nn.functional.normalize(surface["normal"] + torch.tensor([0.3, 0.0, 0.0]), dim=-1)
        out["normal"] = tilt
    return out


@pytest.mark.parametrize("wrong", ["light", *budget_components("gltf")])
def test_the_budget_puts_a_gap_on_the_component_that_causes_it(scene, wrong):
    """A field that holds the truth but for one component (or, under the training light, the
    learned light): replacing that component alone reaches the ceiling, replacing any other alone
    changes nothing of its gap, and the cumulative gains are all zero but that component's, which
    is the whole gap; the cumulative gains add up to the gap, raw and scaled."""
    store, targets, n = scene
    train, _ = fit_sg_light(load_env("builtin:sun_sky"), LOBES, ITERATIONS)  # as the budget fits it
    view = torch.cat([store[i].view for i in range(len(store))])
    true = true_surface(targets, store, "gltf")
    rng = np.random.default_rng(1)
    truth_rgb = {}
    sunset, _ = fit_sg_light(load_env("builtin:sunset"), LOBES, ITERATIONS)
    for name, light in (("builtin:sun_sky", train), ("builtin:sunset", sunset)):
        clean = shade_surface(true, "gltf", view, light, "fitted").numpy()
        truth_rgb[name] = clean * (1 + 0.02 * rng.standard_normal(clean.shape)).astype(np.float32)
    coverage = np.ones(n, np.float32)
    coverage[::7] = 0.5  # partly covered hits never count
    cases = [
        BudgetCase("builtin:sun_sky", "training", truth_rgb["builtin:sun_sky"], coverage),
        BudgetCase("builtin:sunset", "relit", truth_rgb["builtin:sunset"], coverage),
    ]
    held = _perturbed(true, wrong)
    learned = SGLight(train.axis, train.sharpness, train.amplitude * (torch.tensor([1.6, 1.0, 0.6]) if wrong == "light" else 1.0))
    budget = relight_budget(_StandIn(held, learned), store, targets, cases, LOBES, ITERATIONS)
    for case in budget:
        assert case["pixels"] == int((coverage >= 0.999).sum())
        names = [sw["component"] for sw in case["swaps"]]
        assert names == (["light"] if case["role"] == "training" else []) + list(budget_components("gltf"))
        ceiling, base = case["ceiling"], case["recovered"]
        if wrong not in names:  # a relit render takes the environment's fit: the learned light is not in it
            assert base["psnr_db"] == pytest.approx(ceiling["psnr_db"], abs=1e-9)
            continue
        assert base["psnr_db"] < ceiling["psnr_db"] - 0.5
        for sw in case["swaps"]:
            alone, cumulative = sw["alone"], sw["cumulative"]
            if sw["component"] == wrong:
                assert alone["psnr_db"] == pytest.approx(ceiling["psnr_db"], abs=1e-9)
                assert cumulative["gain_db"] == pytest.approx(ceiling["psnr_db"] - base["psnr_db"], abs=1e-9)
            else:
                assert alone["psnr_db"] == pytest.approx(base["psnr_db"], abs=1e-9)
                assert cumulative["gain_db"] == pytest.approx(0.0, abs=1e-9)
        for key in ("gain_db", "gain_scaled_db"):
            total = sum(sw["cumulative"][key] for sw in case["swaps"])
            figure = key.replace("gain", "psnr")
            assert total == pytest.approx(ceiling[figure] - base[figure], abs=1e-9)
