"""Per-point shading with an SG environment light: diffuse + microfacet specular (TANGO Sec. 3.2).

All functions are pure and batched over points ``N`` and light lobes ``K``. No shadows and no
interreflection (TANGO's stated limitation). Inputs are assumed valid: unit normals facing the
viewer (:func:`face_viewer`), albedo and specular colour in [0, 1], roughness in [0.01, 1],
positive light sharpness and amplitude; the networks' parametrisation guarantees them.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from ..config.sections import BRDFS, SPECULAR_LOBES
from .sg import (
    COS_LAMBDA,
    COS_MU,
    COS_OFFSET,
    hemisphere_t_difference,
    hemisphere_terms,
    sg_hemisphere_integral,
    sg_product,
    warp_ndf_to_light,
)
from .specular_albedo import directional_albedo, lobe_moments

#: SG normal distribution ``D(h) = exp(NDF_SHARPNESS / alpha^2 (h . n - 1)) / (pi alpha^2)``, ``alpha = r^2`` [Zhang21]
NDF_SHARPNESS = 2.0
#: Schlick's Fresnel ``F0 + (1 - F0) (1 - cos)^FRESNEL_POWER``
FRESNEL_POWER = 5
#: glTF 2.0's dielectric reflectance at normal incidence (IOR 1.5)
GLTF_DIELECTRIC_F0 = 0.04
#: below this log-ratio the fitted lobe's correction is zero to float precision (exp(-80) ~ 2e-35)
_LOG_RATIO_FLOOR = -80.0
#: the width of the fitted lobe's soft horizon (:func:`log_soft_cosine`), in cosine
HORIZON_SOFTNESS = 1e-3
#: the split sum's average light is the ratio of its two integrals where the lobe's mean cosine
#: with the normal exceeds this (above the cosine fit's error, 0.008), the light along the lobe
#: where it is 0 (a lobe on the horizon), a blend between
SPLIT_SUM_TRUSTED_COSINE = 0.01


@dataclass(frozen=True)
class SGLight:
    """``K`` SG lobes: ``axis (K, 3)`` unit, ``sharpness (K, 1) > 0``, ``amplitude (K, C) >= 0``
    with ``C`` 1 (monochrome) or 3 (RGB)."""

    axis: Tensor
    sharpness: Tensor
    amplitude: Tensor

    def radiance(self, directions: Tensor) -> Tensor:
        """``L(w)`` at unit ``directions (..., 3)`` -> ``(..., C)``: the sum of the lobes, each
        ``exp(lam (w . xi - 1))`` with ``w . xi - 1 = -|w - xi|^2 / 2`` (for unit vectors): the
        difference ``w . xi - 1`` loses the angle below float32's 3.5e-4 radians, which a lobe of
        sharpness 1e5 (3e-3 radians wide) resolves, and its gradient was the large ``lam xi``
        whose part across ``w``, small near the axis, drowned in that vector's rounding (both 2%
        in float32; ``benchmarks/precision.py``)."""
        work = torch.promote_types(directions.dtype, torch.float32)  # (cdist has no bfloat16)
        flat, axis = directions.reshape(-1, 3).to(work), self.axis.to(work)
        apart = torch.cdist(flat, axis, compute_mode="donot_use_mm_for_euclid_dist")  # |w - xi|, (M, K)
        sharpness = lobes_at_points(self.sharpness.T.to(work), len(flat))
        out = torch.exp(-0.5 * sharpness * apart * apart) @ self.amplitude.to(work)
        return out.reshape(*directions.shape[:-1], -1).to(torch.promote_types(directions.dtype, self.amplitude.dtype))


@dataclass(frozen=True)
class Shading:
    """Per-point radiance ``(N, 3)`` split into diffuse and specular; ``rgb = diffuse + specular``."""

    diffuse: Tensor
    specular: Tensor

    @property
    def rgb(self) -> Tensor:
        return self.diffuse + self.specular


def face_viewer(normal: Tensor, view: Tensor, min_cos: float = 1e-3) -> Tensor:
    """Bend unit ``normal (N, 3)`` towards the unit ``view (N, 3)`` (surface -> eye) just enough
    that ``n . v >= min_cos / 2``: ``n' = normalize(n + max(min_cos - n . v, 0) v)``.

    Normals already facing the viewer by ``min_cos`` or more are unchanged. This is the
    parametrisation that keeps the shading's ``n . v`` positive (at silhouettes, and for
    predicted normals tilted away from the eye); ``|n'| >= |n . v + a| = min_cos`` before
    normalisation and ``|n'| <= 2``, hence the bound.
    """
    cos = (normal * view).sum(-1, keepdim=True)
    bent = normal + torch.clamp(min_cos - cos, min=0.0) * view
    return bent / torch.linalg.vector_norm(bent, dim=-1, keepdim=True)


def _cosines(directions: Tensor, axis: Tensor) -> Tensor:
    """Cosines ``(N, K)`` of unit ``directions (N, 3)`` with the lobes' unit ``axis (K, 3)``, the
    product taken in float64 and returned in the directions' dtype: the axes' gradient, a sum over
    the points, then accumulates in float64 (see :func:`lobes_at_points`)."""
    return (directions.double() @ axis.double().T).to(directions.dtype)


def _lit(per_lobe: Tensor, visibility: Tensor | None, amplitude: Tensor) -> Tensor:
    """Each point's light summed over the lobes ``(N, C)``: a per-lobe term ``(N, K)`` of unit
    amplitude, shadowed (:func:`_shadowed`), times the lobes' amplitudes ``(K, C)``, the product
    taken in float64 and returned in the term's dtype."""
    return (_shadowed(per_lobe, visibility).double() @ amplitude.double()).to(per_lobe.dtype)


def _shadowed(per_lobe: Tensor, visibility: Tensor | None) -> Tensor:
    """A per-lobe term ``(N, K)`` (or ``(N, K, C)``) times each lobe's visible share ``(N, K)``
    (:func:`stages.render.visibility.lobe_visibility`; None: no shadows)."""
    if visibility is None:
        return per_lobe
    return per_lobe * (visibility if per_lobe.dim() == 2 else visibility[..., None])


def _hemisphere_product_with_cosine(normal: Tensor, axis: Tensor, sharpness: Tensor, amplitude: Tensor) -> Tensor:
    """``int_{v . n >= 0} G(v) max(v . n, 0) dv`` for SGs ``(N, K, ...)`` and normals ``(N, 1, 3)``,
    with the clamped cosine replaced by its SG fit ``COS_MU exp(COS_LAMBDA (v.n - 1)) - COS_OFFSET``
    [Meder18] and both hemisphere integrals by :func:`sg_hemisphere_integral` (PhySG's scheme)."""
    cos_lam = torch.full_like(normal[..., :1], COS_LAMBDA)
    cos_mu = torch.full_like(normal[..., :1], COS_MU)
    p_axis, p_lam, p_mu = sg_product(normal, cos_lam, cos_mu, axis, sharpness, amplitude)
    first = p_mu * sg_hemisphere_integral(p_lam, (p_axis * normal).sum(-1, keepdim=True))
    second = COS_OFFSET * amplitude * sg_hemisphere_integral(sharpness, (axis * normal).sum(-1, keepdim=True))
    return first - second


def diffuse_radiance_reference(normal: Tensor, albedo: Tensor, light: SGLight, visibility: Tensor | None = None) -> Tensor:
    """``albedo / pi * int L(w) max(w . n, 0) dw`` per point -> ``(N, 3)``.

    ``normal (N, 3)`` unit, ``albedo (N, 3)`` in [0, 1]. Approximate (the clamped-cosine SG fit
    and the hemisphere integral): within 2.5% of brute force for lights of 32 lobes of sharpness
    0.5 to 30 (tested against Monte Carlo, 5 standard errors allowed on top; measured 2.2%).
    ``visibility (N, K)``: each lobe's visible share (shadows; None: none).
    """
    n = normal[:, None, :]
    per_lobe = _hemisphere_product_with_cosine(n, light.axis[None], light.sharpness[None], light.amplitude[None])
    irradiance = _shadowed(per_lobe, visibility).sum(1)  # (N, C)
    # the cosine fit dips to -0.006 at the horizon: clamp the (tiny) negative irradiance [Zhang21]
    return albedo / math.pi * torch.clamp(irradiance, min=0.0)


def ndf_sg(roughness: Tensor) -> tuple[Tensor, Tensor]:
    """SG fit of the GGX-like normal distribution used by PhySG/TANGO for roughness ``r``
    (``alpha = r^2``): sharpness ``lam = 2 / r^4`` (``NDF_SHARPNESS``), amplitude ``1 / (pi r^4)``.
    ``(N, 1)`` each. Normalised to within ``r^4 / 2``: ``int D(h) (h . n) dh = 1 - (1 - exp(-lam)) / lam``
    (tested by quadrature)."""
    r4 = roughness**4
    return NDF_SHARPNESS / r4, 1.0 / (math.pi * r4)


def fresnel_schlick(f0: Tensor, cos: Tensor) -> Tensor:
    """Schlick's Fresnel ``F0 + (1 - F0) (1 - cos)^5``; ``f0 (N, 3)``, ``cos (N, 1)`` in [0, 1]."""
    return f0 + (1.0 - f0) * (1.0 - cos) ** FRESNEL_POWER


def smith_k(roughness: Tensor) -> Tensor:
    """Smith-Schlick's ``k = (r + 1)^2 / 8`` for roughness ``r`` (Karis 2013, as in PhySG; not ``alpha / 2``)."""
    return (roughness + 1.0) ** 2 / 8.0


def smith_schlick_over_cosines(cos_nl: Tensor, cos_nv: Tensor, roughness: Tensor) -> Tensor:
    """``G(l, v) / (4 (n.l) (n.v))`` with Smith-Schlick ``G1(x) = x / (x (1 - k) + k)``,
    ``k = (r + 1)^2 / 8`` (Karis 2013, as in PhySG). Written with the cosines cancelled,
    ``1 / (4 (x_l (1-k) + k) (x_v (1-k) + k))``, so it stays finite at grazing angles."""
    k = smith_k(roughness)
    return 1.0 / (4.0 * (cos_nl * (1.0 - k) + k) * (cos_nv * (1.0 - k) + k))


def specular_radiance_reference(
    normal: Tensor, view: Tensor, specular: Tensor, roughness: Tensor, light: SGLight, visibility: Tensor | None = None
) -> Tensor:
    """Microfacet specular reflection of the SG light per point -> ``(N, 3)`` (TANGO eq. 10).

    The SG normal distribution (:func:`ndf_sg`) is warped into the light domain
    (:func:`~stages.render.sg.warp_ndf_to_light`); the Fresnel and shadowing factor ``M`` is
    evaluated once at the mirror direction ``l = 2 (v.n) n - v`` (where ``h = n``, so
    ``n.l = v.h = n.v``) with ``F0 = specular``; the warped lobe times each light lobe times the
    clamped cosine is integrated over the hemisphere in closed form.

    Accuracy, tested against seeded Monte Carlo (5 standard errors allowed on top of each bound)
    for ``n . v`` in [0.3, 1], roughness 0.1 to 1 and ``F0`` 0.04, 0.3, 0.9:

    - the closed-form integration (clamped-cosine fit, hemisphere integral) is within
      ``0.5% + 0.01 / (n . v)`` of the integral of the same warped lobe (the fit's absolute error,
      0.008, relative to ``n . l ~ n . v``): 1.5% at normal view, 3.8% at ``n . v = 0.3``;
    - against the microfacet BRDF itself (NDF, Fresnel and shadowing varying over the lobe), the
      warp and the single ``M`` are within 3% for roughness <= 0.3 and ``F0 >= 0.3`` (8% at
      ``F0 = 0.04``), and within 30% for roughness <= 1 and ``F0 >= 0.3``; at ``F0 = 0.04`` and
      roughness >= 0.5 the mirror-direction Fresnel overestimates near grazing, up to 3x at
      ``n . v = 0.3`` (bound 200%). Nearer grazing the warp underestimates more (measured, not
      tested: by 54% to 71% at ``n . v = 0.1`` for roughness 0.5 to 1 and ``F0 >= 0.5``), a known
      limit of the isotropic warp [Wang09] that TANGO shares.

    ``normal, view (N, 3)`` unit with ``n . v > 0`` (:func:`face_viewer`), ``specular (N, 3)`` in
    [0, 1], ``roughness (N, 1)`` in [0.01, 1].
    """
    cos_nv = (normal * view).sum(-1, keepdim=True)
    lam, mu = ndf_sg(roughness)
    w_axis, w_lam, w_mu = warp_ndf_to_light(normal, view, lam, mu, cos_nv)
    m = fresnel_schlick(specular, cos_nv) * smith_schlick_over_cosines(cos_nv, cos_nv, roughness)  # (N, 3)
    # the warped BRDF lobe (N, 1, .) times each light lobe (1, K, .)
    p_axis, p_lam, p_mu = sg_product(
        w_axis[:, None],
        w_lam[:, None],
        w_mu[:, None],
        light.axis[None],
        light.sharpness[None],
        light.amplitude[None],
    )
    integral = _shadowed(_hemisphere_product_with_cosine(normal[:, None, :], p_axis, p_lam, p_mu), visibility).sum(1)
    # as for the diffuse term, the cosine fit's slight dip below zero at the horizon is clamped
    return m * torch.clamp(integral, min=0.0)


# ------------------------------------------------------------------------------ fused versions
# The light's amplitudes enter linearly, and every SG quantity the shading needs is a function of
# sharpnesses and of dot products between axes. The fused versions therefore work on (N, K)
# matrices of cosines obtained by matrix products, never on (N, K, 3) tensors, and apply the
# amplitudes with one final (N, K) @ (K, C) product. They are algebraically identical to the
# reference versions above (tested to 1e-10 relative in float64; measured 6e-14) and several times
# faster. Those products, and the sharpnesses' broadcast to the points, are taken in float64
# (_cosines, _lit, lobes_at_points): the light's gradient is a sum over the points whose terms
# cancel.


def lobes_at_points(row: Tensor, points: int) -> Tensor:
    """A per-lobe row ``(1, K)`` (the light's sharpnesses) broadcast to every point ``(N, K)``
    through float64, in the row's own dtype: the same values, but the row's gradient, the sum over
    the ``N`` points of the terms' gradients, is accumulated in float64. Those terms cancel (the
    light's parametrisation holds a lobe's energy), and torch.compile sums a broadcast's gradient
    in its own float32 loop (sequential per vector lane): the default shading's log-sharpness
    gradient over 100,000 points erred by 2.5e-4 of its norm compiled against 1.6e-5 eager; through
    float64, 1.7e-5 (``tests/render/test_light_gradient.py`` holds a compiled sum to eager's).
    Exact in value; the cost is one float64 reduction of ``N x K`` numbers."""
    return row.to(torch.float64).expand(points, -1).to(row.dtype)


def _product_terms(lam1: Tensor, lam2: Tensor, cos12: Tensor) -> tuple[Tensor, Tensor]:
    """Sharpness and log-amplitude factor of the product of two unit SGs from their sharpnesses
    and the cosine between their axes: ``lam = sqrt((l1 - l2)^2 + 2 l1 l2 (1 + c))`` and
    ``lam - l1 - l2 = -2 l1 l2 (1 - c) / (lam + l1 + l2)`` (both free of cancellation). ``c`` is
    a cosine between unit axes, held in [-1, 1]: a matrix product with reduced-precision inputs
    (TF32, bfloat16) returns cosines just outside it, and ``1 + c < 0`` at opposite axes of equal
    sharpness made the square root NaN (TF32 on an H100 at step 40 of a paper run)."""
    cos12 = cos12.clamp(-1.0, 1.0)
    # 0 for lobes of equal sharpness and opposite axes (a cosine rounded to -1 by reduced-precision
    # products reaches it): held at the dtype's smallest normal, where sqrt's derivative is finite
    tiny = torch.finfo(cos12.dtype).tiny
    lam = torch.sqrt(torch.clamp((lam1 - lam2) ** 2 + 2.0 * lam1 * lam2 * (1.0 + cos12), min=tiny))
    log_amp = -2.0 * lam1 * lam2 * (1.0 - cos12) / (lam + lam1 + lam2)
    return lam, log_amp


def cosine_weighted_hemisphere_reference(lam: Tensor, cos_n: Tensor, log_amp: Tensor) -> Tensor:
    """``int_{v.n >= 0} exp(log_amp) G(v; xi, lam, 1) max(v . n, 0) dv`` from ``lam`` and
    ``cos_n = xi . n`` (any matching shapes), with the cosine's SG fit and the hemisphere
    integral, as :func:`_hemisphere_product_with_cosine`: the fit's two terms, ``COS_MU`` and
    ``COS_OFFSET`` times nearly equal integrals, subtracted as they stand (the plain reference
    of :func:`_cosine_weighted_hemisphere`)."""
    cos_lam = torch.as_tensor(COS_LAMBDA, dtype=lam.dtype, device=lam.device)
    lam_q, log_q = _product_terms(lam, cos_lam, cos_n)
    safe = torch.where(lam_q > 0, lam_q, torch.ones_like(lam_q))
    cos_qn = torch.where(lam_q > 0, (COS_LAMBDA + lam * cos_n) / safe, torch.ones_like(lam_q))
    first = COS_MU * torch.exp(log_amp + log_q) * sg_hemisphere_integral(lam_q, cos_qn.clamp(-1.0, 1.0))
    second = COS_OFFSET * torch.exp(log_amp) * sg_hemisphere_integral(lam, cos_n)
    return first - second


def _cosine_weighted_hemisphere(lam: Tensor, cos_n: Tensor, log_amp: Tensor) -> Tensor:
    """:func:`cosine_weighted_hemisphere_reference` (the same function, exact algebra: equal to
    5e-11 in float64) without its cancellation. The fit's two terms are ``COS_MU`` and
    ``COS_OFFSET`` (32.7 and 31.7) times hemisphere integrals of nearly the same lobe (the light's,
    and its product with the cosine's broad lobe), so their difference, near the horizon a
    thousandth of either for a sharp lobe, kept float32's rounding of each times a thousand (the
    diffuse term's gradient erred by 1.5% there; ``benchmarks/precision.py``). With each integral
    ``a + b p s`` (:func:`~stages.render.sg.hemisphere_terms`) and ``q`` the product's:

        COS_MU e^(log_q) H_q - COS_OFFSET H = (COS_MU e^(log_q) a_q - COS_OFFSET a)
            + b ((rho - COS_OFFSET) p_q s_q + COS_OFFSET ((p_q - p) s_q + p (s_q - s)))

    with ``rho - COS_OFFSET = COS_MU e^(log_q) b_q / b - COS_OFFSET``, the cosine's fit at the
    product's axis, counted from the fit's value at the horizon: ``(m - COS_OFFSET) + m
    expm1(log_q + COS_LAMBDA + log(b_q / b))`` with ``m = COS_MU e^-COS_LAMBDA`` (for a sharp lobe
    near the horizon it is -0.0064, and as the difference of two numbers of 32 float32 kept 4e-5
    of it); ``p_q - p`` from each step's own ``p - 1`` (each 1 to ``e^-t`` for a sharp lobe); the
    logistic's difference ``s_q - s = s_q sigma(-t c) (1 - e^-(x_q - x))``; and ``x_q - x``,
    ``lam_q - lam``, ``log_q + COS_LAMBDA``, ``c_q - c`` and ``t_q - t`` each from their own closed
    forms (:func:`~stages.render.sg.hemisphere_t_difference`), so that no two large numbers are
    subtracted. The first bracket cancels only for broad lobes, where the integrals are not small.
    In float32 within 2e-6 of float64 (value and derivatives) for sharpness 50 to 1e5 within 1e-2
    of the horizon (tested), where the split sum divides two such integrals."""
    tiny = torch.finfo(lam.dtype).tiny
    c = cos_n
    lam_q, log_q = _product_terms(lam, torch.as_tensor(COS_LAMBDA, dtype=lam.dtype, device=lam.device), c)
    delta = (COS_LAMBDA**2 + 2.0 * COS_LAMBDA * lam * c) / (lam_q + lam)  # lam_q - lam
    c_q = torch.clamp((COS_LAMBDA + lam * c) / lam_q, -1.0, 1.0)
    a, b, p, p1, s, t = hemisphere_terms(lam, c)
    a_q, b_q, p_q, p1_q, s_q, t_q = hemisphere_terms(lam_q, c_q)
    lam_pos = torch.clamp(lam, min=tiny)
    # log(b_q / b) = 2 log((1 - e^-lam_q) / (1 - e^-lam)) - log(lam_q / lam), each as log1p, where
    # the two lobes are close (lam_q > lam / 2); where the product's lobe all but vanishes (equal
    # sharpness, opposite axes: lam_q at its floor) the logs themselves, which do not cancel there
    near = delta > -0.5 * lam_pos
    d_near = torch.where(near, delta, torch.zeros_like(delta))
    grown = torch.exp(-lam) * -torch.expm1(-d_near) / torch.clamp(-torch.expm1(-lam_pos), min=tiny)
    close = 2.0 * torch.log1p(grown) - torch.log1p(d_near / lam_pos)
    b, b_q = torch.clamp(b, min=tiny), torch.clamp(b_q, min=tiny)
    log_b_ratio = torch.where(near, close, torch.log(torch.where(near, torch.ones_like(b_q), b_q / b)))
    # COS_MU e^(log_q) b_q / b - COS_OFFSET is the cosine's fit at the product's axis: near the
    # horizon -0.0064 (the fit's error there), a difference of two numbers of 32 (float32 kept 4e-5
    # of it, and the split sum's ratio of two such integrals a thousand times that), so counted
    # from the fit at the horizon (Python floats, float64) by log_q's distance to it,
    # log_q + C = C (delta + C + 2 lam c) / (lam_q + lam + C) (_product_terms' form, exact algebra)
    mu_at_horizon = COS_MU * math.exp(-COS_LAMBDA)
    from_horizon = COS_LAMBDA * (delta + COS_LAMBDA + 2.0 * lam * c) / (lam_q + lam + COS_LAMBDA)
    rho_minus_offset = (mu_at_horizon - COS_OFFSET) + mu_at_horizon * torch.expm1(from_horizon + log_b_ratio)
    # x_q - x = t_q c_q - t c by its closed form where the lobes are close, as it stands elsewhere
    # (where lam_q nears its floor c_q is held in [-1, 1] and the closed form divides by lam_q)
    x_close = t * (COS_LAMBDA - d_near * c) / lam_q + hemisphere_t_difference(lam, lam_q, d_near) * c_q
    x_diff = torch.where(near, x_close, t_q * c_q - t * c)
    s_diff = s_q * torch.sigmoid(-t * c) * -torch.expm1(-x_diff)
    opposite = COS_MU * torch.exp(log_q) * a_q - COS_OFFSET * a
    toward = b * (rho_minus_offset * p_q * s_q + COS_OFFSET * ((p1_q - p1) * s_q + p * s_diff))
    return torch.exp(log_amp) * (opposite + toward)


def diffuse_radiance(normal: Tensor, albedo: Tensor, light: SGLight, visibility: Tensor | None = None) -> Tensor:
    """Fused :func:`diffuse_radiance_reference` (same result): ``(N, 3)``."""
    cos_n = _cosines(normal, light.axis)  # (N, K)
    lam = lobes_at_points(light.sharpness.T, len(normal))
    per_lobe = _cosine_weighted_hemisphere(lam, cos_n, torch.zeros_like(light.sharpness.T))
    irradiance = _lit(per_lobe, visibility, light.amplitude)
    return albedo / math.pi * torch.clamp(irradiance, min=0.0)


def gltf_f0(base: Tensor, metallic: Tensor) -> Tensor:
    """glTF 2.0's specular colour at normal incidence: ``F0 = lerp(0.04, base, metallic)`` (the
    dielectric's IOR 1.5, the metal's base colour). ``base (N, 3)``, ``metallic (N, 1)``."""
    return GLTF_DIELECTRIC_F0 * (1.0 - metallic) + base * metallic


def _one_minus_schlick(vh: Tensor) -> Tensor:
    """``1 - (1 - x)^5`` as its expanded polynomial ``x (5 - 10 x + 10 x^2 - 5 x^3 + x^4)``: the
    difference loses its relative precision as ``x`` nears 0 (a half vector nearly across the
    view), the polynomial keeps it."""
    return vh * (5.0 + vh * (-10.0 + vh * (10.0 + vh * (-5.0 + vh))))


def _diffuse_half_vector_cosine(
    normal: Tensor, view: Tensor, cos_nv: Tensor, cos_n: Tensor, lam: Tensor, light: SGLight
) -> Tensor:
    """``v . h`` ``(N, K)`` with ``h`` the half vector of the view and the axis ``q = (c n + lam xi)
    / lam_q`` of each light lobe's product with the clamped cosine's SG (``c`` its sharpness),
    from the components of ``q + v`` in the frame ``(n, t, n x t)`` of the view's tangent
    direction ``t``: ``v . h = |q + v| / 2``, a sum of squares. The difference ``1 + q . v``
    cancels where the product's axis is opposite the view (a broad lobe under the horizon seen
    along the normal: float32's value was 150 times too small there; ``benchmarks/precision.py``).
    Held at 1e-6 where ``q = -v`` (``h`` undefined; the square root's derivative infinite).
    ``cos_n (N, K)``: the lobes' cosines with the normal; ``lam (N, K)``: their sharpnesses at the
    points (:func:`lobes_at_points`)."""
    tangent, across, v_t, v_b = _view_frame(normal, view, cos_nv)
    cos_t, cos_b = _cosines(tangent, light.axis), _cosines(across, light.axis)
    # lam_q is positive (held at its floor by _product_terms)
    lam_q, _ = _product_terms(lam, torch.as_tensor(COS_LAMBDA, dtype=lam.dtype, device=lam.device), cos_n)
    q_n, q_t, q_b = (COS_LAMBDA + lam * cos_n) / lam_q, lam * cos_t / lam_q, lam * cos_b / lam_q
    squared = (q_n + cos_nv) ** 2 + (q_t + v_t) ** 2 + (q_b + v_b) ** 2  # |q + v|^2
    return torch.sqrt(torch.clamp(squared / 4.0, min=1e-12, max=1.0))


def diffuse_radiance_gltf(
    normal: Tensor, view: Tensor, diffuse_color: Tensor, light: SGLight, visibility: Tensor | None = None
) -> Tensor:
    """glTF 2.0's diffuse layer under the SG light -> ``(N, 3)``: ``c / pi int (1 - F(v.h)) L(l)
    max(n . l, 0) dl`` with the dielectric's ``F = 0.04 + 0.96 (1 - v.h)^5`` (the specular layer's
    reflection taken out: energy conserving, glTF 2.0 Appendix B ``fresnel_mix``) and ``c`` the
    diffuse colour ``base (1 - metallic)``.

    Per light lobe the cosine-weighted integral is :func:`diffuse_radiance`'s closed form, and the
    Fresnel weight ``1 - F`` is taken at the half vector of ``v`` and the axis of that lobe's product
    with the clamped cosine's SG (where the integrand sits): exact for a lobe far sharper than the
    cosine (a sun), and for a broad one the weight at ``h`` between ``v`` and ``n``. Tested against
    Monte Carlo of the specification's formula. ``visibility (N, K)``: each lobe's visible share."""
    cos_nv = (normal * view).sum(-1, keepdim=True)
    cos_n = _cosines(normal, light.axis)  # (N, K)
    lam = lobes_at_points(light.sharpness.T, len(normal))
    per_lobe = _cosine_weighted_hemisphere(lam, cos_n, torch.zeros_like(light.sharpness.T))
    weight = (1.0 - GLTF_DIELECTRIC_F0) * _one_minus_schlick(_diffuse_half_vector_cosine(normal, view, cos_nv, cos_n, lam, light))
    irradiance = _lit(per_lobe * weight, visibility, light.amplitude)
    return diffuse_color / math.pi * torch.clamp(irradiance, min=0.0)


def specular_radiance(
    normal: Tensor, view: Tensor, specular: Tensor, roughness: Tensor, light: SGLight, visibility: Tensor | None = None
) -> Tensor:
    """Fused :func:`specular_radiance_reference` (same result): ``(N, 3)``."""
    cos_nv = (normal * view).sum(-1, keepdim=True)
    lam, mu = ndf_sg(roughness)
    w_axis, w_lam, w_mu = warp_ndf_to_light(normal, view, lam, mu, cos_nv)
    m = fresnel_schlick(specular, cos_nv) * smith_schlick_over_cosines(cos_nv, cos_nv, roughness)
    integral = w_mu * _lit(_warped_lobe_per_light_lobe(normal, w_axis, w_lam, light), visibility, light.amplitude)
    return m * torch.clamp(integral, min=0.0)


def _warped_lobe_per_light_lobe(normal: Tensor, w_axis: Tensor, w_lam: Tensor, light: SGLight) -> Tensor:
    """``int G_w(l) G_k(l) max(n . l, 0) dl`` of the unit-amplitude warped lobe ``(w_axis (N, 3),
    w_lam (N, 1))`` with each unit-amplitude light lobe ``k`` -> ``(N, K)``, in the closed form of
    :func:`_cosine_weighted_hemisphere` (the light's amplitudes are applied by the caller)."""
    cos_wl = _cosines(w_axis, light.axis)  # (N, K)
    cos_nl = _cosines(normal, light.axis)
    cos_nw = (normal * w_axis).sum(-1, keepdim=True)  # (N, 1)
    lam_l = lobes_at_points(light.sharpness.T, len(normal))
    lam_p, log_p = _product_terms(w_lam, lam_l, cos_wl)
    safe = torch.where(lam_p > 0, lam_p, torch.ones_like(lam_p))
    cos_pn = torch.where(lam_p > 0, (w_lam * cos_nw + lam_l * cos_nl) / safe, torch.ones_like(lam_p))
    return _cosine_weighted_hemisphere(lam_p, cos_pn.clamp(-1.0, 1.0), log_p)


def specular_radiance_split_sum(
    normal: Tensor,
    view: Tensor,
    specular: Tensor,
    roughness: Tensor,
    light: SGLight,
    brdf: str = "tango",
    visibility: Tensor | None = None,
) -> Tensor:
    """Microfacet specular reflection of the SG light with exact energy [Karis13's split sum]:
    ``(F0 A + B) <L>`` per point -> ``(N, 3)``.

    ``F0 A + B`` is the BRDF's directional albedo (:mod:`stages.render.specular_albedo`, the
    reflected energy under a uniform white light, tabulated by quadrature of the same BRDF);
    ``<L>`` is the light averaged under the warped lobe of :func:`specular_radiance` times the
    clamped cosine, ``int W L (n.l) / int W (n.l)``, both integrals in the same closed form (the
    lobe's own integral is its product with a light of sharpness 0). The isotropic warp and the
    mirror-direction Fresnel then shape the average only, not the energy: where
    :func:`specular_radiance` errs by -90% to +180% near grazing for rough lobes, this stays
    within 3% of Monte Carlo of the microfacet BRDF for ``n . v >= 0.3`` and roughness 0.05 to 1,
    and within 17% down to ``n . v = 0.05`` (the lobe's shape there, rough lobes of 0.5-0.8;
    tested). ``<L>`` is clamped to ``[0, sum of the amplitudes]`` (an average cannot leave the
    light's range), which keeps it finite where both integrals vanish at extreme grazing.

    ``normal, view (N, 3)`` unit with ``n . v > 0`` (:func:`face_viewer`), ``specular (N, 3)`` in
    [0, 1], ``roughness (N, 1)`` in [0.01, 1].
    """
    cos_nv = (normal * view).sum(-1, keepdim=True)
    lam, mu = ndf_sg(roughness)
    w_axis, w_lam, _ = warp_ndf_to_light(normal, view, lam, mu, cos_nv)
    lit = _lit(_warped_lobe_per_light_lobe(normal, w_axis, w_lam, light), visibility, light.amplitude)  # (N, C)
    cos_nw = (normal * w_axis).sum(-1, keepdim=True)  # (N, 1)
    whole = _cosine_weighted_hemisphere(w_lam, cos_nw.clamp(-1.0, 1.0), torch.zeros_like(w_lam))  # (N, 1)
    tiny = torch.finfo(whole.dtype).tiny
    brightest = light.amplitude.sum(0, keepdim=True)  # (1, C): no average of the light exceeds it
    ratio = torch.minimum(torch.clamp(lit, min=0.0) / torch.clamp(whole, min=tiny), brightest)
    # a lobe on the horizon: the cosine's SG fit errs by up to 0.008 in the cosine, and both
    # integrals sink into that error (``whole`` came out negative at n . v = 1e-3, and the ratio
    # of two vanishing numbers was the brightest light in float64 and 0 in float32); there the
    # average tends to the light along the lobe, taken where ``whole`` falls below the fit's error
    trust = torch.clamp(whole * w_lam / (2.0 * math.pi * SPLIT_SUM_TRUSTED_COSINE), min=0.0, max=1.0)
    mean = trust * ratio + (1.0 - trust) * light.radiance(w_axis)
    a, b = directional_albedo(cos_nv, roughness, brdf)
    return (specular * a + b) * mean


def _log_ndf_times_visibility(one_minus_nh: Tensor, nl: Tensor, nv: Tensor, roughness: Tensor, brdf: str) -> Tensor:
    """``log(D(h) G(l, v) / (4 (n.l)(n.v)))`` of the BRDF ``brdf`` from ``1 - n.h``, ``n.l`` and
    ``n.v`` (broadcasting). ``tango``: the SG NDF (:func:`ndf_sg`) and Smith-Schlick
    (:func:`smith_schlick_over_cosines`); ``gltf``: GGX ``alpha^2 / (pi ((n.h)^2 (alpha^2 - 1) +
    1)^2)`` and the separable Smith-GGX visibility ``1 / ((n.l + sqrt(alpha^2 + (1 - alpha^2)
    (n.l)^2)) (n.v + sqrt(...)))`` with ``alpha = r^2`` (glTF 2.0, Appendix B.3.2), the GGX
    denominator written ``alpha^2 (n.h)^2 + (1 - n.h)(1 + n.h)`` so that a sharp lobe keeps its
    precision near its peak."""
    if brdf == "tango":
        lam_d, mu_d = ndf_sg(roughness)
        k = smith_k(roughness)
        return torch.log(mu_d) - lam_d * one_minus_nh - torch.log(4.0 * (nl * (1.0 - k) + k) * (nv * (1.0 - k) + k))
    if brdf != "gltf":
        raise ValueError(f"unknown BRDF {brdf!r}; choose one of {', '.join(BRDFS)}")
    a2 = roughness**4
    nh = 1.0 - one_minus_nh
    denom = a2 * nh * nh + one_minus_nh * (2.0 - one_minus_nh)
    vis = (nl + torch.sqrt(a2 + (1.0 - a2) * nl * nl)) * (nv + torch.sqrt(a2 + (1.0 - a2) * nv * nv))
    return torch.log(a2 / math.pi) - 2.0 * torch.log(denom) - torch.log(vis)


def log_soft_cosine(cos: Tensor, width: float = HORIZON_SOFTNESS) -> Tensor:
    """``log(w softplus(cos / w))``: the log of the clamped cosine ``max(cos, 0)`` with its
    horizon softened over ``w`` (``HORIZON_SOFTNESS``), any shape, any ``cos``. Above the horizon
    it is ``log(cos)`` to a relative ``w e^(-cos/w) / cos`` (5e-6 at ``cos = 10 w``); below it it
    falls as ``log(w) + cos / w``, straight into the fitted lobe's floor. Its derivative is
    bounded by about ``1.3 / w``, where ``log(max(cos, 0))``'s grows as ``1 / cos`` at the horizon
    and then jumps to 0: the fitted lobe's correction at a product lobe's axis near the horizon
    (float32's rounding of that cosine, amplified by ``1 / cos``, made its gradient err by 29%).
    ``softplus(y)`` for ``y < -20`` is ``e^y`` to a relative ``e^y / 2``, taken as such."""
    y = cos / width
    soft = torch.log(torch.nn.functional.softplus(torch.clamp(y, min=-20.0)))
    return math.log(width) + torch.where(y < -20.0, y, soft)


class LightCosines(NamedTuple):
    """Each light lobe's axis against a point's frame ``(N, K)``: its cosines with the normal
    (``nl``), the view (``vl``), the view's tangent direction (``tl``) and ``n x t`` (``bl``); and
    per point ``(N, 1)`` the view's components along the normal (``nv``), along ``t`` (its sine,
    ``sin_nv``) and along ``n x t`` (``vb``: 0, but its gradient is the view's motion across the
    plane, which the sine alone loses where the view is normal and ``t`` an arbitrary choice). The
    axis's component across the ``n``-``t`` plane is ``bl`` itself, not ``1 - nl^2 - tl^2``: that
    difference cancels where the axis lies in the plane and, clamped at 0, left a kink that
    float32's rounding of a unit normal crossed (the fitted lobe's gradient to the normal erred by
    8% there)."""

    nl: Tensor
    vl: Tensor
    tl: Tensor
    nv: Tensor
    sin_nv: Tensor
    bl: Tensor
    vb: Tensor | float = 0.0


class BrdfPart(NamedTuple):
    """One Fresnel part of the BRDF's lobe at each point ``(N, 1)``: the fitted vMF's mean direction
    as its angle from the mirror direction towards the normal (``tilt``,
    :func:`~stages.render.specular_albedo.lobe_moments`) and its concentration (``kappa``), the
    part's ``energy``, and which part it is (``"a"``: the ``F0``-weighted one, ``"b"``: Schlick's)."""

    tilt: Tensor
    kappa: Tensor
    energy: Tensor
    fresnel: str


def _view_tangent(normal: Tensor, view: Tensor, cos_nv: Tensor) -> tuple[Tensor, Tensor]:
    """The unit direction ``t (N, 3)`` of the view across the normal and the view's sine with it
    ``(N, 1)``: ``(v - (n.v) n) / sin``; at a normal view (sine below 1e-7), where the lobe's mean
    is the normal and any direction across it serves, ``n x e`` normalised for the coordinate axis
    ``e`` least aligned with ``n``, so that ``(n, t, n x t)`` stays a frame.

    ``v - (n.v) n`` is taken as ``(n x v) x n`` (equal for a unit ``n``): a cross product with ``n``
    is perpendicular to ``n`` to its own rounding, where the difference near a normal view keeps
    float32's rounding of ``n.v`` along ``n`` (at a sine of 1.3e-7 the "tangent" pointed mostly along
    the normal, and a horizon lobe's specular came out 13 times too dark in float32; found by
    ``benchmarks/precision.py``)."""
    tangent = torch.linalg.cross(torch.linalg.cross(normal, view, dim=-1), normal, dim=-1)
    sin_nv = torch.linalg.vector_norm(tangent, dim=-1, keepdim=True)
    pick = torch.nn.functional.one_hot(normal.abs().argmin(dim=-1), 3).to(normal.dtype)
    across = torch.nn.functional.normalize(torch.linalg.cross(normal, pick, dim=-1), dim=-1)
    degenerate = sin_nv <= 1e-7
    tangent = torch.where(degenerate, across, tangent / torch.where(degenerate, torch.ones_like(sin_nv), sin_nv))
    return tangent, sin_nv


def _view_frame(normal: Tensor, view: Tensor, cos_nv: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The frame ``(n, t, n x t)`` of the view's tangent direction (:func:`_view_tangent`) as
    ``t, n x t (N, 3)``, and the view's components along them ``(N, 1)`` (its sine, and 0) as
    products with the frame, so that their gradient holds in every direction across ``n`` (at a
    normal view the sine's norm had none)."""
    tangent, _ = _view_tangent(normal, view, cos_nv)
    across = torch.linalg.cross(normal, tangent, dim=-1)
    return tangent, across, (view * tangent).sum(-1, keepdim=True), (view * across).sum(-1, keepdim=True)


class LobeMean(NamedTuple):
    """A fitted lobe's mean direction ``mu = cos_t n - sin_t t + b (n x t)`` in the view's frame
    ``(N, 1)`` each, and ``sin_gap = sin_nv - sin_t``, the mean's gap from the mirror direction
    along ``t`` (:func:`_lobe_mean`)."""

    cos_t: Tensor
    sin_t: Tensor
    b: Tensor
    sin_gap: Tensor


def _lobe_mean(c: LightCosines, tilt: Tensor) -> LobeMean:
    """The mean direction of a lobe tilted by ``tilt (N, 1)`` from the mirror direction of the view
    towards the normal: the mirror direction ``(n.v, -sin_nv, -vb)`` turned in the plane of ``n``
    and the view, from the view's own components, so that near the mirror configuration the mean's
    gap from it, ``sin_nv - sin_t = 2 sin_nv sin^2(tilt / 2) + n.v sin(tilt)``, is a sum that does
    not cancel. Its component across the plane is ``-(sin_t / sin_nv) vb``: 0, but where the view
    is normal to the surface (the frame's ``t`` an arbitrary choice, see :class:`LightCosines`) it
    carries the mean's motion with a view turning across ``t``; the factor's own gradient meets
    ``vb = 0`` and is left out (it held ``1 / sin_nv^2`` there). ``sin_t / sin_nv`` tends to 1 at a
    normal view (the tilt vanishes there to second order) and is taken as 1 below ``sin_nv``
    1e-6."""
    cos_d, sin_d = torch.cos(tilt), torch.sin(tilt)
    cos_t = c.nv * cos_d + c.sin_nv * sin_d
    sin_t = c.sin_nv * cos_d - c.nv * sin_d
    sin_gap = 2.0 * c.sin_nv * torch.sin(0.5 * tilt) ** 2 + c.nv * sin_d
    with torch.no_grad():
        tilted = c.sin_nv > 1e-6
        turn = torch.where(tilted, sin_t / torch.where(tilted, c.sin_nv, torch.ones_like(sin_t)), torch.ones_like(sin_t))
    return LobeMean(cos_t, sin_t, -turn * c.vb, sin_gap)


def _half_vector_terms(nl, cos_tl, c: LightCosines, mean: LobeMean, cos_ml, kappa, sharpness, lam_p):
    """``1 - n.h`` and ``1 - v.h`` of the half vector ``h = (xi' + v) / |xi' + v|`` between the
    product lobe's axis ``xi' = (kappa mu + nu xi) / lam_p`` and the view, ``(N, K)`` each, from the
    components of ``xi' + v`` and ``xi' - v`` in the frame ``(n, t, n x t)`` (``t`` the view's
    tangent direction), as sums of squares: ``1 - n.h = (t^2 + b^2) / (L^2 + (n.(xi'+v)) L)`` with
    ``L = |xi' + v|``, and ``1 - v.h = 1 - L / 2 = |xi' - v|^2 / (2 (2 + L))``. The plain
    differences cancel to nothing where it matters: ``1 - n.h`` near the mirror configuration,
    where a sharp NDF multiplies it by ``2 / alpha^2`` (4e4 at roughness 0.08), and ``1 - v.h``
    where the axis nears the view, where Schlick's factor takes its fifth power; clamped at 0 and
    1e-30 their rounding left kinks (float64's finite differences of the fitted lobe ran from 7.7
    to 127 as the step shrank; float32's gradient erred by 29% to the view and 8% to the normal)."""
    t_x = (sharpness * cos_tl - kappa * mean.sin_t) / lam_p  # xi' along t
    b_x = (sharpness * c.bl + kappa * mean.b) / lam_p  # xi' along n x t
    b2 = (b_x + c.vb) ** 2  # (xi' + v) along n x t, squared
    # xi' + v along n, and along t: t_x + sin_nv, which near the mirror configuration is the
    # difference of two sines near 1 (the view's and the mean's); written with the mean's gap from
    # the mirror direction, sin_nv - sin_t, and lam_p - kappa = nu (nu + 2 kappa mu.xi) / (lam_p +
    # kappa), each without cancellation
    lam_gap = sharpness * (sharpness + 2.0 * kappa * cos_ml) / (lam_p + kappa)
    n_c = nl + c.nv
    t_c = (sharpness * cos_tl + lam_gap * c.sin_nv + kappa * mean.sin_gap) / lam_p
    across = t_c**2 + b2
    # |xi' + v| held at 1e-6 where the axis is opposite the view (h undefined; the square root's
    # derivative at 0 is infinite)
    length = torch.sqrt(torch.clamp(n_c**2 + across, min=1e-12))
    # 1 - n.h: the sum of squares where h is above the horizon (n_c > 0: no cancellation can reach
    # the denominator), the plain difference below it (1 - n.h > 1: none to fear)
    up = n_c > 0
    den = torch.where(up, length * (length + n_c), torch.ones_like(length))
    one_minus_nh = torch.where(up, across / den, 1.0 - n_c / length)
    apart = (nl - c.nv) ** 2 + (t_x - c.sin_nv) ** 2 + (b_x - c.vb) ** 2  # |xi' - v|^2
    one_minus_vh = apart / (2.0 * (2.0 + length))
    return one_minus_nh, torch.clamp(one_minus_vh, min=0.0, max=1.0)


def _fitted_part(c: LightCosines, part: BrdfPart, roughness: Tensor, sharpness: Tensor, brdf: str = "tango") -> Tensor:
    """``int f_part(l) (n . l) G_k(l) dl / energy`` for one part of the BRDF and every unit light
    lobe ``k`` -> ``(N, K)``; see :func:`specular_radiance_fitted`. ``roughness (N, 1)``,
    ``sharpness (N, K)`` (:func:`lobes_at_points`)."""
    cos_nl, cos_tl, cos_nv = c.nl, c.tl, c.nv
    tilt, kappa, energy, fresnel_part = part
    mean = _lobe_mean(c, tilt)
    cos_t, sin_t, mean_b = mean.cos_t, mean.sin_t, mean.b
    cos_ml = cos_t * cos_nl - sin_t * cos_tl + mean_b * c.bl
    lam_p, log_amp = _product_terms(kappa, sharpness, cos_ml)
    lam_p = torch.clamp(lam_p, min=1e-12)
    # the normalised vMF's inner product with the light lobe, exp(lam_p - kappa - nu) written stably;
    # its exponential is taken below, together with the correction's, in one exp
    inner = kappa * torch.expm1(-2.0 * lam_p) / (lam_p * torch.expm1(-2.0 * kappa))
    # the product lobe's axis xi' = (kappa mu + nu xi) / lam_p: its cosines with n and v
    nl = (kappa * cos_t + sharpness * cos_nl) / lam_p
    # kappa (mu . xi' - 1) = -kappa x / lam_p, c = mu . xi, with x = lam_p - (kappa + nu c), which
    # equals nu^2 (1 - c^2) / (kappa + nu c + lam_p) (their product is lam_p^2 - (kappa + nu c)^2):
    # the quotient where kappa + nu c >= 0 (the difference cancels as xi nears mu), the difference,
    # a sum of positives, where kappa + nu c < 0 (there the quotient's denominator cancels to 0 as
    # xi nears -mu: float32 held it at 1e-12 and the fit came out e^80 too large)
    toward = kappa + sharpness * cos_ml
    # 1 - (mu . xi)^2 = |mu x xi|^2, from the components (no cancellation where xi nears mu)
    across = (cos_t * cos_tl + sin_t * cos_nl) ** 2
    across = across + (sin_t * c.bl + mean_b * cos_tl) ** 2 + (mean_b * cos_nl - cos_t * c.bl) ** 2
    ahead = toward >= 0
    x = torch.where(ahead, sharpness**2 * across / torch.where(ahead, toward + lam_p, torch.ones_like(lam_p)), lam_p - toward)
    log_fit = torch.log(kappa / (-2.0 * math.pi * torch.expm1(-2.0 * kappa))) - kappa * x / lam_p
    # the BRDF part times the cosine at xi', over the part's energy: the true lobe's density there
    nl_c = torch.clamp(nl, min=0.0, max=1.0)
    one_minus_nh, one_minus_vh = _half_vector_terms(nl, cos_tl, c, mean, cos_ml, kappa, sharpness, lam_p)
    tiny = torch.finfo(one_minus_vh.dtype).tiny
    log_schlick = FRESNEL_POWER * torch.log(torch.clamp(one_minus_vh, min=tiny))
    log_fres = log_schlick if fresnel_part == "b" else torch.log1p(-torch.exp(log_schlick).clamp(max=1.0 - 1e-7))
    log_true = (
        _log_ndf_times_visibility(one_minus_nh, nl_c, cos_nv, roughness, brdf)
        + log_fres
        + log_soft_cosine(nl)
        - torch.log(energy)
    )
    ratio = torch.clamp(log_true - log_fit, min=_LOG_RATIO_FLOOR, max=-_LOG_RATIO_FLOOR)
    weight = sharpness / (sharpness + kappa)  # 0: the light is broad against the lobe; 1: sharp
    # one exponential: exp(log_amp) * exp(weight * ratio) as two factors underflows to 0 in the
    # first (log_amp < -104 in float32, a sharp lobe far off the product's axis) while the second
    # reaches e^80, and the backward then multiplies 0 by an overflowed gradient: NaN
    return inner * torch.exp(log_amp + weight * ratio)


def specular_radiance_fitted(
    normal: Tensor,
    view: Tensor,
    specular: Tensor,
    roughness: Tensor,
    light: SGLight,
    brdf: str = "tango",
    visibility: Tensor | None = None,
) -> Tensor:
    """Microfacet specular reflection of the SG light with exact energy and a lobe fitted to the
    BRDF, corrected by the BRDF itself at each light lobe -> ``(N, 3)``.

    The BRDF's lobe ``f_r(l, v) (n . l)`` splits, by Schlick's Fresnel, into an ``F0``-weighted part
    of energy ``A`` and a part of energy ``B`` (:mod:`stages.render.specular_albedo`, by quadrature);
    each part, divided by its energy, is a density ``p`` over light directions. The table also holds
    each density's first moment, from which ``p`` is approximated by the vMF ``q`` with the same mean
    (direction and length): a lobe that bends towards the normal near grazing and widens with
    roughness as the BRDF's does, which the isotropic warp of the mirror direction does not. Per
    light lobe ``G_k`` (axis ``xi``, sharpness ``nu``)

        int p G_k ~ (int q G_k) * (p(xi') / q(xi'))^(nu / (nu + kappa)),

    the closed-form inner product of ``q`` with ``G_k`` times the ratio of the true density to the
    fitted one at the axis ``xi'`` of their product, raised to a power that is 0 for a light broad
    against the lobe (where the mean alone decides) and 1 for a sharp one (where the integral tends
    to ``p(xi) 2 pi / nu``: the BRDF evaluated at the light's direction). Exact in both limits and
    for a light linear in direction (both tested); between them, measured against quadrature of
    the BRDF for ``n . v`` 0.05 to 1 and roughness 0.05 to 1 (``benchmarks/specular_lobes.py``):
    within 5% for smooth lights (32 lobes of sharpness 5; tested against Monte Carlo), 3.8% for the
    studio light, 3.7% for a sun of sharpness 300 away from the mirror direction, 8.9% for 32 lobes
    of sharpness 30; a sun reflected at the mirror direction of a lobe of its own width (roughness
    0.2 to 0.3) errs by up to 30%.

    ``brdf``: whose microfacet lobe (``tango``: TANGO's SG NDF and Smith-Schlick; ``gltf``: GGX and
    the separable Smith-GGX of glTF 2.0), with its own table of energies and moments.

    ``normal, view (N, 3)`` unit with ``n . v > 0`` (:func:`face_viewer`), ``specular (N, 3)`` in
    [0, 1], ``roughness (N, 1)`` in [0.01, 1]. Computed in float32 at least.
    """
    dtype = normal.dtype
    work = torch.float32 if dtype in (torch.float16, torch.bfloat16) else dtype
    normal, view, specular, roughness = (x.to(work) for x in (normal, view, specular, roughness))
    axis, amplitude = light.axis.to(work), light.amplitude.to(work)
    sharpness = lobes_at_points(light.sharpness.to(work).T, len(normal))
    cos_nv = torch.clamp((normal * view).sum(-1, keepdim=True), min=1e-6, max=1.0)
    tangent, across, sin_nv, view_b = _view_frame(normal, view, cos_nv)
    cos_nl, cos_vl, cos_tl, cos_bl = (_cosines(x, axis) for x in (normal, view, tangent, across))
    a, b = directional_albedo(cos_nv, roughness, brdf)
    tilt_a, kappa_a, tilt_b, kappa_b = lobe_moments(cos_nv, roughness, brdf)
    cosines = LightCosines(cos_nl, cos_vl, cos_tl, cos_nv, sin_nv, cos_bl, view_b)
    vis = None if visibility is None else visibility.to(work)
    part_a = _lit(_fitted_part(cosines, BrdfPart(tilt_a, kappa_a, a, "a"), roughness, sharpness, brdf), vis, amplitude)
    part_b = _lit(_fitted_part(cosines, BrdfPart(tilt_b, kappa_b, b, "b"), roughness, sharpness, brdf), vis, amplitude)
    return (specular * a * part_a + b * part_b).to(dtype)


def _outside_autocast(render: Callable) -> Callable:
    """``render`` with any enclosing autocast switched off: the renderer's cosines come from matrix
    products, which an autocast would round to bfloat16 (8 bits of mantissa: a lobe of sharpness
    1e3 then errs by a factor e^4, and the fitted lobe's correction, fed such cosines, reached
    1e28). Training opens its autocast around the networks and the shadows' shares alone; this
    keeps the renderer in its own precision whatever a caller opened."""

    @functools.wraps(render)
    def in_own_precision(normal: Tensor, *args, **kwargs) -> Shading:
        if not torch.is_autocast_enabled(normal.device.type):
            # no autocast to leave: no context either (under torch.compile an autocast context in
            # the graph bypasses AOTAutograd's cache, and every process traced the renderer's
            # joint graph again, 12 s)
            return render(normal, *args, **kwargs)
        with torch.autocast(normal.device.type, enabled=False):
            return render(normal, *args, **kwargs)

    return in_own_precision


@_outside_autocast
def shade_gltf(
    normal: Tensor,
    view: Tensor,
    base: Tensor,
    metallic: Tensor,
    roughness: Tensor,
    light: SGLight,
    lobe: str = "fitted",
    visibility: Tensor | None = None,
) -> Shading:
    """glTF 2.0's metallic-roughness BRDF under the SG light: ``base (N, 3)`` colour, ``metallic``
    and ``roughness (N, 1)``. The diffuse layer (:func:`diffuse_radiance_gltf`) of colour
    ``base (1 - metallic)``; the specular layer of ``F0 = lerp(0.04, base, metallic)``
    (:func:`gltf_f0`: Schlick's Fresnel is linear in ``F0``, so the dielectric and metal lobes of
    the specification's ``mix`` are one lobe) with GGX and the separable Smith-GGX, by ``lobe``:
    ``fitted`` (:func:`specular_radiance_fitted`) or ``split_sum``'s energy with TANGO's
    isotropic shape; the isotropic closed form is TANGO's own BRDF and has no glTF counterpart.
    ``visibility (N, K)``: each light lobe's visible share, scaling it in both layers (shadows)."""
    diffuse = diffuse_radiance_gltf(normal, view, base * (1.0 - metallic), light, visibility)
    f0 = gltf_f0(base, metallic)
    if lobe == "fitted":
        return Shading(diffuse, specular_radiance_fitted(normal, view, f0, roughness, light, "gltf", visibility))
    if lobe == "split_sum":
        return Shading(diffuse, specular_radiance_split_sum(normal, view, f0, roughness, light, "gltf", visibility))
    raise ValueError(f"the glTF BRDF has no {lobe!r} specular model; use fitted or split_sum")


@_outside_autocast
def shade(
    normal: Tensor,
    view: Tensor,
    albedo: Tensor,
    light: SGLight,
    specular: Tensor | None = None,
    roughness: Tensor | None = None,
    lobe: str = "isotropic",
    visibility: Tensor | None = None,
) -> Shading:
    """Diffuse and (when ``specular`` and ``roughness`` are given) specular radiance per point,
    the specular term by the model ``lobe`` names (``SPECULAR_LOBES``): ``isotropic``
    (:func:`specular_radiance`), ``split_sum`` (:func:`specular_radiance_split_sum`) or ``fitted``
    (:func:`specular_radiance_fitted`).

    A diffuse-only material (the ablation without specular/roughness) skips the specular
    computation entirely. ``visibility (N, K)``: each light lobe's visible share, scaling it in
    both terms (shadows, :mod:`stages.render.visibility`; None: unshadowed).
    """
    diffuse = diffuse_radiance(normal, albedo, light, visibility)
    if specular is None or roughness is None:
        return Shading(diffuse, torch.zeros_like(diffuse))
    if lobe == "isotropic":
        return Shading(diffuse, specular_radiance(normal, view, specular, roughness, light, visibility))
    if lobe == "split_sum":
        return Shading(diffuse, specular_radiance_split_sum(normal, view, specular, roughness, light, "tango", visibility))
    if lobe == "fitted":
        return Shading(diffuse, specular_radiance_fitted(normal, view, specular, roughness, light, "tango", visibility))
    raise ValueError(f"unknown specular lobe {lobe!r}; choose one of {', '.join(SPECULAR_LOBES)}")
