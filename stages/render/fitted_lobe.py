"""The fitted specular lobe (``optimize.specular_lobe: fitted``): the BRDF's exact energy and a
vMF lobe fitted to its tabulated moments per Fresnel part (:mod:`stages.render.specular_albedo`),
corrected by the BRDF itself at each light lobe (:func:`specular_radiance_fitted`). The BRDF
enters through its object (:class:`~stages.render.brdf.Brdf`): its table and its
``log_ndf_times_visibility``.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, NamedTuple

import torch
from torch import Tensor

from .shading import FRESNEL_POWER, SGLight, lobe_cosines, lobes_at_points, product_terms, sum_over_lobes, view_frame
from .specular_albedo import directional_albedo, lobe_moments

if TYPE_CHECKING:  # (the BRDFs' package imports this module)
    from .brdf.base import Brdf

#: below this log-ratio the fitted lobe's correction is zero to float precision (exp(-80) ~ 2e-35)
_LOG_RATIO_FLOOR = -80.0
#: the width of the fitted lobe's soft horizon (:func:`log_soft_cosine`), in cosine
HORIZON_SOFTNESS = 1e-3


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


def _fitted_part(c: LightCosines, part: BrdfPart, roughness: Tensor, sharpness: Tensor, brdf: Brdf) -> Tensor:
    """``int f_part(l) (n . l) G_k(l) dl / energy`` for one part of the BRDF and every unit light
    lobe ``k`` -> ``(N, K)``; see :func:`specular_radiance_fitted`. ``roughness (N, 1)``,
    ``sharpness (N, K)`` (:func:`~stages.render.shading.lobes_at_points`)."""
    cos_nl, cos_tl, cos_nv = c.nl, c.tl, c.nv
    tilt, kappa, energy, fresnel_part = part
    mean = _lobe_mean(c, tilt)
    cos_t, sin_t, mean_b = mean.cos_t, mean.sin_t, mean.b
    cos_ml = cos_t * cos_nl - sin_t * cos_tl + mean_b * c.bl
    lam_p, log_amp = product_terms(kappa, sharpness, cos_ml)
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
        brdf.log_ndf_times_visibility(one_minus_nh, nl_c, cos_nv, roughness) + log_fres + log_soft_cosine(nl) - torch.log(energy)
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
    brdf: Brdf,
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
    the BRDF for ``n . v`` 0.05 to 1 and roughness 0.05 to 1 (``benchmarks/render/specular_lobes.py``):
    within 5% for smooth lights (32 lobes of sharpness 5; tested against Monte Carlo), 3.8% for the
    studio light, 3.7% for a sun of sharpness 300 away from the mirror direction, 8.9% for 32 lobes
    of sharpness 30; a sun reflected at the mirror direction of a lobe of its own width (roughness
    0.2 to 0.3) errs by up to 30%.

    ``brdf``: whose microfacet lobe (:meth:`~stages.render.brdf.Brdf.log_ndf_times_visibility`:
    TANGO's SG NDF and Smith-Schlick, or glTF's GGX and separable Smith-GGX), with its own table
    of energies and moments.

    ``normal, view (N, 3)`` unit with ``n . v > 0`` (:func:`~stages.render.shading.face_viewer`), ``specular (N, 3)`` in
    [0, 1], ``roughness (N, 1)`` in [0.01, 1]. Computed in float32 at least.
    """
    dtype = normal.dtype
    work = torch.float32 if dtype in (torch.float16, torch.bfloat16) else dtype
    normal, view, specular, roughness = (x.to(work) for x in (normal, view, specular, roughness))
    axis, amplitude = light.axis.to(work), light.amplitude.to(work)
    sharpness = lobes_at_points(light.sharpness.to(work).T, len(normal))
    cos_nv = torch.clamp((normal * view).sum(-1, keepdim=True), min=1e-6, max=1.0)
    tangent, across, sin_nv, view_b = view_frame(normal, view, cos_nv)
    cos_nl, cos_vl, cos_tl, cos_bl = (lobe_cosines(x, axis) for x in (normal, view, tangent, across))
    a, b = directional_albedo(cos_nv, roughness, brdf)
    tilt_a, kappa_a, tilt_b, kappa_b = lobe_moments(cos_nv, roughness, brdf)
    cosines = LightCosines(cos_nl, cos_vl, cos_tl, cos_nv, sin_nv, cos_bl, view_b)
    vis = None if visibility is None else visibility.to(work)
    part_a = sum_over_lobes(_fitted_part(cosines, BrdfPart(tilt_a, kappa_a, a, "a"), roughness, sharpness, brdf), vis, amplitude)
    part_b = sum_over_lobes(_fitted_part(cosines, BrdfPart(tilt_b, kappa_b, b, "b"), roughness, sharpness, brdf), vis, amplitude)
    return (specular * a * part_a + b * part_b).to(dtype)
