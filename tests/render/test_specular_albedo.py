"""The specular albedo table: its quadrature against Monte Carlo of the textbook BRDF, the shipped
file against the code that builds it, its interpolation between nodes, and finite values and
gradients at the extremes (float32 and bfloat16)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from stages.render import specular_albedo as sa
from stages.render.brdf import TANGO


def monte_carlo_albedo(nv: float, r: float, f0: float, n: int = 1_000_000, seed: int = 0) -> tuple[float, float]:
    """``int f_r(l, v) (n.l) dl`` for TANGO's BRDF written out here from its definition,
    ``f_r = D(h) F(v.h) G(l, v) / (4 (n.l)(n.v))`` with ``D(h) = exp(2 / r^4 (h.n - 1)) / (pi r^4)``,
    Schlick's ``F`` and Smith-Schlick ``G1(x) = x / (x (1 - k) + k)``, ``k = (r + 1)^2 / 8``,
    estimated by sampling half vectors from ``D`` (truncated to the sphere) and weighting each
    reflected ``l`` by ``f_r (n.l) / pdf(l)``, ``pdf(l) = pdf(h) / (4 v.h)``. Returns (mean,
    standard error)."""
    rng = np.random.default_rng(seed)
    lam = 2.0 / r**4
    norm = -math.expm1(-2.0 * lam)  # the exponential on u in [0, 2 lam]
    u = -np.log1p(-rng.random(n) * norm)
    phi = 2.0 * math.pi * rng.random(n)
    cos_t = 1.0 - u / lam
    sin_t = np.sqrt(np.clip(1.0 - cos_t**2, 0.0, None))
    h = np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], axis=1)
    pdf_h = lam * np.exp(-u) / (2.0 * math.pi * norm)
    v = np.array([math.sqrt(1.0 - nv * nv), 0.0, nv])
    vh = h @ v
    l_dir = 2.0 * vh[:, None] * h - v
    nl = l_dir[:, 2]
    ok = (vh > 0) & (nl > 0)
    d = np.exp(lam * (h[:, 2] - 1.0)) / (math.pi * r**4)
    fres = f0 + (1.0 - f0) * (1.0 - np.clip(vh, 0, 1)) ** 5
    k = (r + 1.0) ** 2 / 8.0

    def g1(x):
        return x / (x * (1.0 - k) + k)

    with np.errstate(divide="ignore", invalid="ignore"):
        f_r = d * fres * g1(nl) * g1(nv) / (4.0 * nl * nv)
        pdf_l = pdf_h / (4.0 * vh)
        x = np.where(ok, f_r * nl / pdf_l, 0.0)
    return float(x.mean()), float(x.std() / math.sqrt(n))


@pytest.mark.parametrize("nv", [0.05, 0.3, 1.0])
@pytest.mark.parametrize("r", [0.05, 0.3, 1.0])
def test_quadrature_matches_monte_carlo(nv, r):
    terms = sa._entry_terms(np.array([nv]), r, TANGO)
    a, b = terms["a"], terms["b"]
    for f0 in (0.04, 1.0):
        mc, se = monte_carlo_albedo(nv, r, f0)
        quad = f0 * a[0] + b[0]
        assert abs(quad - mc) <= 0.003 * mc + 5 * se, (nv, r, f0, quad, mc, se)


def test_shipped_table_is_what_the_code_builds():
    with np.load(TANGO.table_path) as z:
        # to the last bits, not bitwise: numpy's exp takes an AVX-512 path on the machine that built
        # the table and another on AVX2-only CPUs, an ulp apart (seen on an AMD EPYC, 2026-11-24)
        np.testing.assert_allclose(z["nv"], sa.nv_grid(), rtol=4 * np.finfo(float).eps, atol=0)
        np.testing.assert_allclose(z["roughness"], sa.roughness_grid(), rtol=4 * np.finfo(float).eps, atol=0)
        for key in sa.TABLE_COLUMNS:
            assert z[key].shape == (sa.NV_NODES, sa.R_NODES), key
        for j in (0, sa.R_NODES // 2, sa.R_NODES - 1):
            built = sa._entry_terms(sa.nv_grid(), float(sa.roughness_grid()[j]), TANGO)
            for key in sa.TABLE_COLUMNS:
                # Rebuilt on another CPU (numpy's sums and exp take AVX-512 or AVX2 paths, an ulp apart)
                # the table agrees to its conditioning: at n.v = 1 the tilt theta is 0 exactly and the
                # quadrature leaves ~1e-20 of rounding (atol); kappa = 1 / (1 - R) for R within 1e-8
                # of 1 moves by kappa^2 times R's rounding (seen on an AMD EPYC, 2026-11-24)
                cond = 16 * np.finfo(float).eps * z[key][:, j] ** 2 if key.startswith("kappa") else 0.0
                err = np.abs(z[key][:, j] - built[key])
                assert (err <= 1e-12 * np.abs(built[key]) + 1e-15 + cond).all(), (key, err.max())


def monte_carlo_mean_direction(nv: float, r: float, part: str, n: int = 1_000_000, seed: int = 1) -> tuple[float, float, float]:
    """The mean of ``l`` under the lobe ``f_r (n.l)`` of the ``A`` part (Fresnel weight ``1 - (1 -
    v.h)^5``) or the ``B`` part (``(1 - v.h)^5``) of TANGO's BRDF, sampled as
    :func:`monte_carlo_albedo` (half vectors from the NDF), the BRDF written out here: ``(x, z)``
    with ``v = (sqrt(1 - nv^2), 0, nv)`` and ``n = z``, and the standard error of its angle (the
    ratio estimator's, by the delta method)."""
    rng = np.random.default_rng(seed)
    lam = 2.0 / r**4
    u = -np.log1p(-rng.random(n) * -math.expm1(-2.0 * lam))
    phi = 2.0 * math.pi * rng.random(n)
    cos_t = 1.0 - u / lam
    sin_t = np.sqrt(np.clip(1.0 - cos_t**2, 0.0, None))
    h = np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], axis=1)
    v = np.array([math.sqrt(1.0 - nv * nv), 0.0, nv])
    vh = h @ v
    l_dir = 2.0 * vh[:, None] * h - v
    nl = l_dir[:, 2]
    ok = (vh > 0) & (nl > 0)
    k = (r + 1.0) ** 2 / 8.0
    schlick = (1.0 - np.clip(vh, 0, 1)) ** 5
    fres = schlick if part == "b" else 1.0 - schlick
    # f_r (n.l) / pdf(l) with pdf(l) = D(h) / (4 v.h) (up to the constant normalisation, which cancels)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(ok, fres * (nl / (nl * (1 - k) + k)) / (nv * (1 - k) + k) * vh, 0.0)
    mx, mz = (w * l_dir[:, 0]).sum() / w.sum(), (w * l_dir[:, 2]).sum() / w.sum()
    # the angle's error: the error of the mean's component across it, over the mean's length
    across = (l_dir[:, 0] - mx) * mz - (l_dir[:, 2] - mz) * mx
    se = float(np.std(w * across) / (math.sqrt(n) * w.mean()) / (mx * mx + mz * mz))
    return float(mx), float(mz), se


@pytest.mark.parametrize("nv", [0.05, 0.3, 1.0])
@pytest.mark.parametrize("r", [0.1, 0.5, 1.0])
def test_lobe_moments_match_monte_carlo(nv, r):
    """The table's mean direction (its tilt from the mirror direction, so its angle from n is
    ``acos(n.v) - tilt``) and vMF concentration of each part's lobe, looked up at (n.v, r), against
    the mean of l by Monte Carlo; the concentration against the mean resultant length
    ``coth(kappa) - 1/kappa`` of a vMF, written out here."""
    got = sa.lobe_moments(torch.tensor([nv], dtype=torch.float64), torch.tensor([r], dtype=torch.float64), TANGO)
    for part, tilt, kappa in (("a", got[0], got[1]), ("b", got[2], got[3])):
        theta = math.acos(nv) - float(tilt)
        mx, mz, se = monte_carlo_mean_direction(nv, r, part)
        assert abs(float(theta) - math.atan2(-mx, mz)) < 0.005 + 5 * se, (part, float(theta), math.atan2(-mx, mz), se)
        kappa = float(kappa)
        # 1 - R = 1 / kappa - (coth(kappa) - 1), coth(kappa) - 1 = 2 e / (1 - e), e = exp(-2 kappa)
        e = math.exp(-2.0 * kappa)
        spread = 1.0 / kappa - 2.0 * e / (1.0 - e)
        spread_mc = 1.0 - math.hypot(mx, mz)
        assert abs(spread - spread_mc) <= 0.03 * spread_mc, (part, spread, spread_mc)


def test_interpolation_between_nodes():
    """Halfway between nodes in both coordinates (the worst place for a bilinear lookup), against
    quadrature there, from grazing (n.v = 5e-4) to normal incidence and roughness 0.01 to 1
    (measured 2026-11-22: 0.72% at worst)."""
    nv = np.exp(math.log(sa.NV_MIN) * (1.0 - (np.arange(sa.NV_NODES - 1) + 0.5) / (sa.NV_NODES - 1)))
    nodes = sa.roughness_grid()
    worst = 0.0
    for r in np.sqrt(nodes[:-1] * nodes[1:])[[0, 8, 21, 34, 47, 62]]:
        terms = sa._entry_terms(nv, float(r), TANGO)
        a, b = terms["a"], terms["b"]
        ta, tb = sa.directional_albedo(torch.tensor(nv), torch.full((len(nv),), float(r), dtype=torch.float64), TANGO)
        for f0 in (0.04, 1.0):
            exact = f0 * a + b
            got = f0 * ta.numpy() + tb.numpy()
            worst = max(worst, float(np.max(np.abs(got - exact) / exact)))
    assert worst < 0.01, worst


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_finite_values_and_gradients_at_the_extremes(dtype):
    nv = torch.tensor([5e-4, 1e-3, 0.05, 0.5, 1.0, 0.0, 1.2], dtype=dtype, requires_grad=True)
    r = torch.tensor([0.01, 1.0, 0.05, 0.5, 0.01, 1.0, 0.3], dtype=dtype, requires_grad=True)
    a, b = sa.directional_albedo(nv, r, TANGO)
    moments = sa.lobe_moments(nv, r, TANGO)
    assert all(m.dtype == dtype and torch.isfinite(m).all() for m in moments)
    view_angle = torch.acos(nv.detach().double().clamp(sa.NV_MIN, 1.0))
    assert all((m > 0).all() for m in moments[1::2])
    for tilt in moments[::2]:  # the mean's angle from the normal in [0, pi/2]
        assert (view_angle - tilt.double() >= -1e-2).all() and (view_angle - tilt.double() <= math.pi / 2 + 1e-2).all()
    sum(m.float().sum() for m in moments).backward(retain_graph=True)
    a, b = sa.directional_albedo(nv, r, TANGO)
    assert a.dtype == dtype and torch.isfinite(a).all() and torch.isfinite(b).all()
    assert (a >= 0).all() and (b >= 0).all() and (a + b <= 1.0 + 1e-2).all()  # energy never created
    (a.float().sum() + b.float().sum()).backward()
    assert torch.isfinite(nv.grad).all() and torch.isfinite(r.grad).all()
