"""Encodings, the SVBRDF and normal networks, the tangent frame at the poles, and the SG light."""

from __future__ import annotations

import math

import pytest
import torch

from stages.model.lights.sg import SGLightModule, fibonacci_sphere
from stages.model.networks import (
    FourierFeatures,
    IdentityEncoding,
    NerfEncoding,
    NormalNet,
    SVBRDFNet,
    symmetric,
    tangent_frame,
)
from stages.render.envmap import equirect_directions
from stages.render.sg import sg_integral


def test_nerf_encoding():
    enc = NerfEncoding(3)
    x = torch.tensor([[0.25, -0.5, 1.0]])
    out = enc(x)
    assert out.shape == (1, 3 * 7) and enc.out_dim == 21
    torch.testing.assert_close(out[0, :3], x[0])
    # sin(2^k pi x) for k = 0..2, coordinate-major
    expected = torch.sin(math.pi * torch.tensor([0.25, 0.5, 1.0, -0.5, -1.0, -2.0, 1.0, 2.0, 4.0]))
    torch.testing.assert_close(out[0, 3:12], expected, atol=1e-6, rtol=0)


def test_fourier_features_statistics():
    g = torch.Generator().manual_seed(0)
    enc = FourierFeatures(4096, 2.5, generator=g)
    assert enc.out_dim == 3 + 8192
    assert enc.B.std().item() == pytest.approx(2.5, rel=0.03)  # 12288 draws: se ~0.6%
    x = torch.randn(10, 3)
    out = enc(x)
    torch.testing.assert_close(out[:, 3:4099] ** 2 + out[:, 4099:] ** 2, torch.ones(10, 4096))
    assert IdentityEncoding()(x) is x


def test_svbrdf_bounds_and_init():
    net = SVBRDFNet(NerfEncoding(4), width=32, init_specular=0.04, init_roughness=0.3, min_roughness=0.01)
    x = torch.randn(500, 3) * 3
    m = net(x)
    assert ((m.albedo > 0) & (m.albedo < 1)).all()
    assert ((m.roughness >= 0.01) & (m.roughness <= 1)).all()
    assert m.specular.mean().item() == pytest.approx(0.04, abs=0.01)
    assert m.roughness.mean().item() == pytest.approx(0.3, abs=0.02)


def test_diffuse_only_builds_no_specular_heads():
    full = SVBRDFNet(IdentityEncoding(), width=64)
    diffuse = SVBRDFNet(IdentityEncoding(), width=64, specular=False)
    assert diffuse.specular is None and diffuse.roughness is None
    n_full = sum(p.numel() for p in full.parameters())
    n_diff = sum(p.numel() for p in diffuse.parameters())
    assert n_diff < 0.5 * n_full
    m = diffuse(torch.randn(4, 3))
    assert m.specular is None and m.roughness is None


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_tangent_frame_orthonormal_everywhere(dtype):
    n = torch.randn(10000, 3, dtype=dtype)
    n = torch.cat([n, torch.tensor([[0, 0, 1.0], [0, 0, -1.0], [1e-9, 0, -1.0], [0, 0, 1.0 - 1e-7]], dtype=dtype)])
    n = n / n.norm(dim=-1, keepdim=True)
    t, b = tangent_frame(n)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    for u, v in ((t, b), (t, n), (b, n)):
        assert (u * v).sum(-1).abs().max() < tol
    for u in (t, b):
        assert (u.norm(dim=-1) - 1).abs().max() < tol
    # right-handed: t x b = n
    assert (torch.linalg.cross(t, b) - n).abs().max() < 10 * tol


def spherical_offset(n: torch.Tensor, d_theta: torch.Tensor, d_phi: torch.Tensor) -> torch.Tensor:
    """TANGO's parametrisation: offset the normal's spherical angles (theta azimuth, phi polar)."""
    theta = torch.atan2(n[:, 1], n[:, 0]) + d_theta
    phi = torch.acos(n[:, 2]) + d_phi
    return torch.stack([torch.sin(phi) * torch.cos(theta), torch.sin(phi) * torch.sin(theta), torch.cos(phi)], -1)


@pytest.mark.parametrize("pole", [1.0, -1.0])
def test_spherical_angles_are_singular_at_poles_but_tangent_offsets_are_not(pole):
    n = torch.tensor([[0.0, 0.0, pole]], dtype=torch.float64, requires_grad=True)
    d = torch.zeros(1, dtype=torch.float64, requires_grad=True)
    out = spherical_offset(n, d, torch.zeros(1, dtype=torch.float64))
    out.sum().backward()
    # acos' is infinite at +-1: the gradient reaching the normal is not finite
    assert not torch.isfinite(n.grad).all()
    # and an azimuth offset does not move a polar normal at all
    moved = spherical_offset(n.detach(), torch.tensor([0.5], dtype=torch.float64), torch.zeros(1, dtype=torch.float64))
    torch.testing.assert_close(moved, n.detach())
    # the tangent-frame offset: finite gradients, and each component tilts the normal
    net = NormalNet(IdentityEncoding(), width=16, max_delta=0.3).double()
    with torch.no_grad():
        net.mlp[-1].bias.copy_(torch.tensor([2.0, -1.0]))
    p = torch.zeros(1, 3, dtype=torch.float64, requires_grad=True)
    nn_ = torch.tensor([[0.0, 0.0, pole]], dtype=torch.float64, requires_grad=True)
    out = net(p, nn_)
    out.sum().backward()
    assert torch.isfinite(nn_.grad).all() and torch.isfinite(p.grad).all()
    assert all(torch.isfinite(q.grad).all() for q in net.parameters())
    tilt = torch.acos((out * nn_).sum(-1).clamp(-1, 1)).item()
    assert 0.1 < tilt <= math.atan(math.sqrt(2) * 0.3) + 1e-9


def test_normal_net_bounded_tilt():
    net = NormalNet(NerfEncoding(4), width=32, max_delta=0.2)
    with torch.no_grad():
        for p in net.parameters():
            p.normal_(0, 3.0)  # drive the tanh to saturation
    n = torch.randn(2000, 3)
    n = n / n.norm(dim=-1, keepdim=True)
    out = net(torch.randn(2000, 3), n)
    torch.testing.assert_close(out.norm(dim=-1), torch.ones(2000))
    tilt = torch.acos((out * n).sum(-1).clamp(-1, 1))
    assert tilt.max().item() <= math.atan(math.sqrt(2) * 0.2) + 1e-4


@pytest.mark.parametrize(("lobes", "rgb"), [(32, True), (64, False)])
def test_light_initial_energy_and_layout(lobes, rgb):
    light_mod = SGLightModule(lobes, rgb=rgb, total_energy=6.25)
    light = light_mod()
    assert light.axis.shape == (lobes, 3) and light.amplitude.shape == (lobes, 3)
    torch.testing.assert_close(light_mod.energy(), torch.full((3,), 6.25), rtol=1e-5, atol=0)
    assert (light.sharpness > 0).all() and (light.amplitude > 0).all()
    if not rgb:
        assert light_mod.log_energy.shape == (lobes, 1)
    # the energy is the true SG integral: a lone lobe's radiance integrates to it (uniform MC)
    g = torch.Generator().manual_seed(0)
    v = torch.randn(1 << 18, 3, generator=g, dtype=torch.float64)
    v = v / v.norm(dim=-1, keepdim=True)
    mc = 4 * math.pi * light.radiance(v.float()).double().mean(0)
    se = 4 * math.pi * light.radiance(v.float()).double().std(0) / math.sqrt(len(v))
    assert ((mc - 6.25).abs() <= 5 * se + 1e-4).all()
    assert sg_integral(light.sharpness[:1], light.amplitude[:1])[0, 0].item() == pytest.approx(6.25 / lobes, rel=1e-5)


def test_fibonacci_and_equirect():
    d = fibonacci_sphere(64)
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(64))
    assert d.mean(0).abs().max() < 0.02
    e = equirect_directions(8, 16)
    assert e.shape == (8, 16, 3) and e[0, :, 1].min() > 0.9 and e[-1, :, 1].max() < -0.9


def test_symmetry_prior():
    x = torch.tensor([[0.1, 0.2, -0.7], [0.1, 0.2, 0.7]])
    s = symmetric(x)
    torch.testing.assert_close(s[0], s[1])


def test_field_of_format_1_loads_with_the_same_light(tmp_path):
    """A ``field.pt`` of format 1 (the light as ``0.01 + softplus`` sharpness and softplus
    amplitude) loads into today's logarithmic light with the same lobes: written here from format
    1's definitions, not through the conversion."""
    from stages.config.guidance_modes import guidance_mode
    from stages.config.sections import OptimizeSettings
    from stages.core.provenance import ORIGIN_KEY
    from stages.model.checkpoint import load_field
    from stages.model.field import StyleField

    s = OptimizeSettings(width=16, light_lobes=4, light_init="broad")
    field = StyleField(s.field_settings())
    state = {k.replace("light.sg.", "light."): v for k, v in field.state_dict().items()}  # (formats 1, 2: at the top)
    gen = torch.Generator().manual_seed(3)
    sharp_raw = torch.randn(4, 1, generator=gen) * 3.0
    amp_raw = torch.randn(4, 3, generator=gen)
    del state["light.log_sharpness"], state["light.log_energy"]
    state["light.sharpness_raw"], state["light.amplitude_raw"] = sharp_raw, amp_raw
    origin = guidance_mode("image").origin_record("image targets: a test", test_only=False, prompt="p")
    torch.save({"format": 1, "settings": s.to_dict(), "prompt": "p", ORIGIN_KEY: origin, "state_dict": state}, tmp_path / "f.pt")
    loaded, _ = load_field(tmp_path / "f.pt")
    light = loaded.light.sg()
    lam = 0.01 + torch.log1p(torch.exp(sharp_raw))
    torch.testing.assert_close(light.sharpness, lam, rtol=1e-5, atol=0)
    torch.testing.assert_close(light.amplitude, torch.log1p(torch.exp(amp_raw)), rtol=1e-4, atol=1e-7)


def test_field_of_format_2_loads_its_lobes_into_the_sum(tmp_path):
    """A ``field.pt`` of format 2 (the SG lobes' parameters at the light's top, ``light.axis_raw``,
    before lights were sums of components) loads with the same lobes under ``light.sg.``."""
    from stages.config.guidance_modes import guidance_mode
    from stages.config.sections import OptimizeSettings
    from stages.core.provenance import ORIGIN_KEY
    from stages.model.checkpoint import load_field
    from stages.model.field import StyleField

    s = OptimizeSettings(width=16, light_lobes=4, light_init="tango", seed=5)
    field = StyleField(s.field_settings())
    with torch.no_grad():
        field.light.sg.log_energy.add_(torch.randn(4, 3, generator=torch.Generator().manual_seed(1)))
    state = {k.replace("light.sg.", "light."): v for k, v in field.state_dict().items()}
    assert "light.axis_raw" in state
    origin = guidance_mode("image").origin_record("image targets: a test", test_only=False, prompt="p")
    torch.save({"format": 2, "settings": s.to_dict(), "prompt": "p", ORIGIN_KEY: origin, "state_dict": state}, tmp_path / "f.pt")
    loaded, _ = load_field(tmp_path / "f.pt")
    for name, p in field.light.sg.named_parameters():
        assert torch.equal(getattr(loaded.light.sg, name), p), name
