"""The levers against baked-in lighting: the known-light mode (``optimize.light: fixed``, the SG
fit of ``light_map`` held still through a run and into every later file), the prior that keeps a
learned light's colour neutral (``optimize.light_neutral``), and glTF's metallic taken to 0 or 1
(``optimize.metallic_binary``) or started at a dielectric's (``optimize.init_metallic``), and the
surface priors: the material smooth over the surface (``optimize.material_smooth``) and the
predicted normals near the mesh's (``optimize.normal_tilt``)."""

from __future__ import annotations

import json
import math

import pytest
import torch
from test_optimize import TINY

from stages import optimize
from stages.config.sections import OptimizeSettings
from stages.core.errors import ConfigError
from stages.core.provenance import Timer
from stages.geometry.raycache import RayCache
from stages.model.checkpoint import load_field
from stages.model.lights.sg import SGLightModule, colour_spread, fit_sg_light
from stages.render.envmap import load_env
from stages.training.optimizer import Optimizer


def test_colour_spread_against_its_definition():
    """Written out here: per lobe the population variance of ln(E) over the channels, weighted by
    the lobe's share of the summed energy; zero for grey lobes of any brightness, (ln r)^2 * 2/3
    for a lobe (r, 1, 1/r); the weights carry no gradient (mutation: a brighter lobe alone cannot
    lower the prior by taking energy from a coloured one)."""
    e = torch.tensor([[2.0, 2.0, 2.0], [3.0, 1.0, 1 / 3.0], [0.5, 0.1, 0.2]], dtype=torch.float64)
    log_e = torch.log(e).requires_grad_()
    got = colour_spread(log_e)
    share = e.sum(1) / e.sum()
    var = [float(torch.var(torch.log(row), unbiased=False)) for row in e]
    assert float(got.detach()) == pytest.approx(sum(float(w) * v for w, v in zip(share, var, strict=True)), rel=1e-12)
    assert var[0] == 0.0 and var[1] == pytest.approx(2 / 3 * math.log(3.0) ** 2, rel=1e-12)
    got.backward()
    assert log_e.grad[0].abs().max() == 0.0  # a grey lobe is not pushed at all, whatever the weights
    assert float(colour_spread(torch.full((4, 3), -200.0))) == 0.0  # finite at the parametrisation's floor
    assert torch.isfinite(colour_spread(torch.tensor([[30.0, -300.0, 0.0]])))


def test_the_prior_pulls_a_coloured_light_towards_white(cache):
    """With light_neutral the loss grows by the weight times the spread (recorded per step), and
    the light ends greyer than the same run without it."""
    ends = {}
    for weight in (0.0, 1.0):
        s = OptimizeSettings(iterations=6, light_neutral=weight, light_lr=0.1, **TINY)
        opt = Optimizer(s, RayCache(cache / "train.npz"), "a vase made of wood", "cpu")
        with torch.no_grad():
            opt.field.light.sg.log_energy[:, 0] += 1.0  # a red light to start from
        for _ in range(6):
            row = opt.step(Timer())
        assert ("light_colour_spread" in row) == (weight > 0)
        ends[weight] = float(opt.field.light.colour_spread().detach())
    assert ends[1.0] < 0.8 * ends[0.0], ends


def test_a_fixed_light_is_the_maps_fit_and_never_moves(cache, tmp_path):
    """light: fixed puts the SG fit of the map in the light (the same lobes fit_sg_light gives for
    the field's number of lobes), trains without moving it, records it in the metadata and hands it
    to every later stage through field.pt; the networks still learn."""
    s = OptimizeSettings(iterations=4, light="fixed", light_map="builtin:sunset", **TINY)
    meta = optimize.run(cache / "train.npz", cache / "eval.npz", "a vase", tmp_path, s, "cpu")
    assert meta["light"]["mode"] == "fixed" and meta["light"]["map"] == "builtin:sunset"
    assert meta["light"]["lobes"] == TINY["light_lobes"] and 0 < meta["light"]["sg_fit_relative_rms"] < 1
    field, _ = load_field(tmp_path / "field.pt")
    fitted, _ = fit_sg_light(load_env("builtin:sunset"), TINY["light_lobes"], 400)
    light = field.light.sg()
    torch.testing.assert_close(light.axis, fitted.axis, rtol=0, atol=1e-6)
    torch.testing.assert_close(light.sharpness, fitted.sharpness, rtol=1e-5, atol=0)
    torch.testing.assert_close(light.amplitude, fitted.amplitude, rtol=1e-4, atol=0)
    learned = SGLightModule(TINY["light_lobes"], init="tango")
    assert not torch.allclose(learned().amplitude, light.amplitude)
    rows = (tmp_path / "loss.csv").read_text().splitlines()
    assert len(rows) == 5
    start = OptimizeSettings(iterations=1, **TINY)
    first = Optimizer(start, RayCache(cache / "train.npz"), "a vase", "cpu").field.svbrdf.state_dict()
    trained = field.svbrdf.state_dict()
    assert any(not torch.equal(first[k], trained[k]) for k in first)
    assert json.loads((tmp_path / "meta.json").read_text())["light"]["mode"] == "fixed"


def test_light_settings_are_checked():
    with pytest.raises(ConfigError, match="no light_map"):
        OptimizeSettings(light="fixed")
    with pytest.raises(ConfigError, match="light must be one of learn, fixed"):
        OptimizeSettings(light="baked")
    with pytest.raises(ConfigError, match="neither builtin"):
        OptimizeSettings(light="fixed", light_map="sky.png")
    with pytest.raises(ConfigError, match="no procedural environment"):
        OptimizeSettings(light="fixed", light_map="builtin:moon")
    with pytest.raises(ConfigError, match="does not move"):
        OptimizeSettings(light="fixed", light_map="builtin:sunset", light_neutral=1.0)
    with pytest.raises(ConfigError, match="light_rgb"):
        OptimizeSettings(light="fixed", light_map="builtin:sunset", light_rgb=False)
    with pytest.raises(ConfigError, match="light_neutral must be in"):
        OptimizeSettings(light_neutral=-1.0)


def test_the_metallic_starts_where_asked(cache):
    """init_metallic: the metallic head starts at that value everywhere (within 0.01: its last
    weights are small, not zero); without it, near the sigmoid's middle."""
    from stages.model.field import StyleField

    pts = torch.rand(2000, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1
    for start in (0.02, 0.9):
        field = StyleField(OptimizeSettings(init_metallic=start, **TINY).field_settings())
        m = field.svbrdf(pts).metallic.detach()
        assert float((m - start).abs().max()) < 0.01, (start, float(m.min()), float(m.max()))
    m = StyleField(OptimizeSettings(**TINY).field_settings()).svbrdf(pts).metallic.detach()
    assert 0.2 < float(m.mean()) < 0.8


def test_the_binary_prior_is_the_mean_of_m_one_minus_m_and_pushes_to_the_nearer_end(cache):
    """metallic_binary adds weight x mean(m (1 - m)) over the step's shaded points (recorded), and
    its gradient takes each point's metallic towards the nearer of 0 and 1."""
    from stages.model.networks import Material

    s = OptimizeSettings(iterations=2, metallic_binary=2.0, **TINY)
    opt = Optimizer(s, RayCache(cache / "train.npz"), "a vase", "cpu")
    m = torch.tensor([[0.1], [0.4], [0.6], [0.95]], requires_grad=True)
    mats = [
        Material.gltf(torch.full((2, 3), 0.5), m[:2], torch.full((2, 1), 0.5)),
        Material.gltf(torch.full((2, 3), 0.5), m[2:], torch.full((2, 1), 0.5)),
    ]
    stats: dict = {}
    total = opt.priors(mats, stats)
    expected = float((m * (1 - m)).mean())
    assert stats == {"metallic_between": pytest.approx(expected)} and float(total) == pytest.approx(2.0 * expected)
    total.backward()
    assert (m.grad[:2] > 0).all() and (m.grad[2:] < 0).all()  # descent lowers 0.1, 0.4 and raises 0.6, 0.95
    row = opt.step(Timer())
    assert "metallic_between" in row and "light_colour_spread" not in row


def test_metallic_settings_are_checked():
    with pytest.raises(ConfigError, match="metallic_binary is a prior on glTF's metallic"):
        OptimizeSettings(metallic_binary=0.1, brdf="tango")
    with pytest.raises(ConfigError, match="init_metallic must be in"):
        OptimizeSettings(init_metallic=1.5)
    with pytest.raises(ConfigError, match="brdf tango does not have"):
        OptimizeSettings(init_metallic=0.0, brdf="tango")


def test_material_variation_against_its_definition():
    """Written out here from nvdiffrec's regulariser: the mean over points and channels of |change|
    of the colour, plus the same over the other parameters (glTF: metallic and roughness; TANGO:
    specular colour and roughness); zero for the same material; its gradient is the sign's."""
    from stages.model.networks import Material, cat_materials, material_variation

    g = torch.Generator().manual_seed(3)
    base, met, rough = (torch.rand(5, c, generator=g, dtype=torch.float64) for c in (3, 1, 1))
    base2, met2, rough2 = (torch.rand(5, c, generator=g, dtype=torch.float64) for c in (3, 1, 1))
    base.requires_grad_()
    a, b = Material.gltf(base, met, rough), Material.gltf(base2, met2, rough2)
    colour = sum(abs(float(base[i, c] - base2[i, c])) for i in range(5) for c in range(3)) / 15
    others = sum(abs(float(met[i, 0] - met2[i, 0])) + abs(float(rough[i, 0] - rough2[i, 0])) for i in range(5)) / 10
    got = material_variation(a, b)
    assert float(got) == pytest.approx(colour + others, rel=1e-12)
    got.backward()
    torch.testing.assert_close(base.grad, torch.sign(base - base2).detach() / 15)
    assert float(material_variation(a, a)) == 0.0
    spec, spec2 = torch.rand(5, 3, generator=g), torch.rand(5, 3, generator=g)
    t1, t2 = Material(base2.float(), spec, rough.float()), Material(base2.float(), spec2, rough2.float())
    expect = float((spec - spec2).abs().sum() + (rough - rough2).abs().sum().float()) / 20
    assert float(material_variation(t1, t2)) == pytest.approx(expect, rel=1e-5)
    halves = cat_materials([Material.gltf(base2[:2], met2[:2], rough2[:2]), Material.gltf(base2[2:], met2[2:], rough2[2:])])
    assert torch.equal(halves.base, base2) and torch.equal(halves.metallic, met2) and torch.equal(halves.albedo, b.albedo)


def test_normal_tilt_is_one_minus_the_cosine_of_the_angle():
    """Against angles set by hand: tilts of 0, 30 and 90 degrees give the mean of 1 - cos; a tilt of
    theta is about theta^2 / 2 when small; finite with a finite gradient at zero tilt."""
    from stages.model.networks import normal_tilt

    geo = torch.tensor([[0.0, 0.0, 1.0]] * 3, dtype=torch.float64)
    angles = torch.tensor([0.0, math.pi / 6, math.pi / 2], dtype=torch.float64)
    pred = torch.stack([torch.sin(angles), torch.zeros(3, dtype=torch.float64), torch.cos(angles)], dim=-1)
    assert float(normal_tilt(pred, geo)) == pytest.approx((0 + (1 - math.sqrt(3) / 2) + 1) / 3, rel=1e-12)
    small = torch.tensor([[math.sin(1e-3), 0.0, math.cos(1e-3)]], dtype=torch.float64)
    assert float(normal_tilt(small, geo[:1])) == pytest.approx(0.5e-6, rel=1e-6)
    flat = geo[:1].clone().requires_grad_()
    normal_tilt(flat, geo[:1]).backward()
    assert torch.isfinite(flat.grad).all()


@pytest.mark.parametrize("prior, stat", [("material_smooth", "material_variation"), ("normal_tilt", "normal_tilt")])
def test_the_surface_priors_lower_what_they_measure(cache, prior, stat):
    """material_smooth and normal_tilt add weight x their measure to the loss, are recorded per step,
    and a strong weight leaves less of it after the same steps than a run without (whose measure is
    computed here from its field with the same functions)."""
    from stages.model.networks import material_variation, normal_tilt

    ends = {}
    for weight in (0.0, 50.0):
        s = OptimizeSettings(iterations=8, lr=0.02, **{prior: weight}, **TINY)
        opt = Optimizer(s, RayCache(cache / "train.npz"), "a vase made of wood", "cpu")
        for _ in range(8):
            row = opt.step(Timer())
        assert (stat in row) == (weight > 0)
        v = opt.views[0]
        sel = torch.arange(0, v.points.shape[0], 7)
        with torch.no_grad():
            out = v.shade(opt.field, sel)
            x = v.points[sel]
            if prior == "material_smooth":
                jitter = torch.randn(x.shape, generator=torch.Generator().manual_seed(1)) * s.material_smooth_radius
                ends[weight] = float(material_variation(out.material, opt.field.material(x + jitter)))
            else:
                ends[weight] = float(normal_tilt(out.normal, v.normals[sel]))
    assert ends[50.0] < 0.7 * ends[0.0], ends


def test_surface_prior_settings_are_checked(cache):
    # the default prior on the normals has nothing to act on without the normal network: no error,
    # nothing recorded
    s = OptimizeSettings(iterations=1, normal_network=False, **TINY)
    assert s.normal_tilt > 0
    row = Optimizer(s, RayCache(cache / "train.npz"), "a vase", "cpu").step(Timer())
    assert "normal_tilt" not in row
    with pytest.raises(ConfigError, match="material_smooth must be in"):
        OptimizeSettings(material_smooth=-0.1)
    with pytest.raises(ConfigError, match="material_smooth_radius must be in"):
        OptimizeSettings(material_smooth_radius=0.0)
    with pytest.raises(ConfigError, match="normal_tilt must be a finite number"):
        OptimizeSettings(normal_tilt=float("nan"))


def test_a_killed_run_resumes_only_under_the_same_light_file(cache, tmp_path):
    """light: fixed with a file: the checkpoint records the file's sha256, a killed run resumes when
    the file is unchanged, and starts afresh (its light the new file's fit) when it was edited; the
    file is among the run's recorded inputs."""
    from stages.render.envmap import procedural_envmap
    from stages.render.hdrio import write_hdr

    hdr = tmp_path / "light.hdr"
    write_hdr(hdr, procedural_envmap("sunset", 32))
    s = OptimizeSettings(iterations=4, checkpoint_every=2, light="fixed", light_map=str(hdr), **TINY)
    args = (cache / "train.npz", cache / "eval.npz", "a vase")
    out = tmp_path / "run"
    optimize.run(*args, out, s, "cpu", stop_after=3)
    same = optimize.run(*args, out, s, "cpu")
    assert same["resumed_from_iteration"] == 2 and same["inputs"]["light_map"]["path"] == str(hdr)
    assert same["light"]["sha256"] == same["inputs"]["light_map"]["sha256"]
    optimize.run(*args, out, s, "cpu", stop_after=3)
    write_hdr(hdr, procedural_envmap("overcast", 32))  # the user edits the map meanwhile
    edited = optimize.run(*args, out, s, "cpu")
    assert edited["resumed_from_iteration"] is None and edited["light"]["sha256"] != same["light"]["sha256"]
    fitted, _ = fit_sg_light(load_env(str(hdr)), TINY["light_lobes"], 400)
    torch.testing.assert_close(load_field(out / "field.pt")[0].light.sg().amplitude, fitted.amplitude, rtol=1e-4, atol=0)
    with pytest.raises(ConfigError, match="would be ignored"):
        OptimizeSettings(light_map="builtin:sunset")
