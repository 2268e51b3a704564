"""Suns as a learnable light (:mod:`stages.model.lights.sun`): found in maps whose suns are known
by construction, decided by a measured criterion (``optimize.suns: auto``), fitted before the SG
lobes in the known-light mode, shadowed by rays through the mesh against the geometry's own
answer, and carried through an optimisation, its files and a reload."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from stages import optimize
from stages.config.sections import OptimizeSettings
from stages.geometry.meshio import TriMesh
from stages.geometry.tracing import EmbreeTracer
from stages.model.checkpoint import load_field
from stages.model.field import StyleField
from stages.model.lights import LightModule, SGLightModule, SunLightModule
from stages.model.lights.sun import find_suns, resolve_suns, sun_criterion
from stages.model.shadows import ShadowCache
from stages.render.envmap import SUN_RADIANCE, SUN_RADIUS, load_env, radiant_energy, sun_direction
from stages.render.light import Light, SunLight

TINY = dict(clip_tiny_test=True, image_size=64, width=32, crops=2, light_lobes=8, eval_width=32, material_frequencies=4)


def _disc_map(height: int, direction, radius: float, radiance, sky=(0.2, 0.3, 0.5)) -> np.ndarray:
    """A sky of constant radiance with a disc of ``radiance`` above it, each pixel's share of the
    disc counted by 8 x 8 subsamples (written here, not through the library's maps)."""
    w = 2 * height
    d = np.asarray(direction, np.float64) / np.linalg.norm(direction)
    sub = 8
    el = math.pi / 2 - math.pi * (np.arange(height * sub) + 0.5) / (height * sub)
    az = 2 * math.pi * (np.arange(w * sub) + 0.5) / (w * sub)
    ee, aa = np.meshgrid(el, az, indexing="ij")
    dirs = np.stack([np.cos(ee) * np.cos(aa), np.sin(ee), np.cos(ee) * np.sin(aa)], -1)
    inside = (dirs @ d) >= math.cos(radius)
    cover = inside.reshape(height, sub, w, sub).mean((1, 3))
    return (np.asarray(sky) + cover[..., None] * np.asarray(radiance)).astype(np.float32)


@pytest.mark.parametrize(("radius_deg", "height"), [(1.5, 512), (5.0, 256), (0.5, 1024)])
def test_a_disc_is_found_where_it_was_drawn(radius_deg, height):
    """Direction within a tenth of a pixel, irradiance (the disc's radiance times its solid angle)
    within 1%, radius within 5% (a pixel's size sets the finest radius a map holds)."""
    direction = np.array([0.3, 0.6, -0.5])
    direction /= np.linalg.norm(direction)
    rho = math.radians(radius_deg)
    radiance = np.array([900.0, 800.0, 600.0])
    env = _disc_map(height, direction, rho, radiance)
    (sun,), left = find_suns(env, 1)
    pixel = math.pi / height
    assert math.acos(min(1.0, float(sun.direction @ direction))) < 0.1 * pixel
    expected = radiance * 2 * math.pi * (1 - math.cos(rho))
    np.testing.assert_allclose(sun.irradiance, expected, rtol=0.01)
    assert sun.radius == pytest.approx(rho, rel=0.05)
    np.testing.assert_allclose(sun.background, [0.2, 0.3, 0.5], rtol=1e-6)
    # the disc taken out but for edge pixels it covers by less than 2% (their energy 0.3% of it), the sky kept
    np.testing.assert_allclose(left.min(axis=(0, 1)), [0.2, 0.3, 0.5], rtol=1e-6)
    rest = radiant_energy(left) - radiant_energy(np.broadcast_to(np.float32([0.2, 0.3, 0.5]), env.shape))
    assert (rest < 0.003 * expected).all() and (rest > -1e-6).all()


def test_the_procedural_sun_sky_has_its_sun_and_the_others_none():
    """``builtin:sun_sky``'s sun (its direction, 1.5 degrees, its radiance by construction) is
    found, and ``auto`` counts it; the sunset's glow, the studio's strip light and the overcast
    sky hold less than the default ``suns_share`` of their map's energy in a compact region: no
    sun."""
    env = load_env("builtin:sun_sky", 512)
    share = OptimizeSettings().suns_share
    count, record = sun_criterion(env, 512, share, 4)
    assert count == 1 and record["candidates"][0]["share"] > 0.5
    sun = find_suns(env, 1)[0][0]
    assert math.degrees(math.acos(min(1.0, float(sun.direction @ sun_direction())))) < 0.05
    assert sun.radius == pytest.approx(SUN_RADIUS, rel=0.06)
    np.testing.assert_allclose(sun.irradiance, np.array(SUN_RADIANCE) * 2 * math.pi * (1 - math.cos(SUN_RADIUS)), rtol=0.02)
    for name in ("sunset", "studio", "overcast"):
        assert sun_criterion(load_env(f"builtin:{name}", 512), 512, share, 4)[0] == 0, name
    # the share is the criterion's: a low enough share counts the sunset's glow (7.7 degrees, 8%)
    assert sun_criterion(load_env("builtin:sunset", 512), 512, 0.05, 4)[0] == 1
    # and the radius: with 4096 stored directions (finer visibility) that glow is resolved
    assert sun_criterion(load_env("builtin:sunset", 512), 4096, 0.05, 4)[0] == 0


def test_resolving_the_setting():
    assert resolve_suns(2, None, 512, 0.1) == (2, {"setting": 2, "suns": 2})
    count, record = resolve_suns("auto", None, 512, 0.1)
    assert count == 0 and "no environment" in record["why"]
    count, record = resolve_suns("auto", "builtin:sun_sky", 512, 0.2)
    assert count == 1 and record["environment"] == "builtin:sun_sky" and record["radius_limit_deg"] > 10
    with pytest.raises(ValueError, match="auto is decided before"):
        StyleField(OptimizeSettings(suns="auto").field_settings())


def test_holding_a_map_fits_the_suns_first_and_the_lobes_to_the_sky_left():
    """The known-light mode with a sun and SG lobes: the sun at the map's, the lobes fitted to
    the map without it, the light's energy the map's within 3%, and nothing learns."""
    module = LightModule([SGLightModule(8), SunLightModule(1)])
    record = module.hold("builtin:sun_sky", iterations=60)
    assert list(record)[:2] == ["map", "suns_found"] and "sg_fit_relative_rms" in record
    sun = module.sun()
    assert math.degrees(math.acos(min(1.0, float(sun.direction[0].double() @ torch.from_numpy(sun_direction()))))) < 0.05
    energy = radiant_energy(load_env("builtin:sun_sky", 512))
    np.testing.assert_allclose(module.energy().detach().numpy(), energy, rtol=0.03)
    # the lobes took the sky alone: their energy is the map's less the sun's
    np.testing.assert_allclose(module.sg.energy().detach().numpy(), energy - sun.irradiance[0].numpy(), rtol=0.05)
    assert not any(p.requires_grad for p in module.parameters())


def _shelf() -> TriMesh:
    """A floor (y = 0, 4 x 4) and a square shelf above it (y = 1, x and z in [-0.5, 0.5])."""
    v = np.array(
        [[-2, 0, -2], [2, 0, -2], [2, 0, 2], [-2, 0, 2], [-0.5, 1, -0.5], [0.5, 1, -0.5], [0.5, 1, 0.5], [-0.5, 1, 0.5]],
        np.float64,
    )
    f = np.array([[0, 2, 1], [0, 3, 2], [4, 6, 5], [4, 7, 6]], np.int64)
    return TriMesh(v, f)


def test_a_suns_shadow_falls_where_the_geometry_puts_it():
    """Points on the floor under a shelf, a sun 40 degrees up along x: a point is shadowed when its
    ray towards the sun's centre meets the shelf (its shadow is the square shifted by ``1 / tan
    40``), written here from the geometry; a disc's directions see the penumbra's width. Traced
    once for a sun that stays put, again once it moves."""
    mesh = _shelf()
    gen = np.random.default_rng(0)
    points = np.column_stack([gen.uniform(-1.5, 1.5, 400), np.zeros(400), gen.uniform(-1.5, 1.5, 400)])
    normals = np.tile([0.0, 1.0, 0.0], (400, 1))
    cache = ShadowCache(mesh, points, normals, EmbreeTracer(mesh), directions=64, samples=0)
    el = math.radians(40.0)
    sun = SunLight(torch.tensor([[math.cos(el), math.sin(el), 0.0]]), torch.ones(1, 3), torch.tensor([[1e-4]]), 4)
    shares = cache.sun_shares(sun)
    assert shares.shape == (400, 4)
    shift = 1.0 / math.tan(el)
    under = (np.abs(points[:, 0] + shift) < 0.5) & (np.abs(points[:, 2]) < 0.5)  # the square, moved along -x
    margin = (np.abs(np.abs(points[:, 0] + shift) - 0.5) < 0.01) | (np.abs(np.abs(points[:, 2]) - 0.5) < 0.01)
    lit = shares.numpy().mean(1)
    assert np.array_equal(lit[~margin] < 0.5, under[~margin])
    assert cache._sun.traces == 400
    cache.sun_shares(sun, torch.arange(10))
    assert cache._sun.traces == 400  # the same sun: nothing traced again
    moved = SunLight(torch.tensor([[math.cos(el + 0.05), math.sin(el + 0.05), 0.0]]), torch.ones(1, 3), torch.tensor([[1e-4]]), 4)
    cache.sun_shares(moved, torch.arange(10))
    assert cache._sun.traces == 10
    # a 10-degree disc: points near the shadow's edge see part of it
    wide = SunLight(sun.direction, torch.ones(1, 3), torch.tensor([[math.radians(10.0)]]), 16)
    part = cache.sun_shares(wide).numpy().mean(1)
    assert ((part > 0.05) & (part < 0.95)).sum() > 10


@pytest.mark.parametrize("brdf", ["tango", "gltf"])
def test_a_field_with_a_sun_shades_as_the_sum_of_its_components(brdf):
    lobe = "fitted" if brdf == "gltf" else "isotropic"
    s = OptimizeSettings(width=16, light_lobes=4, suns=1, brdf=brdf, specular_lobe=lobe)
    field = StyleField(s.field_settings()).eval()
    assert [c.kind for c in field.light.components] == ["sg", "sun"]
    g = torch.Generator().manual_seed(0)
    points = torch.rand(50, 3, generator=g) * 2 - 1
    normals = torch.nn.functional.normalize(torch.randn(50, 3, generator=g), dim=-1)
    view = torch.nn.functional.normalize(normals + 0.5 * torch.randn(50, 3, generator=g), dim=-1)
    with torch.no_grad():
        light = field.light()
        sg, sun = light.components
        both = field(points, normals, view)
        alone = [field(points, normals, view, Light.of(c)) for c in (sg, sun)]
    torch.testing.assert_close(both.shading.rgb, alone[0].shading.rgb + alone[1].shading.rgb)
    assert float(alone[1].shading.rgb.abs().max()) > 0  # the sun lights something


def test_an_optimisation_with_a_sun_writes_and_reloads_it(cache, tmp_path):
    """optimize with ``suns: 1``: the sun learns (its direction and irradiance move), its arrays
    and figures are in light.npz and meta.json, the resolved count is in the field file's
    settings and the field reloads with it."""
    s = OptimizeSettings(iterations=3, suns=1, **TINY)
    meta = optimize.run(cache / "train.npz", cache / "eval.npz", "a vase", tmp_path, s, "cpu")
    assert [c["kind"] for c in meta["light_components"]] == ["sg", "sun"]
    assert meta["suns"] == {"setting": 1, "suns": 1}
    start = SunLightModule.build(s.field_settings())()
    with np.load(tmp_path / "light.npz") as z:
        assert {"sun_direction", "sun_irradiance", "sun_radius"} <= set(z.files)
        assert not np.allclose(z["sun_direction"], start.direction.detach().numpy())
        assert not np.allclose(z["sun_irradiance"], start.irradiance.detach().numpy())
    field, settings = load_field(tmp_path / "field.pt")
    assert settings.suns == 1 and [c.kind for c in field.light.components] == ["sg", "sun"]
    with np.load(tmp_path / "light.npz") as z:
        np.testing.assert_array_equal(field.light.sun().direction.detach().numpy(), z["sun_direction"])
    assert json.loads((tmp_path / "meta.json").read_text())["light_components"][1]["suns"][0]["radius_deg"] > 0


@pytest.mark.slow(minutes=2)
def test_training_with_a_shadowed_sun_compiled_steps_as_eager(tmp_path):
    """The renderer compiled (``compile_shading: on``) with a sun and its shadow rays (a cache with
    visibility) and one bounce takes the eager run's losses for three steps and ends at its
    parameters: the sun's and the bounce's components, their visibility inputs and their padding
    go through the compiled graph
    (measured: losses equal to 1e-7, parameters within 5e-7; the compilation about 90 s from an
    empty cache)."""
    from stages.config.sections import NormalizeSettings, RaycacheSettings
    from stages.core.provenance import Timer
    from stages.geometry.meshio import save_ply
    from stages.geometry.normalization import normalize_mesh
    from stages.geometry.raycache import RayCache
    from stages.raycache import run as raycache_run
    from stages.training.optimizer import Optimizer

    save_ply(tmp_path / "vase.ply", normalize_mesh("builtin:vase", NormalizeSettings()).mesh)
    views = RaycacheSettings(
        views=4, resolution=48, eval_azimuths=2, eval_elevations_deg=(0.0,), eval_resolution=32, visibility="on"
    )
    raycache_run(tmp_path / "vase.ply", tmp_path / "train.npz", tmp_path / "eval.npz", tmp_path / "meta.json", views)

    def run(**compile_settings) -> Optimizer:
        s = OptimizeSettings(
            **{**TINY, "light_lobes": 4, "width": 16},
            iterations=5,
            bf16="off",
            bf16_networks="off",
            suns=1,
            bounces=1,
            bounce_every=2,
            **compile_settings,
        )
        return Optimizer(s, RayCache(tmp_path / "train.npz"), "a vase", "cpu")

    eager, compiled = run(compile_shading="off"), run(compile_shading="on")
    assert compiled.shading_path.startswith("torch.compile"), compiled.shading_path
    assert eager.views[0].shadows is not None  # the sun is shadowed
    for _ in range(3):
        a, b = eager.step(Timer()), compiled.step(Timer())
        assert b["loss"] == pytest.approx(a["loss"], rel=1e-5, abs=1e-6)
    for (name, pa), pb in zip(eager.field.named_parameters(), compiled.field.parameters(), strict=True):
        torch.testing.assert_close(pb.detach(), pa.detach(), rtol=1e-4, atol=1e-5, msg=name)
    traced = [v.shadows._sun.traces for v in eager.views._views.values() if v.shadows._sun is not None]
    assert sum(traced) > 0  # its shadow rays were traced
    bounced = [v.shadows._bounce.traces for v in compiled.views._views.values() if v.shadows._bounce is not None]
    assert sum(bounced) > 0 and compiled.bounce_refreshes == 2  # the bounce went through the graph, refreshed twice
    torch.testing.assert_close(compiled.field.light.bounce.table, eager.field.light.bounce.table, rtol=1e-4, atol=1e-6)
