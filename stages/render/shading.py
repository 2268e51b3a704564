"""What every BRDF's shading shares: the SG environment light (the light component of kind
``sg``, :mod:`stages.render.light`), the per-point result, the viewer-facing normal, the
closed-form cosine-weighted integrals of SG lobes over the hemisphere (their plain reference and
the fused form without cancellation), the Lambertian diffuse term (TANGO Sec. 3.2), the frame of
the view across the normal, and the switch that keeps the renderer out of an enclosing autocast.

Each BRDF's own terms are its object in :mod:`stages.render.brdf` (``brdf.shade``), and the three
specular lobe models are their own modules: :mod:`stages.render.isotropic_lobe` (TANGO's closed
form), :mod:`stages.render.split_sum` and :mod:`stages.render.fitted_lobe`.

All functions are pure and batched over points ``N`` and light lobes ``K``. No shadows but the
visible shares a caller passes, and no interreflection (TANGO's stated limitation). Inputs are
assumed valid: unit normals facing the viewer (:func:`face_viewer`), albedo and specular colour in
[0, 1], roughness in [0.01, 1], positive light sharpness and amplitude; the networks'
parametrisation guarantees them.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch
from torch import Tensor

from .sg import (
    COS_LAMBDA,
    COS_MU,
    COS_OFFSET,
    hemisphere_t_difference,
    hemisphere_terms,
    sg_hemisphere_integral,
    sg_integral,
    sg_product,
)

#: Schlick's Fresnel ``F0 + (1 - F0) (1 - cos)^FRESNEL_POWER``
FRESNEL_POWER = 5


@dataclass(frozen=True)
class SGLight:
    """``K`` SG lobes: ``axis (K, 3)`` unit, ``sharpness (K, 1) > 0``, ``amplitude (K, C) >= 0``
    with ``C`` 1 (monochrome) or 3 (RGB).

    The light component of kind ``sg`` (:class:`~stages.render.light.LightComponent`): it shades
    by the BRDF's closed forms (:meth:`shade`, :meth:`stages.render.brdf.Brdf.shade`), its
    visibility input each lobe's visible share ``(N, K)``."""

    axis: Tensor
    sharpness: Tensor
    amplitude: Tensor

    #: its kind's name (:mod:`stages.model.lights`)
    kind: ClassVar[str] = "sg"
    #: an asset draws it into its environment image
    in_environment: ClassVar[bool] = True

    @property
    def device(self) -> torch.device:
        return self.axis.device

    @property
    def lobes(self) -> int:
        """Its number of lobes ``K``."""
        return int(self.axis.shape[0])

    def distant_lights(self) -> list:
        """None: an asset carries the lobes in its environment image."""
        return []

    def shade(self, brdf, normal: Tensor, view: Tensor, material, lobe: str | None, visibility: Tensor | None) -> Shading:
        """``brdf.shade`` of ``material`` under these lobes, each scaled by its visible share
        ``visibility (N, K)`` (:meth:`stages.render.brdf.Brdf.shade`)."""
        return brdf.shade(normal, view, material, self, lobe, visibility)

    def energy(self) -> Tensor:
        """Its radiant energy per channel ``(C,)``: the sum of the lobes' sphere integrals
        (:func:`~stages.render.sg.sg_integral`)."""
        return sg_integral(self.sharpness, self.amplitude).sum(0)

    def describe(self) -> dict:
        """Its kind, lobes and energy per channel."""
        return {"kind": self.kind, "lobes": self.lobes, "energy": self.energy().tolist()}

    def arrays(self) -> dict[str, np.ndarray]:
        """``axis``, ``sharpness`` and ``amplitude`` as they are."""
        return {
            "axis": self.axis.cpu().numpy(),
            "sharpness": self.sharpness.cpu().numpy(),
            "amplitude": self.amplitude.cpu().numpy(),
        }

    def shadowed_by(self, shadows, index: Tensor | None) -> Tensor:
        """Each lobe's visible share ``(n, K)`` at the points ``index`` of ``shadows``
        (:meth:`stages.model.shadows.ShadowCache.shares`)."""
        return shadows.shares(self, index)

    def like(self, leaf: Callable[..., Tensor]) -> SGLight:
        """``K`` lobes from ``leaf``: normalised axes, sharpnesses of ``1 + leaf``, amplitudes."""
        axis, sharpness = leaf(self.lobes, 3), leaf(self.lobes, 1)
        amplitude = leaf(self.lobes, self.amplitude.shape[1])
        return SGLight(torch.nn.functional.normalize(axis, dim=-1), sharpness + 1.0, amplitude)

    def visibility_like(self, leaf: Callable[..., Tensor], points: int) -> Tensor:
        return leaf(points, self.lobes)

    def to(self, device) -> SGLight:
        return SGLight(self.axis.to(device), self.sharpness.to(device), self.amplitude.to(device))

    def detach(self) -> SGLight:
        return SGLight(self.axis.detach(), self.sharpness.detach(), self.amplitude.detach())

    def radiance(self, directions: Tensor) -> Tensor:
        """``L(w)`` at unit ``directions (..., 3)`` -> ``(..., C)``: the sum of the lobes, each
        ``exp(lam (w . xi - 1))`` with ``w . xi - 1 = -|w - xi|^2 / 2`` (for unit vectors): the
        difference ``w . xi - 1`` loses the angle below float32's 3.5e-4 radians, which a lobe of
        sharpness 1e5 (3e-3 radians wide) resolves, and its gradient was the large ``lam xi``
        whose part across ``w``, small near the axis, drowned in that vector's rounding (both 2%
        in float32; ``benchmarks/render/precision.py``)."""
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


def lobe_cosines(directions: Tensor, axis: Tensor) -> Tensor:
    """Cosines ``(N, K)`` of unit ``directions (N, 3)`` with the lobes' unit ``axis (K, 3)``, the
    product taken in float64 and returned in the directions' dtype: the axes' gradient, a sum over
    the points, then accumulates in float64 (see :func:`lobes_at_points`)."""
    return (directions.double() @ axis.double().T).to(directions.dtype)


def sum_over_lobes(per_lobe: Tensor, visibility: Tensor | None, amplitude: Tensor) -> Tensor:
    """Each point's light summed over the lobes ``(N, C)``: a per-lobe term ``(N, K)`` of unit
    amplitude, shadowed (:func:`shadowed`), times the lobes' amplitudes ``(K, C)``, the product
    taken in float64 and returned in the term's dtype."""
    return (shadowed(per_lobe, visibility).double() @ amplitude.double()).to(per_lobe.dtype)


def shadowed(per_lobe: Tensor, visibility: Tensor | None) -> Tensor:
    """A per-lobe term ``(N, K)`` (or ``(N, K, C)``) times each lobe's visible share ``(N, K)``
    (:func:`stages.render.visibility.lobe_visibility`; None: no shadows)."""
    if visibility is None:
        return per_lobe
    return per_lobe * (visibility if per_lobe.dim() == 2 else visibility[..., None])


def hemisphere_product_with_cosine(normal: Tensor, axis: Tensor, sharpness: Tensor, amplitude: Tensor) -> Tensor:
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
    per_lobe = hemisphere_product_with_cosine(n, light.axis[None], light.sharpness[None], light.amplitude[None])
    irradiance = shadowed(per_lobe, visibility).sum(1)  # (N, C)
    # the cosine fit dips to -0.006 at the horizon: clamp the (tiny) negative irradiance [Zhang21]
    return albedo / math.pi * torch.clamp(irradiance, min=0.0)


# ------------------------------------------------------------------------------ fused versions
# The light's amplitudes enter linearly, and every SG quantity the shading needs is a function of
# sharpnesses and of dot products between axes. The fused versions therefore work on (N, K)
# matrices of cosines obtained by matrix products, never on (N, K, 3) tensors, and apply the
# amplitudes with one final (N, K) @ (K, C) product. They are algebraically identical to the
# reference versions (the diffuse one above, the specular one in isotropic_lobe.py; tested to
# 1e-10 relative in float64; measured 6e-14) and several times faster. Those products, and the
# sharpnesses' broadcast to the points, are taken in float64 (lobe_cosines, sum_over_lobes,
# lobes_at_points): the light's gradient is a sum over the points whose terms cancel.


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


def product_terms(lam1: Tensor, lam2: Tensor, cos12: Tensor) -> tuple[Tensor, Tensor]:
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
    integral, as :func:`hemisphere_product_with_cosine`: the fit's two terms, ``COS_MU`` and
    ``COS_OFFSET`` times nearly equal integrals, subtracted as they stand (the plain reference
    of :func:`cosine_weighted_hemisphere`)."""
    cos_lam = torch.as_tensor(COS_LAMBDA, dtype=lam.dtype, device=lam.device)
    lam_q, log_q = product_terms(lam, cos_lam, cos_n)
    safe = torch.where(lam_q > 0, lam_q, torch.ones_like(lam_q))
    cos_qn = torch.where(lam_q > 0, (COS_LAMBDA + lam * cos_n) / safe, torch.ones_like(lam_q))
    first = COS_MU * torch.exp(log_amp + log_q) * sg_hemisphere_integral(lam_q, cos_qn.clamp(-1.0, 1.0))
    second = COS_OFFSET * torch.exp(log_amp) * sg_hemisphere_integral(lam, cos_n)
    return first - second


def cosine_weighted_hemisphere(lam: Tensor, cos_n: Tensor, log_amp: Tensor) -> Tensor:
    """:func:`cosine_weighted_hemisphere_reference` (the same function, exact algebra: equal to
    5e-11 in float64) without its cancellation. The fit's two terms are ``COS_MU`` and
    ``COS_OFFSET`` (32.7 and 31.7) times hemisphere integrals of nearly the same lobe (the light's,
    and its product with the cosine's broad lobe), so their difference, near the horizon a
    thousandth of either for a sharp lobe, kept float32's rounding of each times a thousand (the
    diffuse term's gradient erred by 1.5% there; ``benchmarks/render/precision.py``). With each integral
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
    lam_q, log_q = product_terms(lam, torch.as_tensor(COS_LAMBDA, dtype=lam.dtype, device=lam.device), c)
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
    # log_q + C = C (delta + C + 2 lam c) / (lam_q + lam + C) (product_terms' form, exact algebra)
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
    cos_n = lobe_cosines(normal, light.axis)  # (N, K)
    lam = lobes_at_points(light.sharpness.T, len(normal))
    per_lobe = cosine_weighted_hemisphere(lam, cos_n, torch.zeros_like(light.sharpness.T))
    irradiance = sum_over_lobes(per_lobe, visibility, light.amplitude)
    return albedo / math.pi * torch.clamp(irradiance, min=0.0)


def _view_tangent(normal: Tensor, view: Tensor, cos_nv: Tensor) -> tuple[Tensor, Tensor]:
    """The unit direction ``t (N, 3)`` of the view across the normal and the view's sine with it
    ``(N, 1)``: ``(v - (n.v) n) / sin``; at a normal view (sine below 1e-7), where the lobe's mean
    is the normal and any direction across it serves, ``n x e`` normalised for the coordinate axis
    ``e`` least aligned with ``n``, so that ``(n, t, n x t)`` stays a frame.

    ``v - (n.v) n`` is taken as ``(n x v) x n`` (equal for a unit ``n``): a cross product with ``n``
    is perpendicular to ``n`` to its own rounding, where the difference near a normal view keeps
    float32's rounding of ``n.v`` along ``n`` (at a sine of 1.3e-7 the "tangent" pointed mostly along
    the normal, and a horizon lobe's specular came out 13 times too dark in float32; found by
    ``benchmarks/render/precision.py``)."""
    tangent = torch.linalg.cross(torch.linalg.cross(normal, view, dim=-1), normal, dim=-1)
    sin_nv = torch.linalg.vector_norm(tangent, dim=-1, keepdim=True)
    pick = torch.nn.functional.one_hot(normal.abs().argmin(dim=-1), 3).to(normal.dtype)
    across = torch.nn.functional.normalize(torch.linalg.cross(normal, pick, dim=-1), dim=-1)
    degenerate = sin_nv <= 1e-7
    tangent = torch.where(degenerate, across, tangent / torch.where(degenerate, torch.ones_like(sin_nv), sin_nv))
    return tangent, sin_nv


def view_frame(normal: Tensor, view: Tensor, cos_nv: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The frame ``(n, t, n x t)`` of the view's tangent direction (:func:`_view_tangent`) as
    ``t, n x t (N, 3)``, and the view's components along them ``(N, 1)`` (its sine, and 0) as
    products with the frame, so that their gradient holds in every direction across ``n`` (at a
    normal view the sine's norm had none)."""
    tangent, _ = _view_tangent(normal, view, cos_nv)
    across = torch.linalg.cross(normal, tangent, dim=-1)
    return tangent, across, (view * tangent).sum(-1, keepdim=True), (view * across).sum(-1, keepdim=True)


def tangent_frame(n: Tensor) -> tuple[Tensor, Tensor]:
    """An orthonormal tangent frame ``t, b (N, 3)`` for unit normals ``n (N, 3)``, defined and
    smooth everywhere except across the plane ``n_z = 0`` where its sign convention flips
    (Duff et al. 2017, "Building an orthonormal basis, revisited", JCGT 6(1)); also the frame of a
    sun's disc (:mod:`stages.render.light.sun`). Exact; valid at
    both poles (``n = +-z``), unlike spherical angles, whose azimuth is undefined there."""
    x, y, z = n.unbind(-1)
    sign = torch.where(z >= 0, torch.ones_like(z), -torch.ones_like(z))
    a = -1.0 / (sign + z)
    b = x * y * a
    t = torch.stack([1.0 + sign * x * x * a, sign * b, -sign * x], dim=-1)
    bt = torch.stack([b, sign + y * y * a, -y], dim=-1)
    return t, bt


def in_own_precision(render: Callable[..., Shading], normal: Tensor, *args) -> Shading:
    """``render(normal, *args)`` with any enclosing autocast switched off: the renderer's cosines
    come from matrix products, which an autocast would round to bfloat16 (8 bits of mantissa: a lobe
    of sharpness 1e3 then errs by a factor e^4, and the fitted lobe's correction, fed such cosines,
    reached 1e28). Training opens its autocast around the networks and the shadows' shares alone;
    this keeps the renderer in its own precision whatever a caller opened
    (:meth:`stages.render.brdf.Brdf.shade`)."""
    if not torch.is_autocast_enabled(normal.device.type):
        # no autocast to leave: no context either (under torch.compile an autocast context in the
        # graph bypasses AOTAutograd's cache, and every process traced the renderer's joint graph
        # again, 12 s)
        return render(normal, *args)
    with torch.autocast(normal.device.type, enabled=False):
        return render(normal, *args)
