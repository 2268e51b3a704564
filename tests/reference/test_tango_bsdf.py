"""TANGO's specular BRDF as a Mitsuba BSDF: its samples' mean weight is the BRDF's directional
albedo, computed here by quadrature of the textbook formula (written in this test, not through
the plugin or stages.render.shading)."""

import math

import numpy as np
import pytest
from conftest import require_tool

from stages.reference import mitsuba as mref
from stages.reference import tango_bsdf


def albedo_by_quadrature(cos_i: float, f0: float, r: float, n: int = 1500) -> float:
    """``int f(wi, wo) cos(wo) dwo`` over the hemisphere, midpoint rule in (theta, phi)."""
    wi = np.array([math.sqrt(1 - cos_i**2), 0.0, cos_i])
    th = (np.arange(n) + 0.5) / n * (math.pi / 2)
    ph = (np.arange(2 * n) + 0.5) / (2 * n) * 2 * math.pi
    t, p = np.meshgrid(th, ph, indexing="ij")
    wo = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1)
    h = wo + wi
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    d = np.exp(2 / r**4 * (h[..., 2] - 1)) / (math.pi * r**4)
    f = f0 + (1 - f0) * (1 - (h @ wi)) ** 5
    k = (r + 1) ** 2 / 8
    g = 1 / (4 * (wo[..., 2] * (1 - k) + k) * (cos_i * (1 - k) + k))
    integrand = d * f * g * wo[..., 2] * np.sin(t)
    return float(integrand.sum() * (math.pi / 2 / n) * (2 * math.pi / (2 * n)))


@pytest.mark.parametrize(("cos_i", "f0", "r"), [(0.8, 0.5, 0.3), (0.3, 0.04, 0.7), (0.95, 0.9, 1.0)])
def test_sampled_weights_average_to_the_directional_albedo(cos_i, f0, r):
    require_tool(mref.find_libllvm() is not None, "no libLLVM 16+ for Mitsuba's vectorised variant (apt-get install libllvm19)")
    mi = mref.import_mitsuba("llvm_ad_rgb")
    bsdf = mi.load_dict({"type": tango_bsdf.register(mi), "f0": f0, "roughness": r})
    n = 400_000
    rng = np.random.default_rng(0)
    si = mi.SurfaceInteraction3f()
    si.wi = mi.Vector3f(math.sqrt(1 - cos_i**2), 0.0, cos_i)
    bs, weight = bsdf.sample(
        mi.BSDFContext(),
        si,
        mi.Float(rng.uniform(size=n)),
        mi.Point2f(mi.Float(rng.uniform(size=n)), mi.Float(rng.uniform(size=n))),
    )
    w = np.array(weight)
    w = (w.T if w.shape[0] == 3 else w)[:, 0]
    est, se = w.mean(), w.std() / math.sqrt(n)
    want = albedo_by_quadrature(cos_i, f0, r)
    assert abs(est - want) < 5 * se + 2e-3 * want, (est, se, want)
    # eval / pdf at the sampled directions is the weight the sampler returned
    value, pdf = bsdf.eval_pdf(mi.BSDFContext(), si, bs.wo)
    v = np.array(value)
    v = (v.T if v.shape[0] == 3 else v)[:, 0]
    ok = np.array(pdf) > 0
    assert np.allclose(v[ok] / np.array(pdf)[ok], w[ok], rtol=1e-3, atol=1e-6)
