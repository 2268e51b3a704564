"""TANGO's specular BRDF as a Mitsuba BSDF, evaluated exactly per direction (no SG warp, no
closed-form integration): the reference our closed-form shading is judged by.

``f(wi, wo) = D(h) F(wi . h) G(wi, wo) / (4 (n . wi) (n . wo))`` with, as in TANGO/PhySG and
:mod:`stages.render.shading` (but written here from the formulas, not through that module):

* ``D(h) = exp(2 / r^4 (h . n - 1)) / (pi r^4)``, the SG normal distribution (``alpha = r^2``);
* ``F = F0 + (1 - F0) (1 - wi . h)^5``, Schlick's Fresnel at the half vector (the closed form
  evaluates it once, at the mirror direction);
* ``G / (4 cos cos) = 1 / (4 (n.wo (1 - k) + k) (n.wi (1 - k) + k))``, Smith-Schlick with
  ``k = (r + 1)^2 / 8``.

Sampling draws the half vector from ``D``'s own distribution restricted to the upper hemisphere
(``cos theta_h = 1 + ln(1 - xi (1 - exp(-lam))) / lam``, uniform azimuth; ``h`` and ``-h`` reflect
to the same direction, so only one of them may be drawn) and reflects; ``pdf(wo) = p(h) / (4 |wi .
h|)``. Mitsuba's
path tracer combines it with the environment's importance sampling (MIS). The BSDF is a Python
plugin, so it runs at speed only in the vectorised LLVM variant.
"""

from __future__ import annotations

import math

PLUGIN = "tango_specular"


def register(mi) -> str:
    """Register the plugin ``tango_specular`` (parameters ``f0``: float, ``roughness``: float in
    [0.01, 1]) with the imported Mitsuba module ``mi``; returns its name."""
    import drjit as dr  # installed with mitsuba

    class TangoSpecular(mi.BSDF):
        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            self.f0 = float(props.get("f0", 0.04))
            self.r = min(max(float(props.get("roughness", 0.5)), 0.01), 1.0)
            self.lam = 2.0 / self.r**4
            self.k = (self.r + 1.0) ** 2 / 8.0
            flags = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide
            self.m_components = [flags]
            self.m_flags = flags

        def _value(self, wi, wo):
            cos_i, cos_o = mi.Frame3f.cos_theta(wi), mi.Frame3f.cos_theta(wo)
            h = dr.normalize(wi + wo)
            d = dr.exp(self.lam * (h.z - 1.0)) / (math.pi * self.r**4)
            f = self.f0 + (1.0 - self.f0) * dr.power(dr.maximum(1.0 - dr.dot(wi, h), 0.0), 5.0)
            g = 1.0 / (4.0 * (cos_o * (1.0 - self.k) + self.k) * (cos_i * (1.0 - self.k) + self.k))
            ok = (cos_i > 0) & (cos_o > 0)
            return dr.select(ok, d * f * g * cos_o, 0.0), ok

        def _pdf(self, wi, wo):
            h = dr.normalize(wi + wo)
            p_h = self.lam / (2.0 * math.pi * (1.0 - math.exp(-self.lam))) * dr.exp(self.lam * (h.z - 1.0))
            ok = (mi.Frame3f.cos_theta(wi) > 0) & (mi.Frame3f.cos_theta(wo) > 0)
            return dr.select(ok, p_h / (4.0 * dr.abs(dr.dot(wi, h))), 0.0)

        def eval(self, ctx, si, wo, active=True):
            value, ok = self._value(si.wi, wo)
            return mi.Spectrum(dr.select(active & ok, value, 0.0))

        def pdf(self, ctx, si, wo, active=True):
            return dr.select(active, self._pdf(si.wi, wo), 0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            value, ok = self._value(si.wi, wo)
            return mi.Spectrum(dr.select(active & ok, value, 0.0)), dr.select(active, self._pdf(si.wi, wo), 0.0)

        def sample(self, ctx, si, sample1, sample2, active=True):
            cos_h = 1.0 + dr.log(1.0 - sample2.x * (1.0 - math.exp(-self.lam))) / self.lam
            cos_h = dr.clip(cos_h, 0.0, 1.0)
            sin_h = dr.safe_sqrt(1.0 - cos_h * cos_h)
            phi = 2.0 * math.pi * sample2.y
            h = mi.Vector3f(sin_h * dr.cos(phi), sin_h * dr.sin(phi), cos_h)
            wo = 2.0 * dr.dot(si.wi, h) * h - si.wi
            bs = dr.zeros(mi.BSDFSample3f)
            bs.wo = wo
            bs.pdf = self._pdf(si.wi, wo)
            bs.eta = 1.0
            bs.sampled_type = mi.UInt32(+mi.BSDFFlags.GlossyReflection)
            bs.sampled_component = mi.UInt32(0)
            value, ok = self._value(si.wi, wo)
            ok = active & ok & (bs.pdf > 0)
            return bs, mi.Spectrum(dr.select(ok, value / dr.maximum(bs.pdf, 1e-30), 0.0))

        def traverse(self, callback):
            pass

        def to_string(self):
            return f"TangoSpecular[f0={self.f0}, roughness={self.r}]"

    mi.register_bsdf(PLUGIN, lambda props: TangoSpecular(props))
    return PLUGIN
