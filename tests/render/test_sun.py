"""Suns (:mod:`stages.render.light.sun`) against references written here from the textbook
formulas, never through the functions under test: the irradiance of a spherical cap on a plane
(closed form) and on a sphere where the cap crosses the horizon (a dense grid over the cap), the
BRDFs' specular and diffuse terms over the disc (a dense grid, each model's formula written out),
a mirror's image of the disc, the gradients in direction, size and colour against finite
differences, and finite values and gradients at the extremes in float32 and under bfloat16
autocast."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from stages.render.brdf import GLTF, TANGO
from stages.render.light import Light
from stages.render.light.sun import SunLight, cap_offsets, disc_directions, solid_angle, sun_radiance_reference
from stages.render.shading import tangent_frame

F64 = torch.float64


def unit(*v) -> torch.Tensor:
    t = torch.tensor(v, dtype=F64)
    return t / t.norm()


def material(n: int, albedo=0.5, specular=None, roughness=None, base=None, metallic=None):
    """A material of ``n`` points with the channels a BRDF reads (glTF's from base and metallic,
    as its ``channels`` makes them)."""

    def full(x, width):
        return None if x is None else torch.full((n, width), float(x), dtype=F64)

    if base is not None:
        b, m = full(base, 3), full(metallic, 1)
        return SimpleNamespace(
            albedo=b * (1 - m), specular=0.04 * (1 - m) + b * m, roughness=full(roughness, 1), base=b, metallic=m
        )
    return SimpleNamespace(
        albedo=full(albedo, 3), specular=full(specular, 3), roughness=full(roughness, 1), base=None, metallic=None
    )


def cap_grid(axis: torch.Tensor, radius: float, rings: int = 400, spokes: int = 400):
    """A dense midpoint grid over the cap of ``axis`` and angular ``radius``: directions ``(P, 3)``
    and their solid angles ``(P,)`` (uniform in ``cos theta`` and azimuth: equal cells), built
    here with its own frame."""
    helper = torch.tensor([1.0, 0.0, 0.0], dtype=F64) if abs(float(axis[0])) < 0.9 else torch.tensor([0.0, 1.0, 0.0], dtype=F64)
    t = torch.linalg.cross(axis, helper)
    t = t / t.norm()
    b = torch.linalg.cross(axis, t)
    cos_r = math.cos(radius)
    c = 1.0 - (torch.arange(rings, dtype=F64) + 0.5) / rings * (1.0 - cos_r)
    phi = (torch.arange(spokes, dtype=F64) + 0.5) / spokes * 2 * math.pi
    c, phi = torch.meshgrid(c, phi, indexing="ij")
    s = torch.sqrt(1 - c * c)
    dirs = c[..., None] * axis + s[..., None] * (torch.cos(phi)[..., None] * t + torch.sin(phi)[..., None] * b)
    omega = 2 * math.pi * (1 - cos_r)
    return dirs.reshape(-1, 3), torch.full((rings * spokes,), omega / (rings * spokes), dtype=F64)


def tango_f(n, v, w, f0, r):
    """TANGO's BRDF times the cosine, written out: ``albedo / pi`` aside, the SG NDF ``exp(2 / r^4
    (n.h - 1)) / (pi r^4)``, Schlick's Fresnel at ``v.h``, Smith-Schlick ``k = (r + 1)^2 / 8``."""
    h = (v + w) / (v + w).norm(dim=-1, keepdim=True)
    nh, vh, nl, nv = (n * h).sum(-1), (v * h).sum(-1), (n * w).sum(-1), (n * v).sum(-1)
    d = torch.exp(2 / r**4 * (nh - 1)) / (math.pi * r**4)
    f = f0 + (1 - f0) * (1 - vh) ** 5
    k = (r + 1) ** 2 / 8
    g = nl / (nl * (1 - k) + k) * nv / (nv * (1 - k) + k)
    return torch.where(nl > 0, d * f * g / (4 * nl * nv) * nl, torch.zeros_like(nl))


def gltf_f(n, v, w, base, metallic, r):
    """glTF 2.0 Appendix B's BRDF times the cosine, written out: GGX, the separable Smith-GGX
    visibility, ``fresnel_mix`` for the dielectric and ``conductor_fresnel`` for the metal, mixed by
    metallic -> (diffuse, specular) per channel of ``base``."""
    h = (v + w) / (v + w).norm(dim=-1, keepdim=True)
    nh, vh, nl, nv = (n * h).sum(-1), (v * h).sum(-1), (n * w).sum(-1), (n * v).sum(-1)
    a2 = r**4
    d = a2 / (math.pi * (nh * nh * (a2 - 1) + 1) ** 2)
    vis = 1 / ((nl + torch.sqrt(a2 + (1 - a2) * nl * nl)) * (nv + torch.sqrt(a2 + (1 - a2) * nv * nv)))
    spec = d * vis
    f_d = 0.04 + 0.96 * (1 - vh) ** 5
    f_m = base + (1 - base) * (1 - vh) ** 5
    diffuse = (1 - metallic) * (1 - f_d) * base / math.pi
    specular = (1 - metallic) * f_d * spec + metallic * f_m * spec
    lit = nl > 0
    return torch.where(lit, diffuse * nl, 0 * nl), torch.where(lit, specular * nl, 0 * nl)


def one_sun(axis, irradiance, radius, samples=8, dtype=F64):
    return SunLight(
        axis.reshape(1, 3).to(dtype),
        torch.as_tensor(irradiance, dtype=dtype).reshape(1, -1).expand(1, 3).clone(),
        torch.tensor([[radius]], dtype=dtype),
        samples,
    )


# ---------------------------------------------------------------------------- the quadrature
def test_the_caps_directions_have_equal_solid_angle_and_stay_inside_it():
    """Directions inside the disc, their heights uniform over the cap (the mean cosine with the
    axis is the cap's own, ``1 - (1 - cos rho) / 2``), apart and unit also for a disc of 1e-6
    radians (float64's ``1 - cos`` there would be 0 in float32)."""
    axis = unit(0.3, -0.5, 0.8).reshape(1, 3)
    for radius in (1e-6, math.radians(1.5), 0.5, 1.5):
        u, phi = cap_offsets(64, F64)
        dirs = disc_directions(axis, torch.tensor([[radius]], dtype=F64), u, phi)[0]
        cos = dirs @ axis[0]
        torch.testing.assert_close(dirs.norm(dim=-1), torch.ones(64, dtype=F64))
        assert bool((cos >= math.cos(radius) - 1e-12).all())
        angles = torch.acos(torch.clamp(cos, -1, 1))
        assert float(angles.max()) > 0.9 * radius, radius  # the whole cap used, not its centre
        torch.testing.assert_close(cos.mean(), torch.tensor(1 - (1 - math.cos(radius)) / 2, dtype=F64))
    torch.testing.assert_close(solid_angle(torch.tensor(math.pi / 2, dtype=F64)), torch.tensor(2 * math.pi, dtype=F64))


def test_the_frame_is_orthonormal_everywhere_including_the_poles():
    axes = torch.nn.functional.normalize(torch.randn(500, 3, dtype=F64, generator=torch.Generator().manual_seed(0)), dim=-1)
    axes = torch.cat([axes, torch.tensor([[0, 0, 1.0], [0, 0, -1.0], [0, 1.0, 0], [1e-12, 0, -1.0]], dtype=F64)])
    axes = torch.nn.functional.normalize(axes, dim=-1)
    t, s = tangent_frame(axes)
    for a, b in ((t, s), (t, axes), (s, axes)):
        assert float((a * b).sum(-1).abs().max()) < 1e-12
    torch.testing.assert_close(torch.linalg.cross(t, s), axes)


# ------------------------------------------------------------------- irradiance: closed forms
@pytest.mark.parametrize("elevation_deg", [90.0, 60.0, 25.0])
@pytest.mark.parametrize("radius_deg", [0.0001, 1.5, 10.0])
def test_a_disc_on_a_lambertian_plane_gives_the_caps_closed_form_irradiance(elevation_deg, radius_deg):
    """A cap of radiance ``L`` wholly above the horizon gives a plane the irradiance ``pi L
    sin^2(rho) cos(theta_c)`` (the cap's projected solid angle), so a Lambertian plane of albedo
    ``a`` reflects ``a L sin^2(rho) cos(theta_c)``; in terms of the sun's irradiance ``E = L
    Omega``: ``a E cos(theta_c) (1 + cos rho) / 2``."""
    rho, el = math.radians(radius_deg), math.radians(elevation_deg)
    axis = unit(0.0, math.sin(el), math.cos(el))
    e = 2.5
    sun = one_sun(axis, e, rho, samples=64)
    n = torch.tensor([[0.0, 1.0, 0.0]], dtype=F64)
    v = unit(0.3, 0.8, -0.2).reshape(1, 3)
    out = sun.shade(TANGO, n, v, material(1, albedo=0.7), None, None)
    radiance = e / (2 * math.pi * (1 - math.cos(rho)))
    expected = 0.7 * radiance * math.sin(rho) ** 2 * math.sin(el)  # cos(theta_c) = sin(elevation)
    torch.testing.assert_close(out.diffuse[0], torch.full((3,), expected, dtype=F64), rtol=2e-3, atol=0)
    assert float(out.specular.abs().max()) == 0.0


@pytest.mark.parametrize("brdf", ["tango", "gltf"])
def test_a_disc_across_a_spheres_horizon_against_a_dense_grid(brdf):
    """Points of a unit sphere around its terminator, a 10-degree disc partly below their horizon:
    the diffuse term against a 400 x 400 grid over the cap (the BRDF's formula written out, the
    horizon where ``n . l`` turns negative)."""
    rho = math.radians(10.0)
    axis = unit(1.0, 0.2, 0.0)
    theta = torch.linspace(math.radians(60), math.radians(120), 13, dtype=F64)  # normals' angle from the axis
    n = torch.stack([torch.cos(theta), torch.zeros_like(theta), torch.sin(theta)], -1)
    n = torch.nn.functional.normalize(n + torch.tensor([0.0, 0.2, 0.0], dtype=F64) * torch.cos(theta)[:, None], dim=-1)
    v = torch.nn.functional.normalize(n + torch.tensor([0.0, 0.0, 0.5], dtype=F64), dim=-1)
    e = 3.0
    sun = one_sun(axis, e, rho, samples=512)
    m = (
        material(len(n), albedo=0.6, specular=0.04, roughness=0.9)
        if brdf == "tango"
        else material(len(n), base=0.6, metallic=0.0, roughness=0.9)
    )
    out = sun.shade(TANGO if brdf == "tango" else GLTF, n, v, m, None, None)
    dirs, omega = cap_grid(axis, rho)
    radiance = e / (2 * math.pi * (1 - math.cos(rho)))
    for i in range(len(n)):
        ni, vi = n[i].expand_as(dirs), v[i].expand_as(dirs)
        nl = (ni * dirs).sum(-1)
        if brdf == "tango":
            diffuse = 0.6 / math.pi * torch.clamp(nl, min=0)
        else:
            diffuse, _ = gltf_f(ni, vi, dirs, 0.6, 0.0, 0.9)
        expected = float((diffuse * omega).sum() * radiance)
        assert float(out.diffuse[i, 0]) == pytest.approx(expected, rel=0.02, abs=2e-3 * e), (i, float(theta[i]))


# ------------------------------------------------------------------------ specular, by the grid
@pytest.mark.parametrize("brdf", ["tango", "gltf"])
@pytest.mark.parametrize("roughness", [0.25, 0.5, 1.0])
@pytest.mark.parametrize("elevation_deg", [50.0, 12.0])
def test_the_specular_term_over_a_disc_against_a_dense_grid(brdf, roughness, elevation_deg):
    """A 3-degree sun at several angles from the mirror direction of a glossy surface, high and
    grazing (where Fresnel's term is large): the specular (and glTF's layered diffuse) term
    against the BRDF's formula over a 400 x 400 grid of the disc. Within 2% where the lobe is
    wider than the quadrature's cells (these roughnesses)."""
    rho = math.radians(3.0)
    n = torch.tensor([[0.0, 1.0, 0.0]], dtype=F64).expand(7, 3)
    el = math.radians(elevation_deg)
    axis = unit(0.0, math.sin(el), math.cos(el))
    offsets = torch.linspace(-min(0.3, el / 2), min(0.3, el / 2), 7, dtype=F64)
    v = torch.stack([torch.zeros(7, dtype=F64), torch.sin(el + offsets), -torch.cos(el + offsets)], -1)
    e = 2.0
    sun = one_sun(axis, e, rho, samples=64)
    if brdf == "tango":
        out = sun.shade(TANGO, n, v, material(7, albedo=0.0, specular=0.3, roughness=roughness), None, None)
    else:
        out = sun.shade(GLTF, n, v, material(7, base=0.8, metallic=0.5, roughness=roughness), None, None)
    dirs, omega = cap_grid(axis, rho)
    radiance = e / (2 * math.pi * (1 - math.cos(rho)))
    peak = float(out.specular[:, 0].max())
    for i in range(7):
        ni, vi = n[i].expand_as(dirs), v[i].expand_as(dirs)
        if brdf == "tango":
            spec = tango_f(ni, vi, dirs, 0.3, roughness)
            diff = torch.zeros_like(spec)
        else:
            diff, spec = gltf_f(ni, vi, dirs, 0.8, 0.5, roughness)
        # 2%, or 1% of the highlight's peak in its tails (where the cells' widening lifts a value that is small)
        assert float(out.specular[i, 0]) == pytest.approx(float((spec * omega).sum() * radiance), rel=0.02, abs=0.01 * peak), i
        assert float(out.diffuse[i, 0]) == pytest.approx(float((diff * omega).sum() * radiance), rel=0.02, abs=1e-9), i


def test_a_mirror_sees_the_disc_at_its_radiance_and_nothing_outside_it():
    """A near-mirror (roughness 0.01) under a 1.5-degree sun, viewed so that its mirror direction
    sweeps across the disc: inside the disc's inner half the reflected radiance is the disc's
    radiance times Fresnel and shadowing (``F G``, written out), within 12% for 8 directions (the
    cells' blur, :func:`~stages.render.light.sun.cell_widening`); beyond 1.6 radii it is below 5%
    of it; and the total over the sweep (the disc's image integrated) matches the grid's."""
    rho = math.radians(1.5)
    el = math.radians(60)
    axis = unit(0.0, math.sin(el), math.cos(el))
    sweep = torch.linspace(-2.0 * rho, 2.0 * rho, 81, dtype=F64)
    v = torch.stack([torch.zeros_like(sweep), torch.sin(el + sweep), -torch.cos(el + sweep)], -1)
    n = torch.tensor([[0.0, 1.0, 0.0]], dtype=F64).expand_as(v)
    radiance = 1.0 / (2 * math.pi * (1 - math.cos(rho)))
    out = sun = None
    sun = one_sun(axis, 1.0, rho, samples=8)
    out = sun.shade(TANGO, n, v, material(len(v), albedo=0.0, specular=1.0, roughness=0.01), None, None).specular[:, 0]
    k = (1.01) ** 2 / 8
    nv = torch.sin(el + sweep)
    g = (nv / (nv * (1 - k) + k)) ** 2  # mirror: n.l = n.v
    expected = radiance * g
    inside = sweep.abs() < 0.5 * rho
    outside = sweep.abs() > 1.6 * rho
    ratio = out[inside] / expected[inside]
    assert float((ratio - 1).abs().max()) < 0.12, ratio
    assert float((out[outside] / radiance).max()) < 0.05
    # the image's integral over the sweep against the exact disc's (a unit-height chord profile)
    exact = torch.where(sweep.abs() <= rho, expected, torch.zeros_like(expected))
    assert float(out.sum()) == pytest.approx(float(exact.sum()), rel=0.05)


# --------------------------------------------------------------------- the batched form, shadows
@pytest.mark.parametrize("brdf", [TANGO, GLTF])
def test_several_suns_with_shadows_equal_the_plain_loop(brdf):
    g = torch.Generator().manual_seed(3)
    n = torch.nn.functional.normalize(torch.randn(40, 3, dtype=F64, generator=g), dim=-1)
    v = torch.nn.functional.normalize(n + torch.randn(40, 3, dtype=F64, generator=g) * 0.4, dim=-1)
    from stages.render.shading import face_viewer

    n = face_viewer(n, v)
    axis = torch.nn.functional.normalize(torch.randn(3, 3, dtype=F64, generator=g), dim=-1)
    irradiance = torch.rand(3, 3, dtype=F64, generator=g) * 4
    radius = torch.tensor([[1e-4], [0.03], [0.2]], dtype=F64)
    sun = SunLight(axis, irradiance, radius, 6)
    vis = torch.rand(40, 18, dtype=F64, generator=g)
    m = (
        material(40, albedo=0.4, specular=0.2, roughness=0.3)
        if brdf is TANGO
        else material(40, base=0.4, metallic=0.3, roughness=0.3)
    )
    for visibility in (None, vis):
        out = sun.shade(brdf, n, v, m, None, visibility)
        ref = sun_radiance_reference(brdf, n, v, m, axis, irradiance, radius, 6, visibility)
        torch.testing.assert_close(out.diffuse, ref.diffuse)
        torch.testing.assert_close(out.specular, ref.specular)
    zero = sun.shade(brdf, n, v, m, None, torch.zeros_like(vis))
    assert float(zero.rgb.abs().max()) == 0.0


def test_a_suns_radiance_energy_and_arrays():
    """Its radiance is ``E / Omega`` inside the disc and 0 outside; integrated over a fine
    equirectangular image it gives back ``E`` (its energy); a sum with SG lobes adds both."""
    rho = math.radians(8.0)
    axis = unit(0.2, 0.7, -0.4)
    sun = one_sun(axis, [2.0, 1.0, 0.5], rho, dtype=torch.float32)
    light = Light.of(sun)
    h, w = 720, 1440
    image = light.equirect(h, w).double()
    theta = (torch.arange(h, dtype=F64) + 0.5) / h * math.pi
    area = torch.sin(theta)[:, None] * (math.pi / h) * (2 * math.pi / w)
    total = (image * area[..., None]).sum((0, 1))
    torch.testing.assert_close(total, torch.tensor([2.0, 1.0, 0.5], dtype=F64), rtol=0.02, atol=0)
    torch.testing.assert_close(sun.energy(), torch.tensor([2.0, 1.0, 0.5]))
    assert sorted(sun.arrays()) == ["sun_direction", "sun_irradiance", "sun_radius"]
    d = sun.describe()
    assert d["kind"] == "sun" and d["suns"][0]["radius_deg"] == pytest.approx(8.0, rel=1e-5)
    assert d["suns"][0]["elevation_deg"] == pytest.approx(math.degrees(math.asin(float(axis[1]))), abs=1e-3)


# ------------------------------------------------------------------------------- gradients
def test_gradients_in_direction_size_and_colour_match_finite_differences():
    """float64 gradcheck of the shaded colour in the sun's direction (through a normalised raw
    vector), angular radius and irradiance, for both BRDFs, shadowed."""
    g = torch.Generator().manual_seed(5)
    n = torch.nn.functional.normalize(torch.randn(6, 3, dtype=F64, generator=g) + torch.tensor([0, 2.0, 0], dtype=F64), dim=-1)
    v = torch.nn.functional.normalize(n + 0.3 * torch.randn(6, 3, dtype=F64, generator=g), dim=-1)
    vis = torch.rand(6, 4, dtype=F64, generator=g)
    for brdf, m in (
        (TANGO, material(6, albedo=0.5, specular=0.3, roughness=0.2)),
        (GLTF, material(6, base=0.7, metallic=0.6, roughness=0.15)),
    ):

        def shaded(raw, radius, irradiance, brdf=brdf, m=m):
            sun = SunLight(torch.nn.functional.normalize(raw, dim=-1), irradiance, radius, 4)
            return sun.shade(brdf, n, v, m, None, vis).rgb

        raw = torch.tensor([[0.2, 1.0, 0.3]], dtype=F64, requires_grad=True)
        radius = torch.tensor([[0.1]], dtype=F64, requires_grad=True)
        irradiance = torch.tensor([[1.0, 2.0, 0.5]], dtype=F64, requires_grad=True)
        assert torch.autograd.gradcheck(shaded, (raw, radius, irradiance), eps=1e-6, atol=1e-6, rtol=1e-4)


# ------------------------------------------------------------------------------- extremes
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_finite_values_and_gradients_at_the_extremes(dtype):
    """Radii 1e-6 to 1.2 radians, roughness 0.01 and 1, grazing views (``n . v`` 1e-3), suns at the
    horizon, the poles and behind the surface: every value and gradient finite; a sun below the
    horizon gives nothing."""
    from stages.render.shading import face_viewer

    pts = 64
    g = torch.Generator().manual_seed(7)
    n = torch.nn.functional.normalize(torch.randn(pts, 3, generator=g, dtype=F64), dim=-1)
    tangent = torch.nn.functional.normalize(torch.linalg.cross(n, torch.randn(pts, 3, generator=g, dtype=F64)), dim=-1)
    v = face_viewer(n, tangent)  # grazing
    n, v = n.to(dtype), v.to(dtype)
    axes = torch.tensor([[0, 1.0, 0], [0, -1.0, 0], [0, 0, 1.0], [0, 0, -1.0], [1.0, 1e-7, 0]], dtype=dtype)
    radius = torch.tensor([[1e-6], [1e-3], [math.radians(1.5)], [0.5], [1.2]], dtype=dtype)
    for r in (0.01, 1.0):
        for brdf, m in ((TANGO, material(pts, 0.5, 0.5, r)), (GLTF, material(pts, base=0.5, metallic=0.5, roughness=r))):
            m = SimpleNamespace(**{k: None if x is None else x.to(dtype).requires_grad_() for k, x in vars(m).items()})
            raw = axes.clone().requires_grad_()
            rad = radius.clone().requires_grad_()
            e = torch.ones(5, 3, dtype=dtype, requires_grad=True)
            out = SunLight(torch.nn.functional.normalize(raw, dim=-1), e, rad, 8).shade(brdf, n, v, m, None, None)
            assert bool(torch.isfinite(out.rgb).all())
            out.rgb.sum().backward()
            for x in (raw, rad, e, m.albedo, m.roughness, m.specular):
                assert bool(torch.isfinite(x.grad).all())
    below = SunLight(torch.tensor([[0, -1.0, 0]], dtype=F64), torch.ones(1, 3, dtype=F64), torch.tensor([[0.01]], dtype=F64), 8)
    up = torch.tensor([[0, 1.0, 0]], dtype=F64)
    assert float(below.shade(TANGO, up, up, material(1, 0.5, 0.5, 0.3), None, None).rgb.abs().max()) == 0.0


def test_bfloat16_autocast_leaves_the_sun_in_float32():
    n = torch.tensor([[0.0, 1.0, 0.0]]).expand(4, 3)
    v = torch.nn.functional.normalize(torch.tensor([[0.3, 1.0, 0.1]]).expand(4, 3), dim=-1)
    m = SimpleNamespace(
        albedo=torch.full((4, 3), 0.5),
        specular=torch.full((4, 3), 0.5),
        roughness=torch.full((4, 1), 0.05),
        base=None,
        metallic=None,
    )
    sun = SunLight(
        torch.nn.functional.normalize(torch.tensor([[-0.3, 1.0, -0.1]]), dim=-1), torch.ones(1, 3), torch.tensor([[0.02]]), 8
    )
    plain = sun.shade(TANGO, n, v, m, None, None)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        auto = sun.shade(TANGO, n, v, m, None, None)
    assert auto.rgb.dtype == torch.float32
    torch.testing.assert_close(auto.rgb, plain.rgb)
