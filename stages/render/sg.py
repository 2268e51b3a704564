"""Spherical-Gaussian (SG) algebra as small pure functions on tensors.

An SG is ``G(v; xi, lam, mu) = mu * exp(lam * (v . xi - 1))`` with unit axis ``xi``, sharpness
``lam > 0`` and amplitude ``mu >= 0`` (one or more channels). Shapes broadcast: axes are
``(..., 3)``, sharpness ``(..., 1)``, amplitude ``(..., C)``. Functions assume valid inputs (unit
axes, positive sharpness); the networks' parametrisation guarantees them. Every delicate limit
(``lam -> 0``, ``lam -> inf``, opposite axes) is written in a stable form and tested at sharpness
1e-4 to 1e4 and beyond.

References:
  [Wang09] J. Wang, P. Ren, M. Gong, J. Snyder, B. Guo. All-frequency rendering of dynamic,
      spatially-varying reflectance. SIGGRAPH Asia 2009.
  [Meder18] J. Meder, B. Bruderlin. Hemispherical Gaussians for accurate light integration.
      ICCVG 2018.
  [Zhang21] K. Zhang, F. Luan, Q. Wang, K. Bala, N. Snavely. PhySG: inverse rendering with
      spherical Gaussians for physics-based material editing and relighting. CVPR 2021.
  [Chen22] Y. Chen, R. Chen, J. Lei, Y. Zhang, K. Jia. TANGO: text-driven photorealistic and
      robust 3D stylization via lighting decomposition. NeurIPS 2022.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

#: the SG fit of the clamped cosine used by TANGO [Meder18, Chen22 Sec. 3.2]:
#: max(v . n, 0) ~ COS_MU * exp(COS_LAMBDA (v . n - 1)) - COS_OFFSET, within 0.008 on the upper
#: hemisphere (tested; measured 0.0077 at v = n); its integrals are taken over the upper hemisphere only
COS_LAMBDA = 0.0315
COS_MU = 32.7080
COS_OFFSET = 31.7003

#: the half-vector map l = 2 (h . v) h - v stretches solid angle by d omega_l / d omega_h = 4 |h . v| [Wang09]
HALF_VECTOR_JACOBIAN = 4.0

#: below this sharpness, (1 - exp(-2 lam)) / lam is evaluated by its Taylor series
_SERIES_BELOW = 1e-3


def one_minus_exp_neg2x_over_x(x: Tensor) -> Tensor:
    """``(1 - exp(-2x)) / x`` for ``x > 0``, accurate (float32 and float64) as ``x -> 0`` and ``inf``.

    Exact (to rounding): ``-expm1(-2x) / x`` for ``x >= 1e-3``, and the series
    ``2 - 2x + 4x^2/3 - 2x^3/3`` below (alternating: relative truncation error < 2x^4/15 < 1.4e-13
    there), which also keeps the derivative accurate where the quotient's derivative would cancel.
    Tested over ``x`` in [1e-8, 1e8]: within 2e-13 of ``-expm1(-2x) / x`` in float64, 3e-7 in float32.
    """
    small = x < _SERIES_BELOW
    xs = torch.where(small, x, torch.zeros_like(x))
    series = 2.0 - 2.0 * xs + (4.0 / 3.0) * xs * xs - (2.0 / 3.0) * xs * xs * xs
    xl = torch.where(small, torch.ones_like(x), x)
    exact = -torch.expm1(-2.0 * xl) / xl
    return torch.where(small, series, exact)


def sg_eval(v: Tensor, axis: Tensor, sharpness: Tensor, amplitude: Tensor) -> Tensor:
    """Evaluate ``mu exp(lam (v . xi - 1))`` at unit directions ``v (..., 3)``.

    Returns ``(..., C)``. Exact. Valid for any ``lam >= 0``; the exponent is ``<= 0`` for unit
    vectors, so nothing overflows.
    """
    cos = (v * axis).sum(-1, keepdim=True)
    return amplitude * torch.exp(sharpness * (cos - 1.0))


def sg_product(
    axis1: Tensor,
    sharpness1: Tensor,
    amplitude1: Tensor,
    axis2: Tensor,
    sharpness2: Tensor,
    amplitude2: Tensor,
) -> tuple[Tensor, Tensor, Tensor]:
    """The product of two SGs, itself an SG [Wang09, Chen22 eq. 4].

    ``u = lam1 xi1 + lam2 xi2``, ``lam = |u|``, ``xi = u / lam``,
    ``mu = mu1 mu2 exp(lam - lam1 - lam2)``. Exact. The exponent is ``<= 0`` (triangle
    inequality), so the amplitude never overflows, and it is evaluated as
    ``-lam1 lam2 |xi1 - xi2|^2 / (lam + lam1 + lam2)``, which keeps full relative precision when
    both lobes are sharp and nearly aligned (the specular case). When the axes are opposite and the
    sharpnesses equal, ``lam = 0`` and the product is the constant ``mu``: the axis is then
    irrelevant and returned as the zero vector (evaluating the result is still exact).

    Returns ``axis (..., 3)``, ``sharpness (..., 1)``, ``amplitude (..., C)``.
    """
    u = sharpness1 * axis1 + sharpness2 * axis2
    lam = torch.linalg.vector_norm(u, dim=-1, keepdim=True)
    safe = torch.where(lam > 0, lam, torch.ones_like(lam))
    axis = torch.where(lam > 0, u / safe, torch.zeros_like(u))
    # lam - lam1 - lam2 = (lam^2 - (lam1 + lam2)^2) / (lam + lam1 + lam2)
    #                   = -lam1 lam2 |xi1 - xi2|^2 / (lam + lam1 + lam2),
    # free of the cancellation that loses all digits for sharp, nearly aligned lobes in float32
    d = axis1 - axis2
    exponent = -sharpness1 * sharpness2 * (d * d).sum(-1, keepdim=True) / (lam + sharpness1 + sharpness2)
    amplitude = amplitude1 * amplitude2 * torch.exp(exponent)
    return axis, lam, amplitude


def sg_integral(sharpness: Tensor, amplitude: Tensor) -> Tensor:
    """Integral of an SG over the whole sphere: ``2 pi mu / lam (1 - exp(-2 lam))`` [Chen22 eq. 5].

    Exact; stable for ``lam`` from 0 (limit ``4 pi mu``) to infinity (``2 pi mu / lam``), see
    :func:`one_minus_exp_neg2x_over_x`. ``sharpness (..., 1)``, ``amplitude (..., C)`` ->
    ``(..., C)``.

    Note: TANGO's "light energy" (its eq. 7) divides by ``(1 - exp(-2 lam))`` where the integral
    multiplies; this function follows the mathematics, and the light's energy uses it.
    """
    return 2.0 * math.pi * amplitude * one_minus_exp_neg2x_over_x(sharpness)


def sg_inner_product(
    axis1: Tensor,
    sharpness1: Tensor,
    amplitude1: Tensor,
    axis2: Tensor,
    sharpness2: Tensor,
    amplitude2: Tensor,
) -> Tensor:
    """Integral over the sphere of the product of two SGs [Wang09]. Exact.

    ``2 pi mu1 mu2 exp(lam_m - lam1 - lam2) (1 - exp(-2 lam_m)) / lam_m`` with
    ``lam_m = |lam1 xi1 + lam2 xi2|``; stable as ``lam_m -> 0`` (opposite axes). ``(..., C)``.
    """
    _, lam, mu = sg_product(axis1, sharpness1, amplitude1, axis2, sharpness2, amplitude2)
    return 2.0 * math.pi * mu * one_minus_exp_neg2x_over_x(lam)


#: Meder & Bruderlin's ``t(lam) = sqrt(lam) (T_A lam^2 + T_B lam) / (lam^2 + T_D lam + T_E)``
T_A, T_B, T_D, T_E = 1.6988, 10.8438, 6.2201, 10.2415


def _hemisphere_t(sharpness: Tensor) -> Tensor:
    """Meder & Bruderlin's fitted ``t(lam) = sqrt(lam) (1.6988 lam^2 + 10.8438 lam) /
    (lam^2 + 6.2201 lam + 10.2415)`` (their rational form multiplied through by ``lam^2``, so it
    has no ``1 / lam`` and is finite down to ``lam = 0``; in float32 ``sqrt(lam) lam^2`` overflows
    above ``lam ~ 2e15``, far beyond the renderer's sharpest lobe, ~1e11)."""
    lam = sharpness
    root = torch.sqrt(torch.clamp(lam, min=torch.finfo(lam.dtype).tiny))  # (sqrt's derivative finite at lam = 0)
    return root * (T_A * lam * lam + T_B * lam) / (lam * lam + T_D * lam + T_E)


def hemisphere_t_difference(lam: Tensor, lam_q: Tensor, delta: Tensor) -> Tensor:
    """``t(lam_q) - t(lam)`` of :func:`_hemisphere_t` for ``delta = lam_q - lam`` given without
    cancellation: the square roots' difference as ``delta / (sqrt(lam_q) + sqrt(lam))`` and the
    rational part's by the divided difference ``N(x) D(y) - N(y) D(x) = (x - y) ((T_A T_D - T_B) x y
    + T_A T_E (x + y) + T_B T_E)`` (exact algebra). Any matching shapes."""
    tiny = torch.finfo(lam.dtype).tiny
    root, root_q = torch.sqrt(torch.clamp(lam, min=tiny)), torch.sqrt(torch.clamp(lam_q, min=tiny))
    den, den_q = lam * lam + T_D * lam + T_E, lam_q * lam_q + T_D * lam_q + T_E
    rational_q = (T_A * lam_q * lam_q + T_B * lam_q) / den_q
    rational_diff = delta * ((T_A * T_D - T_B) * lam * lam_q + T_A * T_E * (lam + lam_q) + T_B * T_E) / (den * den_q)
    return delta / (root + root_q) * rational_q + root * rational_diff


def hemisphere_terms(sharpness: Tensor, cos_beta: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """:func:`sg_hemisphere_integral` ``= a + b p s`` in its factors, for callers that take
    differences of two integrals: ``a = A_u e^-lam`` (the opposite hemisphere's share),
    ``b = A_u (1 - e^-lam)``, ``p = (1 - e^-(t (1 + c))) / (1 - e^-t)``, ``p - 1 = (e^-t -
    e^-(t (1 + c))) / (1 - e^-t)`` on its own (for a sharp lobe ``p`` is 1 to ``e^-t`` and the
    difference of two ``p`` as they stand is float32's rounding of 1: 3e-5 of the cosine-weighted
    integral at sharpness 50), the logistic ``s = sigma(t c)`` and ``t = t(lam)`` (last). The
    exponentials' difference is ``e^-t (1 - e^-(t c))`` above the horizon and ``-e^-(t (1 + c))
    (1 - e^(t c))`` below it, each by ``expm1`` of a negative number and on its own side's ``c``
    (no exponential overflows, and neither branch's gradient is inf times 0). Any matching shapes."""
    lam, c = sharpness, cos_beta
    t = _hemisphere_t(lam)
    a_u = math.pi * one_minus_exp_neg2x_over_x(0.5 * lam)
    den = torch.clamp(-torch.expm1(-t), min=torch.finfo(t.dtype).tiny)
    p = -torch.expm1(-t * (1.0 + c)) / den
    above = c >= 0
    c_up, c_down = torch.where(above, c, torch.zeros_like(c)), torch.where(above, torch.zeros_like(c), c)
    up = torch.exp(-t) * -torch.expm1(-t * c_up)
    down = torch.exp(-t * (1.0 + c_down)) * torch.expm1(t * c_down)
    p_minus_one = torch.where(above, up, down) / den
    return a_u * torch.exp(-lam), a_u * -torch.expm1(-lam), p, p_minus_one, torch.sigmoid(t * c), t


def sg_hemisphere_integral(sharpness: Tensor, cos_beta: Tensor) -> Tensor:
    """Approximate integral of a unit-amplitude SG over the hemisphere ``{v : v . n >= 0}``.

    ``cos_beta = xi . n`` is the cosine between the lobe axis and the hemisphere's pole. The
    approximation of [Meder18] as used by PhySG [Zhang21]: the integral interpolates between the
    integrals over the hemisphere centred on the lobe, ``A_u = 2 pi (1 - exp(-lam)) / lam``, and
    over the opposite one, ``A_b = exp(-lam) A_u``, with the smooth step

        s = (1 - exp(-t (1 + c))) / ((1 - exp(-t)) (1 + exp(-t c))),   t = t(lam) (fitted),

    written with ``expm1`` and rescaled so that no exponential of a positive number is taken
    (PhySG's two branches for ``c >= 0`` and ``c < 0`` are the same function). Exact at
    ``c = -1, 0, 1`` (0, half and all of ``A_u + A_b``); elsewhere the error is measured against
    quadrature in ``tests/render/test_sg.py``: at most 1.5% of the full-sphere integral over
    ``lam`` in [1e-4, 1e4] (tested; measured 1.1%). Finite values and gradients for ``lam`` in
    [1e-6, 1e18] in float64 and [1e-6, 1e15] in float32 (tested).

    ``sharpness (..., 1) >= 0``, ``cos_beta (..., 1)`` in [-1, 1] -> ``(..., 1)``. At ``lam = 0`` the
    lobe is 1 everywhere and the integral is ``2 pi`` whatever the step ``s``, whose denominator is
    held at the dtype's smallest normal there instead of dividing 0 by 0.
    """
    lam = sharpness
    t = _hemisphere_t(lam)
    c = cos_beta
    # exp(t min(c, 0)) and exp(-t max(c, 0)), both <= 1, by one branch each: two clamps would both
    # pass the gradient at c = 0 exactly (a lobe on the horizon) and double the step's part in it
    below = c < 0
    lo = torch.exp(t * torch.where(below, c, torch.zeros_like(c)))
    hi = torch.exp(-t * torch.where(below, torch.zeros_like(c), c))
    den = torch.clamp(-torch.expm1(-t), min=torch.finfo(t.dtype).tiny)
    s = -torch.expm1(-t * (1.0 + c)) * lo / (den * (lo + hi))
    a_u = math.pi * one_minus_exp_neg2x_over_x(0.5 * lam)  # 2 pi (1 - exp(-lam)) / lam
    return a_u * (s + torch.exp(-lam) * (1.0 - s))


def warp_ndf_to_light(
    normal: Tensor, view: Tensor, ndf_sharpness: Tensor, ndf_amplitude: Tensor, cos_nv: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Spherical warp of an SG normal distribution ``D(h)`` centred on ``n`` into the light
    domain [Wang09 Sec. 4.2, Zhang21]: the lobe moves to the mirror direction
    ``r = 2 (v . n) n - v``, its sharpness becomes ``lam / (4 |h . v|)`` (``HALF_VECTOR_JACOBIAN``)
    with ``h = n`` at the lobe centre, and its amplitude is unchanged. Approximate (exact at the lobe
    centre; the warp is the first-order Jacobian of ``h -> l``, made isotropic): the warped lobe's
    integral matches that of ``D(h(l))`` over ``l`` to within ``2 / lam`` relative for ``lam >= 32``
    and ``n . v`` in [0.3, 1] (tested; measured ``1 / lam``).

    ``normal, view (..., 3)`` unit (``view`` points from the surface to the eye),
    ``ndf_sharpness (..., 1)``, ``ndf_amplitude (..., C)``, ``cos_nv = n . v (..., 1)`` in
    ``(0, 1]`` (the caller keeps it positive, see
    :func:`stages.render.shading.face_viewer`). Returns the warped SG.
    """
    axis = 2.0 * cos_nv * normal - view  # unit length for unit n and v
    return axis, ndf_sharpness / (HALF_VECTOR_JACOBIAN * cos_nv), ndf_amplitude
