"""SG algebra and shading against brute force, gradients by gradcheck, and the extremes of every
input range.

Every brute-force reference (seeded Monte Carlo with 2^18 samples, or quadrature) is written here
from the textbook formulas that the renderer's docstrings cite, never through ``stages.render``,
so that a wrong constant in the renderer cannot cancel out of a comparison:

- an SG is ``mu exp(lam (v . xi - 1))`` and its sphere integral ``2 pi mu (1 - exp(-2 lam)) / lam``;
- the normal distribution is PhySG's SG ``D(h) = exp(2 / alpha^2 (h . n - 1)) / (pi alpha^2)``,
  ``alpha = r^2``;
- Fresnel is Schlick's ``F0 + (1 - F0) (1 - v . h)^5``;
- shadowing is Smith-Schlick's ``G1(x) = x / (x (1 - k) + k)`` with ``k = (r + 1)^2 / 8`` (Karis
  2013, the convention of PhySG's code; TANGO's text names none);
- the clamped cosine is ``max(n . l, 0)``, and the specular BRDF ``D F G1(n.l) G1(n.v) / (4 (n.l) (n.v))``.

Each comparison is a plain ``check_*(impl)`` function that returns its worst error in units of its
tolerance (so it passes at <= 1). The tolerance is the bound the renderer's docstring states plus
``Z_TOL`` Monte Carlo standard errors, or, for exact closed forms, the standard errors alone. The
mutation tests at the end patch a deliberately wrong constant into the NDF, Fresnel, shadowing,
the warp and the clamped-cosine fit and require the checks to fail.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import numpy as np
import pytest
import torch
from scipy import integrate
from test_specular_albedo import monte_carlo_albedo

from stages.model.networks import Material
from stages.render import fitted_lobe as fitted_module
from stages.render import isotropic_lobe as isotropic_module
from stages.render import sg as sg_module
from stages.render import shading as shading_module
from stages.render import split_sum as split_sum_module
from stages.render.brdf import TANGO
from stages.render.brdf import tango as tango_module
from stages.render.isotropic_lobe import ndf_sg, specular_radiance, specular_radiance_reference
from stages.render.sg import (
    one_minus_exp_neg2x_over_x,
    sg_eval,
    sg_hemisphere_integral,
    sg_inner_product,
    sg_integral,
    sg_product,
    warp_ndf_to_light,
)
from stages.render.shading import SGLight, diffuse_radiance, diffuse_radiance_reference, face_viewer

F64 = torch.float64
N_MC = 1 << 18
# A closed form and a Monte Carlo estimate with standard error `se` agree when they differ by
# less than Z_TOL * se: a false failure has probability ~6e-7 per comparison.
Z_TOL = 5.0
# the relative rounding allowance of the checks of exact float64 formulas
EXACT = 1e-12


def shade(normal, view, albedo, light, specular=None, roughness=None):
    """TANGO's BRDF under ``light`` by its closed form (its ``shade``), from the material's terms."""
    return TANGO.shade(normal, view, Material(albedo, specular, roughness), light, "isotropic")


def split_sum(normal, view, specular, roughness, light):
    """The split-sum specular of TANGO's BRDF."""
    return split_sum_module.specular_radiance_split_sum(normal, view, specular, roughness, light, TANGO)


def fitted(normal, view, specular, roughness, light):
    """The fitted specular lobe of TANGO's BRDF."""
    return fitted_module.specular_radiance_fitted(normal, view, specular, roughness, light, TANGO)


def unit(x: torch.Tensor) -> torch.Tensor:
    return x / torch.linalg.vector_norm(x, dim=-1, keepdim=True)


def fibonacci(k: int) -> torch.Tensor:
    i = torch.arange(k, dtype=F64) + 0.5
    phi = torch.acos(1 - 2 * i / k)
    th = math.pi * (1 + 5**0.5) * i
    return torch.stack([torch.cos(th) * torch.sin(phi), torch.sin(th) * torch.sin(phi), torch.cos(phi)], -1)


def make_light(k: int = 32, lam: float = 5.0, seed: int = 0, dtype=F64) -> SGLight:
    g = torch.Generator().manual_seed(seed)
    return SGLight(
        fibonacci(k).to(dtype),
        torch.full((k, 1), lam, dtype=dtype),
        torch.rand(k, 3, generator=g, dtype=F64).to(dtype),
    )


def score(got: torch.Tensor, ref: torch.Tensor, se: torch.Tensor | float, bound: float | torch.Tensor) -> float:
    """``max |got - ref| / (bound |ref| + Z_TOL se)``: the error in units of the tolerance."""
    return ((got - ref).abs() / (bound * ref.abs() + Z_TOL * se)).max().item()


def exact_score(got: torch.Tensor, ref: torch.Tensor) -> float:
    """The error of an exact float64 formula in units of ``EXACT`` relative (plus 1e-300 absolute)."""
    return ((got - ref).abs() / (EXACT * ref.abs() + 1e-300)).max().item()


# ---------------------------------------------------------------------------- textbook formulas
def sg_value(v: torch.Tensor, axis: torch.Tensor, lam: float, mu: torch.Tensor) -> torch.Tensor:
    """One SG ``mu exp(lam (v . xi - 1))`` at ``v (M, 3)``; ``axis (3,)``, ``mu (C,)`` -> ``(M, C)``."""
    return torch.exp(lam * (v @ axis - 1))[:, None] * mu


def radiance(light: SGLight, w: torch.Tensor) -> torch.Tensor:
    """The environment ``L(w) = sum_k mu_k exp(lam_k (w . xi_k - 1))`` at ``w (M, 3)`` -> ``(M, C)``."""
    return torch.exp((w @ light.axis.T - 1) * light.sharpness[:, 0]) @ light.amplitude


def sphere_integral(lam: float, mu: float | torch.Tensor = 1.0):
    """``int_S2 mu exp(lam (v . xi - 1)) dv = 2 pi mu (1 - exp(-2 lam)) / lam``."""
    return 2 * math.pi * mu * -math.expm1(-2 * lam) / lam


def ndf(cos_hn: torch.Tensor, r: float) -> torch.Tensor:
    """PhySG's SG normal distribution ``exp(2 / alpha^2 (h . n - 1)) / (pi alpha^2)``, ``alpha = r^2``."""
    a2 = r**4
    return torch.exp(2 / a2 * (cos_hn - 1)) / (math.pi * a2)


def schlick(f0: torch.Tensor, cos: torch.Tensor) -> torch.Tensor:
    return f0 + (1 - f0) * (1 - cos) ** 5


def smith_g1(cos: torch.Tensor, r: float) -> torch.Tensor:
    k = (r + 1) ** 2 / 8
    return cos / (cos * (1 - k) + k)


def reflect(v: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    return 2 * (v @ n) * n - v


# --------------------------------------------------------------------------------- Monte Carlo
def sphere_samples(n: int = N_MC, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return unit(torch.randn(n, 3, generator=g, dtype=F64))


def mc_sphere(f: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Uniform-sphere MC estimate and standard error of the integral of samples ``f (N, C)``."""
    n = f.shape[0]
    return 4 * math.pi * f.mean(0), 4 * math.pi * f.std(0) / math.sqrt(n)


def mc_weighted(f: torch.Tensor, pdf: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Importance-sampled MC estimate and standard error of the integral of ``f (N, C)``."""
    w = f / pdf[:, None]
    return w.mean(0), w.std(0) / math.sqrt(w.shape[0])


def lobe_pdf(axis: torch.Tensor, lam: float, v: torch.Tensor) -> torch.Tensor:
    """Density of the normalised SG ``exp(lam (v . axis - 1)) / sphere_integral(lam)``."""
    return torch.exp(lam * (v @ axis - 1)) / sphere_integral(lam)


def sample_lobe(axis: torch.Tensor, lam: float, n: int, g: torch.Generator) -> torch.Tensor:
    """Exact samples of :func:`lobe_pdf` (inverse CDF: ``cos = 1 + log(u + (1 - u) exp(-2 lam)) / lam``)."""
    u, phi = torch.rand(n, generator=g, dtype=F64), 2 * math.pi * torch.rand(n, generator=g, dtype=F64)
    c = (1 + torch.log(u + (1 - u) * math.exp(-2 * lam)) / lam).clamp(-1, 1)
    s = torch.sqrt(1 - c * c)
    x = unit(torch.linalg.cross(torch.tensor([0.6, 0.8, 0.0], dtype=F64), axis))
    y = torch.linalg.cross(axis, x)
    return (s * torch.cos(phi))[:, None] * x + (s * torch.sin(phi))[:, None] * y + c[:, None] * axis


def specular_samples(n: torch.Tensor, v: torch.Tensor, r: float, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Defensive importance sampling of light directions for a microfacet lobe: half uniform on the
    sphere, half ``l = 2 (v . h) h - v`` with ``h`` drawn from the NDF. Returns ``l (N_MC, 3)`` and
    the mixture's density ``1/2 / (4 pi) + 1/2 (p(h) + p(-h)) / (4 |h . v|)``, ``h = (l + v) / |l + v|``
    (``d omega_l = 4 |h . v| d omega_h``, and ``h`` and ``-h`` reflect ``v`` to the same ``l``)."""
    g = torch.Generator().manual_seed(seed)
    lam = 2 / r**4
    h = sample_lobe(n, lam, N_MC // 2, g)
    light_dirs = torch.cat([unit(torch.randn(N_MC // 2, 3, generator=g, dtype=F64)), 2 * (h @ v)[:, None] * h - v])
    h = unit(light_dirs + v)
    p_l = (lobe_pdf(n, lam, h) + lobe_pdf(n, lam, -h)) / (4 * (h @ v).abs())
    return light_dirs, 0.5 / (4 * math.pi) + 0.5 * p_l


def test_importance_sampling_is_unbiased():
    """The specular sampler's density integrates to one and its estimates match plain sampling."""
    n = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    light = make_light(32, 5.0)
    for r, cos_nv in ((0.3, 0.5), (1.0, 0.3)):
        v = torch.tensor([math.sqrt(1 - cos_nv**2), 0.0, cos_nv], dtype=F64)
        dirs, pdf = specular_samples(n, v, r, seed=11)
        one, se = mc_weighted(torch.ones(len(dirs), 1, dtype=F64), pdf)
        assert abs(one.item() - 4 * math.pi) <= Z_TOL * se.item()
        f = lambda w: radiance(light, w) * (w @ n).clamp(min=0)[:, None]  # noqa: E731
        got, se1 = mc_weighted(f(dirs), pdf)
        ref, se2 = mc_sphere(f(sphere_samples(seed=12)))
        assert torch.all((got - ref).abs() <= Z_TOL * torch.sqrt(se1**2 + se2**2))


# ---------------------------------------------------------------------------- exact identities
def test_eval_is_the_textbook_sg():
    v = sphere_samples(1000, seed=1)
    axis = unit(torch.tensor([0.3, -0.5, 0.8], dtype=F64))
    for lam in (0.0, 1e-4, 1.0, 100.0):  # the exponent's rounding grows as lam: 1e-12 relative holds to lam ~ 1e3
        mu = torch.tensor([1.0, 2.0], dtype=F64)
        got = sg_eval(v, axis, torch.tensor([lam], dtype=F64), mu)
        assert exact_score(got, sg_value(v, axis, lam, mu)) <= 1


def test_product_evaluates_to_product_of_evaluations():
    g = torch.Generator().manual_seed(1)
    v = unit(torch.randn(1000, 3, generator=g, dtype=F64))
    a1, a2 = (
        unit(torch.randn(1000, 3, generator=g, dtype=F64)),
        unit(torch.randn(1000, 3, generator=g, dtype=F64)),
    )
    l1 = 10 ** (torch.rand(1000, 1, generator=g, dtype=F64) * 6 - 3)
    l2 = 10 ** (torch.rand(1000, 1, generator=g, dtype=F64) * 6 - 3)
    m1, m2 = torch.rand(1000, 3, generator=g, dtype=F64), torch.rand(1000, 1, generator=g, dtype=F64)
    pa, pl, pm = sg_product(a1, l1, m1, a2, l2, m2)

    def value(axis, lam, mu):  # mu exp(lam (v . xi - 1)), row by row
        return mu * torch.exp(lam * ((v * axis).sum(-1, keepdim=True) - 1))

    torch.testing.assert_close(value(pa, pl, pm), value(a1, l1, m1) * value(a2, l2, m2), rtol=1e-10, atol=1e-300)


def test_product_of_opposite_equal_lobes_is_constant():
    a = torch.tensor([[0.0, 0.0, 1.0]], dtype=F64)
    lam = torch.tensor([[3.0]], dtype=F64)
    mu = torch.tensor([[2.0]], dtype=F64)
    pa, pl, pm = sg_product(a, lam, mu, -a, lam, mu)
    assert pl.item() == 0.0 and torch.all(pa == 0)
    # exp(3 (v.a - 1)) exp(3 (-v.a - 1)) = exp(-6) for every v
    torch.testing.assert_close(pm, torch.tensor([[4 * math.exp(-6)]], dtype=F64), rtol=1e-14, atol=0)
    # the integral of that constant is 4 pi mu: the lam -> 0 limit
    torch.testing.assert_close(sg_integral(pl, pm), 4 * math.pi * pm)


def test_fused_product_of_opposite_lobes_survives_cosines_past_minus_one():
    """A matrix product with reduced-precision inputs (TF32, bfloat16) returns cosines between unit
    axes just outside [-1, 1]; at opposite lobes of equal sharpness the product's sharpness
    ``sqrt((l1 - l2)^2 + 2 l1 l2 (1 + c))`` then took the root of a negative number (NaN at step 40
    of a TF32 run on an H100). A cosine past -1 is the cosine -1: sharpness 0, amplitude exp(-2 l)."""
    lam = torch.tensor([5.0], dtype=torch.float32)
    for c in (-1.0 - 1e-6, -1.0 - 1e-3, 1.0 + 1e-6):
        cos = torch.tensor([c], dtype=torch.float32)
        pl, log_amp = shading_module.product_terms(lam, lam, cos)
        clamped = max(-1.0, min(1.0, c))
        assert torch.isfinite(pl).all() and torch.isfinite(log_amp).all(), c
        assert pl.item() == pytest.approx(math.sqrt(2 * 25.0 * (1.0 + clamped)), abs=1e-6)
        assert log_amp.item() == pytest.approx(-2 * 25.0 * (1.0 - clamped) / (pl.item() + 10.0), rel=1e-6)


# ------------------------------------------------------------------------------------ integral
INTEGRAL_SHARPNESS = (1e-4, 1e-2, 0.3, 1.0, 3.0, 10.0, 30.0)


@functools.cache
def integral_mc() -> tuple[torch.Tensor, torch.Tensor]:
    """MC of ``int (1, 2) exp(lam (v . xi - 1)) dv`` for each of INTEGRAL_SHARPNESS -> ``(L, 2)`` each."""
    v = sphere_samples(seed=2)
    axis = unit(torch.tensor([0.3, -0.5, 0.8], dtype=F64))
    mc = [mc_sphere(sg_value(v, axis, lam, torch.tensor([1.0, 2.0], dtype=F64))) for lam in INTEGRAL_SHARPNESS]
    return torch.stack([m for m, _ in mc]), torch.stack([s for _, s in mc])


def check_integral(impl: Callable | None = None) -> float:
    """The sphere integral (exact) against Monte Carlo: within Z_TOL standard errors."""
    impl = impl or sg_module.sg_integral
    ref, se = integral_mc()
    lam = torch.tensor(INTEGRAL_SHARPNESS, dtype=F64)[:, None]
    got = impl(lam, torch.tensor([[1.0, 2.0]], dtype=F64).expand(len(lam), 2))
    return score(got, ref, se + 1e-15, 0.0)


def test_integral_against_monte_carlo():
    assert check_integral() <= 1


@pytest.mark.parametrize("lam", [1e-4, 1.0, 1e2, 1e3, 1e4, 1e6])
def test_integral_against_quadrature(lam):
    # in the lobe's frame the integrand depends on u = cos(theta) only: 2 pi int exp(lam (u-1)) du
    pts = [min(2.0, k / lam) for k in (1, 10, 50)]
    ref, _ = integrate.quad(lambda w: 2 * math.pi * math.exp(-lam * w), 0, 2, points=pts, limit=200, epsrel=1e-12)
    for dtype, rtol in ((F64, 1e-10), (torch.float32, 2e-6)):
        got = sg_integral(torch.tensor([[lam]], dtype=dtype), torch.ones(1, 1, dtype=dtype)).item()
        assert got == pytest.approx(ref, rel=rtol)


def test_stable_ratio_matches_expm1():
    """Exact to rounding: float64 within 2e-13 (the series' truncation error is below 2 x^4 / 15 <
    1.4e-13 relative under x = 1e-3), float32 within 3e-7 (about 2.5 ulp)."""
    x = torch.logspace(-8, 8, 400, dtype=F64)
    ref = -torch.expm1(-2 * x) / x
    torch.testing.assert_close(one_minus_exp_neg2x_over_x(x), ref, rtol=2e-13, atol=0)
    got = one_minus_exp_neg2x_over_x(x.float()).double()
    torch.testing.assert_close(got, ref, rtol=3e-7, atol=0)
    # and its derivative, where the naive quotient rule cancels catastrophically
    xf = x.float().requires_grad_()
    one_minus_exp_neg2x_over_x(xf).sum().backward()
    dref = (2 * torch.exp(-2 * x) * x + torch.expm1(-2 * x)) / x**2
    small = x < 1e-3
    dref[small] = (-2 + 8 / 3 * x - 2 * x**2)[small]
    torch.testing.assert_close(xf.grad.double(), dref, rtol=1e-4, atol=1e-12)


INNER_PRODUCT_SHARPNESS = ((1e-4, 0.5), (1.0, 1.0), (3.0, 8.0), (20.0, 0.01))
INNER_A1 = unit(torch.tensor([0.2, 0.1, 1.0], dtype=F64))
INNER_A2 = unit(torch.tensor([-0.4, 0.9, 0.3], dtype=F64))
INNER_MU1, INNER_MU2 = torch.tensor([1.5], dtype=F64), torch.tensor([0.7, 1.0, 2.0], dtype=F64)


@functools.cache
def inner_product_mc() -> tuple[torch.Tensor, torch.Tensor]:
    v = sphere_samples(seed=3)
    mc = [
        mc_sphere(sg_value(v, INNER_A1, l1, INNER_MU1) * sg_value(v, INNER_A2, l2, INNER_MU2))
        for l1, l2 in INNER_PRODUCT_SHARPNESS
    ]
    return torch.stack([m for m, _ in mc]), torch.stack([s for _, s in mc])


def check_inner_product(impl: Callable | None = None) -> float:
    """The inner product of two SGs (exact) against Monte Carlo: within Z_TOL standard errors."""
    impl = impl or sg_module.sg_inner_product
    ref, se = inner_product_mc()
    l1, l2 = (torch.tensor(x, dtype=F64)[:, None] for x in zip(*INNER_PRODUCT_SHARPNESS, strict=True))
    k = len(l1)
    got = impl(INNER_A1.expand(k, 3), l1, INNER_MU1.expand(k, 1), INNER_A2.expand(k, 3), l2, INNER_MU2.expand(k, 3))
    return score(got, ref, se, 0.0)


def test_inner_product_against_monte_carlo():
    assert check_inner_product() <= 1


# --------------------------------------------------------------------------- hemisphere integral
def hemisphere_quadrature(lam: float, c: float) -> float:
    """int_{v.n >= 0} exp(lam (v.xi - 1)) dv with xi.n = c, as a 1D integral over u = v.xi."""
    s = math.sqrt(max(1 - c * c, 0.0))

    def f(w):
        u = 1 - w
        su = math.sqrt(max(1 - u * u, 0.0))
        if s * su == 0:
            arc = 2 * math.pi if u * c >= 0 else 0.0
        else:
            arc = 2 * math.acos(min(max(-u * c / (su * s), -1.0), 1.0))
        return math.exp(-lam * w) * arc

    pts = [min(2.0, k / lam) for k in (1, 5, 20)]
    val, _ = integrate.quad(f, 0, 2, points=pts, limit=500, epsrel=1e-9)
    return val


HEMISPHERE_SHARPNESS = tuple(np.logspace(-4, 4, 17).tolist())
HEMISPHERE_COSINES = tuple(np.linspace(-1, 1, 11).tolist())
#: sg_hemisphere_integral's docstring: within 1.5% of the full-sphere integral (measured 1.1%)
HEMISPHERE_BOUND = 0.015


@functools.cache
def hemisphere_table() -> torch.Tensor:
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", integrate.IntegrationWarning)
        rows = [[hemisphere_quadrature(lam, c) for c in HEMISPHERE_COSINES] for lam in HEMISPHERE_SHARPNESS]
    return torch.tensor(rows, dtype=F64)


def check_hemisphere_integral(impl: Callable | None = None) -> float:
    """The hemisphere integral's approximation against quadrature: error / (bound x full-sphere integral)."""
    impl = impl or sg_module.sg_hemisphere_integral
    lam = torch.tensor(HEMISPHERE_SHARPNESS, dtype=F64)[:, None].expand(-1, len(HEMISPHERE_COSINES))
    c = torch.tensor(HEMISPHERE_COSINES, dtype=F64)[None].expand(len(HEMISPHERE_SHARPNESS), -1)
    got = impl(lam.reshape(-1, 1), c.reshape(-1, 1)).reshape(lam.shape)
    full = torch.tensor([sphere_integral(x) for x in HEMISPHERE_SHARPNESS], dtype=F64)[:, None]
    return ((got - hemisphere_table()).abs() / (HEMISPHERE_BOUND * full)).max().item()


def test_hemisphere_integral_within_stated_bound():
    assert check_hemisphere_integral() <= 1


@pytest.mark.parametrize("lam", [1e-4, 0.1, 1.0, 10.0, 1e4])
def test_hemisphere_integral_exact_cases(lam):
    lt = torch.tensor([[lam]], dtype=F64)
    upper = 2 * math.pi * -math.expm1(-lam) / lam
    h = lambda c: sg_hemisphere_integral(lt, torch.tensor([[c]], dtype=F64)).item()  # noqa: E731
    assert h(0.0) == pytest.approx(sphere_integral(lam) / 2, rel=1e-12)
    assert h(1.0) == pytest.approx(upper, rel=1e-12)
    assert h(-1.0) == pytest.approx(math.exp(-lam) * upper, rel=1e-12, abs=1e-300)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_hemisphere_integral_finite_over_stated_range(dtype):
    """The docstring's range: finite values and gradients for sharpness 1e-6 to 1e15 in float32
    (where sqrt(lam) lam^2 overflows at ~2e15) and to 1e18 in float64."""
    top = 15 if dtype == torch.float32 else 18
    k = 2 * (top + 6) + 1
    lam = torch.logspace(-6, top, k, dtype=dtype)[:, None].expand(-1, 5).reshape(-1, 1).clone().requires_grad_()
    c = torch.tensor([-1.0, -0.3, 0.0, 0.4, 1.0], dtype=dtype).repeat(k)[:, None].requires_grad_()
    out = sg_hemisphere_integral(lam, c)
    assert torch.isfinite(out).all() and (out >= 0).all()
    out.sum().backward()
    assert torch.isfinite(lam.grad).all() and torch.isfinite(c.grad).all()


@pytest.mark.parametrize("lam", [1e-2, 1.0, 100.0, 1e5])
def test_hemisphere_integral_gradient_on_the_horizon(lam):
    """A lobe exactly on the horizon (``c = 0``: an axis-aligned normal and a light lobe on the
    equator) has the derivative of the smooth function there, the central difference's: the two
    branches' clamps once both passed the gradient at 0 and doubled the step's part (found by
    ``benchmarks/render/precision.py``: the diffuse term's gradient to the normal 290 times too large at
    sharpness 100)."""
    lt = torch.tensor([[lam]], dtype=F64)
    c = torch.zeros(1, 1, dtype=F64, requires_grad=True)
    sg_hemisphere_integral(lt, c).sum().backward()
    h = 1e-6 / math.sqrt(lam)
    step = lambda x: sg_hemisphere_integral(lt, torch.tensor([[x]], dtype=F64)).item()  # noqa: E731
    assert c.grad.item() == pytest.approx((step(h) - step(-h)) / (2 * h), rel=1e-5)


#: sg.py's COS_* docstring: within 0.008 of max(v . n, 0) on the upper hemisphere (measured 0.0077)
COSINE_FIT_BOUND = 0.008


def renderer_cosine_fit(normal):
    """The renderer's SG fit of the clamped cosine, ``COS_MU exp(COS_LAMBDA (v . n - 1)) - COS_OFFSET``,
    as (axis, sharpness, amplitude, offset); the constants are read when called, so mutations show."""
    lam = torch.full_like(normal[..., :1], sg_module.COS_LAMBDA)
    mu = torch.full_like(normal[..., :1], sg_module.COS_MU)
    return normal, lam, mu, sg_module.COS_OFFSET


def check_cosine_fit(impl: Callable | None = None) -> float:
    """The clamped cosine's SG fit against ``max(v . n, 0)`` on the upper hemisphere: error / bound."""
    impl = impl or renderer_cosine_fit
    n = unit(torch.tensor([[0.2, -0.3, 0.9]], dtype=F64))
    axis, lam, mu, offset = impl(n)
    theta = torch.linspace(0, math.pi / 2, 2001, dtype=F64)
    t = unit(torch.linalg.cross(n[0], torch.tensor([1.0, 0.0, 0.0], dtype=F64)))
    v = torch.cos(theta)[:, None] * n[0] + torch.sin(theta)[:, None] * t
    fit = sg_value(v, axis[0], lam.item(), mu[0]) - offset
    return ((fit[:, 0] - (v @ n[0]).clamp(min=0)).abs().max() / COSINE_FIT_BOUND).item()


def test_clamped_cosine_fit_error():
    assert check_cosine_fit() <= 1


# ------------------------------------------------------------------ BRDF factors and the warp
NDF_ROUGHNESS = (0.01, 0.05, 0.1, 0.3, 0.5, 0.8, 1.0)


def check_ndf(impl: Callable | None = None) -> float:
    """A microfacet NDF is normalised, ``int D(h) (h . n) dh = 1`` (Walter et al. 2007, eq. 4); the SG
    NDF ``exp(lam (h . n - 1)) / (pi alpha^2)``, ``lam = 2 / alpha^2``, to within ``alpha^2 / 2``:
    ``int = 2 pi / (pi alpha^2) int_0^1 exp(lam (c - 1)) c dc = 1 - (1 - exp(-lam)) / lam``. Adaptive
    quadrature of the implementation's lobe against that value, in units of 1e-9 (the quadrature's
    tolerance)."""
    impl = impl or isotropic_module.ndf_sg
    worst = 0.0
    for r in NDF_ROUGHNESS:
        lam, mu = (x.item() for x in impl(torch.tensor([[r]], dtype=F64)))
        # 2 pi mu int_0^1 exp(-lam w) (1 - w) dw, w = 1 - h.n
        pts = [min(1.0, k / lam) for k in (1, 10, 50)]
        val, _ = integrate.quad(lambda w: math.exp(-lam * w) * (1 - w), 0, 1, points=pts, limit=200, epsrel=1e-13)  # noqa: B023
        a2 = r**4
        expected = 1 + math.expm1(-2 / a2) * a2 / 2  # 1 - (1 - exp(-lam)) / lam, lam = 2 / alpha^2
        worst = max(worst, abs(2 * math.pi * mu * val - expected) / 1e-9)
    return worst


def test_ndf_is_normalised():
    assert check_ndf() <= 1


def check_fresnel(impl: Callable | None = None) -> float:
    """Schlick's Fresnel (exact) against the textbook formula, in units of ``EXACT``."""
    impl = impl or isotropic_module.fresnel_schlick
    f0 = torch.linspace(0, 1, 11, dtype=F64)[:, None].expand(-1, 3).repeat(101, 1)
    cos = torch.linspace(0, 1, 101, dtype=F64).repeat_interleave(11)[:, None]
    return exact_score(impl(f0, cos), schlick(f0, cos))


def test_fresnel_is_schlick():
    assert check_fresnel() <= 1


def check_smith(impl: Callable | None = None) -> float:
    """``G1(n.l) G1(n.v) / (4 (n.l) (n.v))`` (exact) against the textbook formula, in units of ``EXACT``."""
    impl = impl or isotropic_module.smith_schlick_over_cosines
    c = torch.linspace(0.01, 1, 34, dtype=F64)
    cl, cv = (x.reshape(-1, 1) for x in torch.meshgrid(c, c, indexing="ij"))
    worst = 0.0
    for r in (0.01, 0.1, 0.3, 0.5, 0.8, 1.0):
        ref = smith_g1(cl, r) * smith_g1(cv, r) / (4 * cl * cv)
        worst = max(worst, exact_score(impl(cl, cv, torch.full_like(cl, r)), ref))
    return worst


def test_smith_is_smith_schlick():
    assert check_smith() <= 1


WARP_CASES = tuple((r, c) for r in (0.1, 0.2, 0.3, 0.5) for c in (1.0, 0.7, 0.5, 0.3))


@functools.cache
def warped_ndf_integral(r: float, cos_nv: float) -> float:
    """``int_S2 D(h(l)) dl`` with ``h(l) = (l + v) / |l + v|``: the NDF seen from the light, by
    Gauss-Legendre (in the angle from the mirror direction) x trapezoid (azimuth) quadrature."""
    n = np.array([0.0, 0.0, 1.0])
    v = np.array([math.sqrt(1 - cos_nv**2), 0.0, cos_nv])
    m = 2 * cos_nv * n - v
    x = np.cross([0.0, 1.0, 0.0], m)
    x /= np.linalg.norm(x)
    y = np.cross(m, x)
    phi = 2 * math.pi * np.arange(256) / 256
    split = min(math.pi, 40 * math.sqrt(2 * cos_nv) * r**2)  # 40 standard deviations of the warped lobe
    total = 0.0
    for lo, hi in ((0.0, split), (split, math.pi)):
        if hi <= lo:
            continue
        t, wt = np.polynomial.legendre.leggauss(600)
        th, wt = lo + (hi - lo) * (t + 1) / 2, wt * (hi - lo) / 2
        dirs = np.sin(th)[:, None, None] * (np.cos(phi)[:, None] * x + np.sin(phi)[:, None] * y) + np.cos(th)[:, None, None] * m
        h = (dirs + v) / np.linalg.norm(dirs + v, axis=-1, keepdims=True)
        d = ndf(torch.from_numpy(h @ n), r).numpy()
        total += float(np.sum(d.sum(1) * np.sin(th) * wt)) * 2 * math.pi / len(phi)
    return total


def check_warp(impl: Callable | None = None) -> float:
    """The warped lobe against the NDF seen from the light: its axis is the mirror direction
    (exact) and its integral matches ``int D(h(l)) dl`` to within ``r^4 = 2 / lam``
    (warp_ndf_to_light's docstring). Worst error in units of those tolerances."""
    impl = impl or isotropic_module.warp_ndf_to_light
    worst = 0.0
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=F64)
    for r, cos_nv in WARP_CASES:
        v = torch.tensor([[math.sqrt(1 - cos_nv**2), 0.0, cos_nv]], dtype=F64)
        lam, mu = torch.tensor([[2 / r**4]], dtype=F64), torch.tensor([[1 / (math.pi * r**4)]], dtype=F64)
        axis, w_lam, w_mu = impl(n, v, lam, mu, torch.tensor([[cos_nv]], dtype=F64))
        worst = max(worst, (axis[0] - reflect(v[0], n[0])).abs().max().item() / EXACT)
        closed = sphere_integral(w_lam.item(), w_mu.item())
        ref = warped_ndf_integral(r, cos_nv)
        worst = max(worst, abs(closed - ref) / (r**4 * ref))
    return worst


def test_warp_axis_and_integral():
    assert check_warp() <= 1


def test_warp_matches_ndf_near_mirror_direction_at_normal_incidence():
    """At normal incidence, D(h(l)) = mu exp(lam (cos(d/2) - 1)) and the warped lobe is
    mu exp(lam / 4 (cos d - 1)); both are mu exp(-lam d^2 / 8) to second order in the angle d."""
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=F64)
    lam = torch.tensor([[200.0]], dtype=F64)
    mu = torch.tensor([[1.0]], dtype=F64)
    axis, wl, wm = warp_ndf_to_light(n, n, lam, mu, torch.ones(1, 1, dtype=F64))
    torch.testing.assert_close(axis, n)
    for d in (0.0, 0.02, 0.05):
        ll = torch.tensor([math.sin(d), 0.0, math.cos(d)], dtype=F64)
        exact = math.exp(lam.item() * (math.cos(d / 2) - 1))  # D(h(l)): h = (l + n) / |l + n| is at d / 2 from n
        warped = sg_value(ll[None], axis[0], wl.item(), wm[0]).item()
        assert warped == pytest.approx(exact, rel=lam.item() * d**4 / 50 + 1e-12)


# ------------------------------------------------------------------------------------- shading
DIFFUSE_SHARPNESS = (0.5, 3.0, 10.0, 30.0)
DIFFUSE_NORMALS = unit(torch.tensor([[0.0, 0.0, 1.0], [0.3, -0.8, 0.1], [0.0, 0.0, -1.0], [0.5, 0.5, 0.5]], dtype=F64))
#: diffuse_radiance_reference's docstring: within 2.5% of brute force (measured 2.2%)
DIFFUSE_BOUND = 0.025


@functools.cache
def diffuse_mc(lam: float) -> tuple[torch.Tensor, torch.Tensor]:
    """MC of ``int L(w) max(w . n, 0) dw`` for each of DIFFUSE_NORMALS -> ``(4, 3)`` each."""
    v = sphere_samples(seed=4)
    rad = radiance(make_light(32, lam), v)
    mc = [mc_sphere(rad * (v @ n).clamp(min=0)[:, None]) for n in DIFFUSE_NORMALS]
    return torch.stack([m for m, _ in mc]), torch.stack([s for _, s in mc])


def check_diffuse(impl: Callable | None = None) -> float:
    """Diffuse radiance with albedo pi (so it is the irradiance) against Monte Carlo."""
    impl = impl or shading_module.diffuse_radiance
    worst = 0.0
    for lam in DIFFUSE_SHARPNESS:
        got = impl(DIFFUSE_NORMALS, torch.full((4, 3), math.pi, dtype=F64), make_light(32, lam))
        worst = max(worst, score(got, *diffuse_mc(lam), DIFFUSE_BOUND))
    return worst


@pytest.mark.parametrize("impl", [diffuse_radiance, diffuse_radiance_reference])
def test_diffuse_against_monte_carlo(impl):
    assert check_diffuse(impl) <= 1


SPEC_ROUGHNESS = (0.1, 0.3, 0.5, 0.8, 1.0)
SPEC_COS_NV = (1.0, 0.7, 0.5, 0.3)
SPEC_CASES = tuple((r, c) for r in SPEC_ROUGHNESS for c in SPEC_COS_NV)
SPEC_F0 = torch.tensor([[0.04, 0.3, 0.9]], dtype=F64)
SPEC_NORMAL = torch.tensor([0.0, 0.0, 1.0], dtype=F64)


def spec_view(cos_nv: float) -> torch.Tensor:
    return torch.tensor([math.sqrt(1 - cos_nv**2), 0.0, cos_nv], dtype=F64)


def specular_model_bound(r: float, cos_nv: float) -> float:
    """specular_radiance_reference's docstring: its closed-form integration of the warped lobe is
    within 0.5% + 0.01 / (n . v) of brute force (the cosine fit's error, 0.008, relative to n . l ~ n . v)."""
    return 0.005 + 0.01 / cos_nv


def specular_brdf_bound(r: float, cos_nv: float) -> torch.Tensor:
    """specular_radiance_reference's docstring, for n . v >= 0.3 and F0 = SPEC_F0 = (0.04, 0.3, 0.9):
    within 3% of the microfacet BRDF for roughness <= 0.3 and F0 >= 0.3 (8% at F0 = 0.04), 30% for
    roughness <= 1 and F0 >= 0.3, and a factor 3 (200%) at F0 = 0.04."""
    return torch.tensor([0.08, 0.03, 0.03] if r <= 0.3 else [2.0, 0.3, 0.3], dtype=F64)


@functools.cache
def specular_mc(r: float, cos_nv: float) -> dict[str, tuple[torch.Tensor, torch.Tensor]]:
    """Brute-force specular radiance for the light make_light(32, 5), normal +z, F0 = SPEC_F0:
    ``model`` integrates what the renderer integrates in closed form (the NDF warped to the mirror
    direction [Wang09], times Fresnel and shadowing at the mirror direction, times max(n . l, 0)),
    ``brdf`` the microfacet BRDF itself."""
    n, v = SPEC_NORMAL, spec_view(cos_nv)
    dirs, pdf = specular_samples(n, v, r, seed=5)
    light = radiance(make_light(32, 5.0), dirs)
    cos_nl = (dirs @ n).clamp(min=0)
    lam, mu = 2 / r**4, torch.tensor([1 / (math.pi * r**4)], dtype=F64)
    warped = sg_value(dirs, reflect(v, n), lam / (4 * cos_nv), mu)
    m = schlick(SPEC_F0, cos_nv) * smith_g1(cos_nv, r) ** 2 / (4 * cos_nv**2)
    h = unit(dirs + v)
    g = (smith_g1(cos_nl, r) * smith_g1(cos_nv, r) / (4 * cos_nv))[:, None]  # (n.l) cancels the BRDF's 1 / (n.l)
    brdf = ndf(h @ n, r)[:, None] * schlick(SPEC_F0, (h @ v)[:, None]) * g
    return {
        "model": mc_weighted(light * warped * m * cos_nl[:, None], pdf),
        "brdf": mc_weighted(light * brdf * (cos_nl > 0)[:, None], pdf),
    }


def specular_scores(kind: str, impl: Callable | None = None) -> dict[tuple[float, float], float]:
    """Per case, the error of the specular radiance against ``specular_mc(...)[kind]`` in units of its tolerance."""
    impl = impl or isotropic_module.specular_radiance
    bound = {"model": specular_model_bound, "brdf": specular_brdf_bound}[kind]
    light = make_light(32, 5.0)
    out = {}
    for r, cos_nv in SPEC_CASES:
        got = impl(SPEC_NORMAL[None], spec_view(cos_nv)[None], SPEC_F0, torch.tensor([[r]], dtype=F64), light)[0]
        out[r, cos_nv] = score(got, *specular_mc(r, cos_nv)[kind], bound(r, cos_nv))
    return out


def check_specular_model(impl: Callable | None = None) -> float:
    return max(specular_scores("model", impl).values())


def check_specular_brdf(impl: Callable | None = None) -> float:
    return max(specular_scores("brdf", impl).values())


@pytest.mark.parametrize("impl", [specular_radiance, specular_radiance_reference])
def test_specular_against_monte_carlo_of_the_warped_lobe(impl):
    scores = specular_scores("model", impl)
    assert max(scores.values()) <= 1, scores


@pytest.mark.parametrize("impl", [specular_radiance, specular_radiance_reference])
def test_specular_against_monte_carlo_of_the_microfacet_brdf(impl):
    scores = specular_scores("brdf", impl)
    assert max(scores.values()) <= 1, scores


SPLIT_ROUGHNESS = (0.05, 0.1, 0.3, 0.5, 0.8, 1.0)
SPLIT_COS_NV = (1.0, 0.5, 0.3, 0.1, 0.05)


def brdf_scores(model, tolerance) -> dict:
    """``model``'s specular under the 32-lobe test light against Monte Carlo of the microfacet
    BRDF, per (roughness, n.v), as :func:`score` with ``tolerance(n.v)`` (<= 1: within it)."""
    light = make_light(32, 5.0)
    scores = {}
    for r in SPLIT_ROUGHNESS:
        for cos_nv in SPLIT_COS_NV:
            got = model(SPEC_NORMAL[None], spec_view(cos_nv)[None], SPEC_F0, torch.tensor([[r]], dtype=F64), light)[0]
            scores[r, cos_nv] = score(got, *specular_mc(r, cos_nv)["brdf"], tolerance(cos_nv))
    return scores


def test_split_sum_specular_against_monte_carlo_of_the_microfacet_brdf():
    """The split-sum specular (exact energy, the isotropic lobe's shape) against the BRDF itself,
    roughness 0.05 to 1 and n.v down to 0.05, F0 0.04 / 0.3 / 0.9: within 3% for n.v >= 0.3 and 17%
    below (measured 2026-11-22: 1.9% and 15.8%; the isotropic closed form errs by up to 91% there)."""
    scores = brdf_scores(split_sum, lambda cos_nv: 0.03 if cos_nv >= 0.3 else 0.17)
    assert max(scores.values()) <= 1, scores


def test_fitted_specular_against_monte_carlo_of_the_microfacet_brdf():
    """The fitted lobe (exact energy, a vMF with the BRDF lobe's first moment, corrected by the BRDF
    at each light lobe) against the BRDF itself, roughness 0.05 to 1 and n.v down to 0.05, F0 0.04 /
    0.3 / 0.9: within 5% everywhere (the issue's target; measured 2026-11-22 against quadrature: 4.9%)."""
    scores = brdf_scores(fitted, lambda cos_nv: 0.05)
    assert max(scores.values()) <= 1, scores


def textbook_brdf_times_cosine(n, v, l_dir, f0, r):
    """``f_r(l, v) (n . l)`` of TANGO's BRDF from its definition: ``D F G / (4 (n.l)(n.v)) (n.l)`` with
    ``D = exp(2 / r^4 (h.n - 1)) / (pi r^4)``, Schlick's ``F`` at ``v.h``, Smith-Schlick ``G1(x) = x /
    (x (1 - k) + k)``, ``k = (r + 1)^2 / 8``; ``(C,)`` for ``f0 (C,)``, 0 below the horizon."""
    h = unit(l_dir + v)
    nl, nv = float(l_dir @ n), float(v @ n)
    if nl <= 0:
        return torch.zeros_like(f0)
    k = (r + 1) ** 2 / 8
    g = (nl / (nl * (1 - k) + k)) * (nv / (nv * (1 - k) + k))
    fres = f0 + (1 - f0) * (1 - float(h @ v)) ** 5
    return ndf(h @ n, r) * fres * g / (4 * nl * nv) * nl


@pytest.mark.parametrize("r", [0.5, 1.0])
@pytest.mark.parametrize("cos_nv", [1.0, 0.5, 0.1])
def test_fitted_specular_limits(r, cos_nv):
    """Exact in both limits of the light's width: a light lobe far sharper than the BRDF lobe
    (sharpness 1e6) gives the BRDF at its axis times the lobe's solid angle ``2 pi / nu``, and a
    uniform light (sharpness 1e-6) gives the directional albedo (Monte Carlo of the textbook BRDF)."""
    n, v = SPEC_NORMAL, spec_view(cos_nv)
    f0 = SPEC_F0[0]
    for xi in (unit(torch.tensor([-0.4, 0.2, 0.8], dtype=F64)), unit(torch.tensor([0.3, -0.6, 0.5], dtype=F64))):
        nu = 1e6
        sharp = SGLight(xi[None], torch.tensor([[nu]], dtype=F64), torch.ones(1, 3, dtype=F64))
        got = fitted(n[None], v[None], f0[None], torch.tensor([[r]], dtype=F64), sharp)[0]
        want = textbook_brdf_times_cosine(n, v, xi, f0, r) * 2 * math.pi / nu
        torch.testing.assert_close(got, want, rtol=1e-3, atol=0)
    uniform = SGLight(n[None], torch.tensor([[1e-6]], dtype=F64), torch.ones(1, 3, dtype=F64))
    got = fitted(n[None], v[None], f0[None], torch.tensor([[r]], dtype=F64), uniform)[0]
    for c, value in enumerate(f0.tolist()):
        mc, se = monte_carlo_albedo(cos_nv, r, value, n=400_000)
        assert abs(float(got[c]) - mc) <= 0.01 * mc + 5 * se, (c, float(got[c]), mc, se)


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
@pytest.mark.parametrize("impl", [split_sum, fitted], ids=["split_sum", "fitted"])
def test_exact_energy_specular_finite_at_the_extremes(dtype, impl):
    """n.v from 5e-4 (face_viewer's floor) to 1, roughness 0.01 and 1, light sharpness 1e-4 to 1e4:
    finite, non-negative values and finite gradients for every input."""
    g = torch.Generator().manual_seed(11)
    cases = [(c, r) for c in (5e-4, 1e-3, 0.05, 1.0) for r in (0.01, 0.3, 1.0)]
    n = torch.tensor([[0.0, 0.0, 1.0]] * len(cases), dtype=dtype)
    view = torch.tensor([[math.sqrt(1 - c * c), 0.0, c] for c, _ in cases], dtype=dtype, requires_grad=True)
    rough = torch.tensor([[r] for _, r in cases], dtype=dtype, requires_grad=True)
    f0 = torch.full((len(cases), 3), 0.04, dtype=dtype, requires_grad=True)
    for lam in (1e-4, 1.0, 1e4):
        light = SGLight(
            unit(torch.randn(8, 3, generator=g, dtype=F64)).to(dtype).requires_grad_(),
            torch.full((8, 1), lam, dtype=dtype, requires_grad=True),
            torch.rand(8, 3, generator=g, dtype=F64).to(dtype).requires_grad_(),
        )
        out = impl(n, view, f0, rough, light)
        assert out.dtype == dtype and torch.isfinite(out).all() and (out >= 0).all(), lam
        out.float().sum().backward()
        for t in (view, rough, f0, light.axis, light.sharpness, light.amplitude):
            assert torch.isfinite(t.grad).all(), lam
            t.grad = None


def test_face_viewer():
    g = torch.Generator().manual_seed(6)
    n = unit(torch.randn(5000, 3, generator=g, dtype=F64))
    v = unit(torch.randn(5000, 3, generator=g, dtype=F64))
    out = face_viewer(n, v, 1e-3)
    cos = (out * v).sum(-1)
    assert (cos >= 0.5e-3 - 1e-15).all()
    keep = (n * v).sum(-1) >= 1e-3
    torch.testing.assert_close(out[keep], n[keep])
    torch.testing.assert_close(torch.linalg.vector_norm(out, dim=-1), torch.ones(5000, dtype=F64))


# ----------------------------------------------------------------------- gradients and extremes
def test_gradcheck_sg_functions():
    g = torch.Generator().manual_seed(7)

    def rand(*shape, lo=0.1, hi=1.0):
        return (lo + (hi - lo) * torch.rand(*shape, generator=g, dtype=F64)).requires_grad_()

    a1 = unit(torch.randn(4, 3, generator=g, dtype=F64)).requires_grad_()
    a2 = unit(torch.randn(4, 3, generator=g, dtype=F64)).requires_grad_()
    for lam_lo, lam_hi in ((1e-4, 1e-3), (0.5, 5.0), (1e3, 1e4)):
        l1, l2 = rand(4, 1, lo=lam_lo, hi=lam_hi), rand(4, 1, lo=lam_lo, hi=lam_hi)
        m1, m2 = rand(4, 3), rand(4, 1)
        assert torch.autograd.gradcheck(lambda *x: sg_product(*x)[2], (a1, l1, m1, a2, l2, m2))
        assert torch.autograd.gradcheck(sg_integral, (l1, m1))
        assert torch.autograd.gradcheck(sg_inner_product, (a1, l1, m1, a2, l2, m2))
        c = (2 * torch.rand(4, 1, generator=g, dtype=F64) - 1).requires_grad_()
        assert torch.autograd.gradcheck(sg_hemisphere_integral, (l1, c))


# face_viewer's kink sits at n.v = 1e-3: check on both sides of it, not on it
@pytest.mark.parametrize("cos_nv", [1.0, 0.5, 1e-2, 2e-3, 3e-4])
@pytest.mark.parametrize("r", [0.01, 0.3, 1.0])
def test_gradcheck_shading(cos_nv, r):
    light = make_light(8, 2.0)
    axis = light.axis.clone().requires_grad_()
    lam = light.sharpness.clone().requires_grad_()
    amp = light.amplitude.clone().requires_grad_()
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=F64, requires_grad=True)
    v = torch.tensor([[math.sqrt(1 - cos_nv**2), 0.0, cos_nv]], dtype=F64)
    albedo = torch.full((1, 3), 0.6, dtype=F64, requires_grad=True)
    spec = torch.full((1, 3), 0.3, dtype=F64, requires_grad=True)
    rough = torch.full((1, 1), r, dtype=F64, requires_grad=True)

    def f(n, albedo, spec, rough, axis, lam, amp):
        nn = face_viewer(unit(n), v, 1e-3)
        return shade(nn, v, albedo, SGLight(axis, lam, amp), spec, rough).rgb

    # fast mode and a step that keeps the extreme sharpness (2 / 0.01^4) numerically resolvable
    eps = 1e-6 if r >= 0.3 else 1e-9
    assert torch.autograd.gradcheck(f, (n, albedo, spec, rough, axis, lam, amp), eps=eps, atol=1e-5, rtol=1e-3)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_extremes_finite_values_and_gradients(dtype):
    """Sharpness 1e-4..1e4, roughness 0.01..1, views from head-on to tangent, normals at +-z."""
    lams = torch.logspace(-4, 4, 9, dtype=dtype)
    k = len(lams)
    axis = fibonacci(k).to(dtype).requires_grad_()
    lam = lams[:, None].clone().requires_grad_()
    amp = torch.ones(k, 3, dtype=dtype, requires_grad=True)
    poles = torch.tensor([[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0]], dtype=dtype)
    cosines = torch.tensor([1.0, 0.5, 1e-2, 1e-4, 0.0, -0.3], dtype=dtype)
    rough = torch.tensor([0.01, 0.05, 0.3, 0.99, 1.0], dtype=dtype)
    rows = []
    for n in poles:
        t = unit(torch.linalg.cross(n, torch.tensor([0.3, 0.7, 0.1], dtype=dtype)))
        for c in cosines:
            s = torch.sqrt(torch.clamp(1 - c * c, min=0))
            for r in rough:
                rows.append((n, c * n + s * t, r))
    normal = torch.stack([r[0] for r in rows]).requires_grad_()
    view = torch.stack([r[1] for r in rows])
    r = torch.stack([r[2] for r in rows])[:, None].requires_grad_()
    albedo = torch.full((len(rows), 3), 0.5, dtype=dtype, requires_grad=True)
    spec = torch.full((len(rows), 3), 0.04, dtype=dtype, requires_grad=True)
    nn = face_viewer(normal, view, 1e-3)
    out = shade(nn, view, albedo, SGLight(axis, lam, amp), spec, r)
    assert torch.isfinite(out.diffuse).all() and torch.isfinite(out.specular).all()
    assert (out.diffuse >= 0).all() and (out.specular >= 0).all()
    out.rgb.sum().backward()
    for x in (normal, r, albedo, spec, axis, lam, amp):
        assert torch.isfinite(x.grad).all()


def test_float32_agrees_with_float64():
    g = torch.Generator().manual_seed(8)
    n = unit(torch.randn(2000, 3, generator=g, dtype=F64))
    v = unit(n + 0.8 * unit(torch.randn(2000, 3, generator=g, dtype=F64)))
    n = face_viewer(n, v)
    albedo = torch.rand(2000, 3, generator=g, dtype=F64)
    spec = torch.rand(2000, 3, generator=g, dtype=F64)
    rough = 0.05 + 0.95 * torch.rand(2000, 1, generator=g, dtype=F64)
    light = make_light(32, 4.0)
    ref = shade(n, v, albedo, light, spec, rough)
    light32 = SGLight(light.axis.float(), light.sharpness.float(), light.amplitude.float())
    got = shade(n.float(), v.float(), albedo.float(), light32, spec.float(), rough.float())
    # the cosine fit subtracts two terms ~30x the result: float32 keeps about 5 digits
    torch.testing.assert_close(got.diffuse.double(), ref.diffuse, rtol=2e-4, atol=2e-5)
    torch.testing.assert_close(got.specular.double(), ref.specular, rtol=2e-3, atol=2e-5)


def test_fused_shading_equals_reference():
    """The fused (N, K)-matrix shading is the reference algebra rearranged: equal to 1e-10."""
    g = torch.Generator().manual_seed(9)
    n = unit(torch.randn(3000, 3, generator=g, dtype=F64))
    v = unit(n + unit(torch.randn(3000, 3, generator=g, dtype=F64)))
    n = face_viewer(n, v)
    k = 24
    light = SGLight(
        unit(torch.randn(k, 3, generator=g, dtype=F64)),
        10 ** (torch.rand(k, 1, generator=g, dtype=F64) * 6 - 3),
        torch.rand(k, 3, generator=g, dtype=F64),
    )
    albedo = torch.rand(3000, 3, generator=g, dtype=F64)
    spec = torch.rand(3000, 3, generator=g, dtype=F64)
    rough = 0.01 + 0.99 * torch.rand(3000, 1, generator=g, dtype=F64)
    torch.testing.assert_close(
        diffuse_radiance(n, albedo, light),
        diffuse_radiance_reference(n, albedo, light),
        rtol=1e-10,
        atol=1e-12,
    )
    torch.testing.assert_close(
        specular_radiance(n, v, spec, rough, light),
        specular_radiance_reference(n, v, spec, rough, light),
        rtol=1e-10,
        atol=1e-12,
    )


# ------------------------------------------------------------------------------------ mutations
# Each mutation is a deliberately wrong constant (or convention) patched into the renderer where
# it is defined; the reference checks above must then fail. A mutation of a module-level name is
# applied to every stages.render module that holds it, as editing its definition would.
CHECKS: dict[str, Callable[[], float]] = {
    "integral": check_integral,
    "inner_product": check_inner_product,
    "hemisphere": check_hemisphere_integral,
    "cosine_fit": check_cosine_fit,
    "ndf": check_ndf,
    "fresnel": check_fresnel,
    "smith": check_smith,
    "warp": check_warp,
    "diffuse": check_diffuse,
    "specular_model": check_specular_model,
    "specular_brdf": check_specular_brdf,
}


def failing_checks() -> set[str]:
    return {name for name, check in CHECKS.items() if check() > 1}


def ndf_amplitude_times(factor: float) -> Callable:
    def mutated(roughness):
        lam, mu = ndf_sg(roughness)
        return lam, mu * factor

    return mutated


def warp_without_cosine(normal, view, ndf_sharpness, ndf_amplitude, cos_nv):
    axis, lam, mu = warp_ndf_to_light(normal, view, ndf_sharpness, ndf_amplitude, cos_nv)
    return axis, lam * cos_nv, mu  # sharpness lam / 4 instead of lam / (4 |h . v|)


# mutation -> (name patched, wrong value, the checks that must catch it); measured to fail exactly these
SPEC = {"specular_model", "specular_brdf"}
MUTATIONS = {
    "ndf sharpness 2/r^4 -> 1/r^4": ("NDF_SHARPNESS", 1.0, {"ndf", *SPEC}),
    "ndf sharpness 2/r^4 -> 2.2/r^4": ("NDF_SHARPNESS", 2.2, {"ndf", *SPEC}),
    "ndf amplitude 1/(pi r^4) -> 1/(3 r^4)": ("ndf_sg", ndf_amplitude_times(math.pi / 3), {"ndf", *SPEC}),
    "fresnel exponent 5 -> 4": ("FRESNEL_POWER", 4, {"fresnel", *SPEC}),
    "fresnel F0 + (1-cos)^5": ("fresnel_schlick", lambda f0, cos: f0 + (1 - cos) ** 5, {"fresnel", *SPEC}),
    "smith k (r+1)^2/8 -> (r+1)^2/4": ("smith_k", lambda r: (r + 1) ** 2 / 4, {"smith", *SPEC}),
    "smith k -> alpha/2 = r^2/2": ("smith_k", lambda r: r**2 / 2, {"smith", *SPEC}),
    "warp 4|h.v| -> 2|h.v|": ("HALF_VECTOR_JACOBIAN", 2.0, {"warp", *SPEC}),
    "warp 4|h.v| -> 4": ("warp_ndf_to_light", warp_without_cosine, {"warp", *SPEC}),
    "cosine 32.7080 -> 32.7800": ("COS_MU", 32.78, {"cosine_fit", "diffuse", *SPEC}),
    "cosine 0.0315 -> 0.0351": ("COS_LAMBDA", 0.0351, {"cosine_fit", "diffuse", *SPEC}),
    "cosine 31.7003 -> 31.7030": ("COS_OFFSET", 31.703, {"cosine_fit"}),
}


#: the stages.render modules of the SG algebra, TANGO's BRDF and its shading
RENDER_MODULES = (sg_module, shading_module, isotropic_module, split_sum_module, fitted_module, tango_module)


def patch_everywhere(monkeypatch: pytest.MonkeyPatch, name: str, value) -> None:
    """Patch ``name`` in every stages.render module that holds it (the shading modules import sg's
    constants, the split sum and the BRDF the isotropic lobe's NDF)."""
    modules = [m for m in RENDER_MODULES if hasattr(m, name)]
    assert modules, name
    for module in modules:
        monkeypatch.setattr(module, name, value)


@pytest.mark.parametrize("mutation", list(MUTATIONS))
def test_mutation_fails_the_checks(monkeypatch, mutation):
    name, value, expected = MUTATIONS[mutation]
    patch_everywhere(monkeypatch, name, value)
    assert expected <= failing_checks()


def test_smith_k_convention_swap_fails_every_case_it_changes(monkeypatch):
    """k = alpha / 2 = r^2 / 2 instead of (r + 1)^2 / 8: the two agree at r = 1, and the renderer
    evaluates shadowing at the mirror direction, where G1(n . v = 1) = 1 for any k; every one of the
    other 12 of the 20 specular cases must fail (they did: 2 of 12 under the former 20% tolerance)."""
    patch_everywhere(monkeypatch, "smith_k", lambda r: r**2 / 2)
    changed = {(r, c) for r, c in SPEC_CASES if r < 1 and c < 1}
    model = specular_scores("model")
    assert {case for case in SPEC_CASES if model[case] > 1} == changed
    brdf = specular_scores("brdf")
    assert {case for case in SPEC_CASES if brdf[case] > 1} <= changed


def test_light_radiance_of_a_sun_in_float32():
    """``SGLight.radiance`` of a lobe of sharpness 1e5 (3e-3 radians wide) in float32 at 0.3 to 3
    widths from its axis, against ``exp(lam (cos t - 1))`` from the angle ``t`` in float64 (the
    textbook form): within 1e-4, and the gradient to the direction within 1e-3. Taken through
    ``w . xi - 1``, float32 resolved the angle to 3.5e-4 radians only: 0.6% off in value and the
    gradient's part across the direction 2% off."""
    g = torch.Generator().manual_seed(4)
    axis = unit(torch.randn(1, 3, generator=g, dtype=F64))
    across = unit(torch.linalg.cross(axis, torch.randn(1, 3, generator=g, dtype=F64), dim=-1))
    angle = torch.linspace(0.3, 3.0, 50, dtype=F64)[:, None] / math.sqrt(1e5)
    w = torch.cos(angle) * axis + torch.sin(angle) * across
    light = SGLight(axis.float(), torch.full((1, 1), 1e5), torch.ones(1, 3))
    wf = w.float().requires_grad_()
    out = light.radiance(wf)[:, 0]
    out.sum().backward()
    want = torch.exp(1e5 * (torch.cos(angle[:, 0]) - 1.0))
    assert torch.allclose(out.double(), want, rtol=1e-4, atol=0)
    # d/dw along the direction of growing angle: -lam sin(t) exp(...) (the textbook derivative)
    away = -torch.sin(angle) * axis + torch.cos(angle) * across
    slope = (wf.grad.double() * away).sum(-1)
    assert torch.allclose(slope, -1e5 * torch.sin(angle[:, 0]) * want, rtol=1e-3, atol=0)


def test_cosine_weighted_hemisphere_without_its_cancellation():
    """The renderer's cosine-weighted hemisphere integral equals its plain form (the fit's two
    terms subtracted as they stand) in float64, and in float32 keeps the value and the derivative
    in the cosine near the horizon for sharp lobes, where the plain form's two terms are a
    thousand times the difference: against float64 on the same inputs, within 5e-3 where the fit
    itself crosses 0 (0.18% and 0.36% measured, value and derivative), where the plain form errs by
    0.8% and 32%."""
    lam = torch.logspace(-4, 6, 41, dtype=F64)
    cos = torch.tensor([-0.999, -0.5, -0.1, -1e-2, -1e-3, -1e-4, 0.0, 1e-4, 1e-3, 1e-2, 0.1, 0.5, 0.999], dtype=F64)
    lt, ct = (x.reshape(-1, 1) for x in torch.meshgrid(lam, cos, indexing="ij"))
    zero = torch.zeros_like(lt)
    plain = shading_module.cosine_weighted_hemisphere_reference(lt, ct, zero)
    fused = shading_module.cosine_weighted_hemisphere(lt, ct, zero)
    # to the plain form's own rounding, that of the terms it subtracts
    terms = sg_module.COS_OFFSET * sg_hemisphere_integral(lt, ct)
    assert ((fused - plain).abs() <= 1e-12 * terms + 1e-290).all()
    # float32 against float64 on the same inputs: sharp lobes (10 to 1e6) near the horizon
    near = (lt >= 10) & (ct.abs() <= 1e-2)
    lam32, cos32 = lt[near].float()[:, None], ct[near].float()[:, None]
    errors = {}
    forms = {"plain": shading_module.cosine_weighted_hemisphere_reference, "fused": shading_module.cosine_weighted_hemisphere}
    for name, fn in forms.items():
        out = {}
        for dtype in (F64, torch.float32):
            c = cos32.to(dtype).requires_grad_()
            value = fn(lam32.to(dtype), c, torch.zeros_like(c))
            (grad,) = torch.autograd.grad(value.sum(), c)
            out[dtype] = (value.double(), grad.double())
        (v64, g64), (v32, g32) = out[F64], out[torch.float32]
        errors[name] = tuple(((a - b).abs() / b.abs()).max().item() for a, b in ((v32, v64), (g32, g64)))
    # the worst are where the fit itself crosses 0 (a thousandth of its two terms)
    assert errors["fused"][0] < 5e-3 and errors["fused"][1] < 5e-3, errors
    assert errors["plain"][0] > 3 * errors["fused"][0] and errors["plain"][1] > 10 * errors["fused"][1], errors


def test_cosine_weighted_hemisphere_of_a_sharp_lobe_at_the_horizon_in_float32():
    """The cosine-weighted integral of a sharp lobe (sharpness 50 to 1e5) within 1e-2 of the horizon,
    in float32 against float64 on the same float32 inputs: value and derivatives within 1e-5. Two
    differences of nearly equal numbers kept float32's rounding of 1: the cosine fit's value at the
    lobe, ``COS_MU e^(log_q) - COS_OFFSET`` (-0.0064 there, from numbers of 32: 4e-5 of the
    integral), and the difference of the two lobes' steps ``p``, each 1 to ``e^-t`` (3e-5 at
    sharpness 50); the split sum divides two such integrals and its gradient erred by 10%."""
    lam0 = torch.tensor([50.0, 500.0, 5e3, 5e4, 1e5])
    c0 = torch.tensor([-1e-3, -1e-4, 0.0, 1e-4, 3e-4, 1e-3, 1e-2])
    lam0, c0 = (x.reshape(-1, 1) for x in torch.meshgrid(lam0, c0, indexing="ij"))
    out = {}
    for dtype in (F64, torch.float32):
        lam, c = lam0.to(dtype).requires_grad_(), c0.to(dtype).requires_grad_()
        value = shading_module.cosine_weighted_hemisphere(lam, c, torch.zeros_like(lam))
        out[dtype] = torch.cat([value, *torch.autograd.grad(value.sum(), (lam, c))], dim=1).double()
    rel = ((out[torch.float32] - out[F64]).abs() / out[F64].abs()).max()
    assert rel <= 1e-5, float(rel)
