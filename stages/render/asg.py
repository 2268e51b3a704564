"""Anisotropic spherical Gaussians (ASG) [Xu13] as small pure functions on tensors: the
reflection lobe of an SG normal distribution, warped into the light domain without making it
isotropic, and its inner product with an SG light lobe.

An ASG is ``G(v) = c * S(v . z) * exp(-bx (v . x)^2 - by (v . y)^2)`` with an orthonormal frame
``x, y, z`` (``z`` the lobe's centre), bandwidths ``bx, by > 0`` and amplitude ``c >= 0``;
``S(t) = max(t, 0)``. Shapes broadcast: frame vectors ``(..., 3)``, bandwidths ``(..., 1)``,
amplitudes ``(..., C)``.

The smooth term ``S`` is the Jacobian of the orthographic projection onto the disk at ``z``: with
``s = v . x`` and ``t = v . y``, ``dv = ds dt / (v . z)`` on the upper hemisphere, so an ASG's
integrals are integrals of a plane Gaussian ``exp(-bx s^2 - by t^2)`` over the unit disk, exactly.
The closed forms below extend that disk to the plane (the Gaussian's mass outside the disk is at
most ``exp(-min(bx, by))`` of the total) and, for the inner product, take the light's SG to the
same plane at second order; both are exact as the bandwidths grow and are tested against
quadrature of the definitions.

References:
  [Xu13] K. Xu, W.-L. Sun, Z. Dong, D.-Y. Zhao, R.-D. Wu, S.-M. Hu. Anisotropic spherical
      Gaussians. ACM TOG 32(6) (SIGGRAPH Asia 2013).
  [Wang09] J. Wang, P. Ren, M. Gong, J. Snyder, B. Guo. All-frequency rendering of dynamic,
      spatially-varying reflectance. SIGGRAPH Asia 2009 (the isotropic warp this one refines).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

#: below this length, the in-plane direction of a reflection frame is undefined (n parallel to r);
#: the lobe is isotropic there (equal bandwidths), so any frame gives the same lobe
_DEGENERATE_PLANE = 1e-6


@dataclass(frozen=True)
class ASG:
    """An ASG lobe (see the module docstring): ``x, y, z (..., 3)`` orthonormal, ``bx, by (..., 1)``
    positive, ``amplitude (..., C)`` non-negative."""

    x: Tensor
    y: Tensor
    z: Tensor
    bx: Tensor
    by: Tensor
    amplitude: Tensor


def asg_eval(lobe: ASG, v: Tensor) -> Tensor:
    """``c max(v . z, 0) exp(-bx (v . x)^2 - by (v . y)^2)`` at unit directions ``v (..., 3)``
    -> ``(..., C)``. Exact."""
    s = (v * lobe.x).sum(-1, keepdim=True)
    t = (v * lobe.y).sum(-1, keepdim=True)
    smooth = torch.clamp((v * lobe.z).sum(-1, keepdim=True), min=0.0)
    return lobe.amplitude * smooth * torch.exp(-lobe.bx * s * s - lobe.by * t * t)


def asg_integral(lobe: ASG) -> Tensor:
    """``int G(v) dv ~ c pi / sqrt(bx by)`` -> ``(..., C)`` [Xu13 eq. 6]. The exact value is the
    plane Gaussian's integral over the unit disk, so this overestimates by the Gaussian's mass
    outside the disk: at most a fraction ``exp(-min(bx, by))`` (tested against quadrature)."""
    return lobe.amplitude * (math.pi * torch.rsqrt(lobe.bx * lobe.by))


def asg_sg_inner_product(lobe: ASG, axis: Tensor, sharpness: Tensor, amplitude: Tensor) -> Tensor:
    """``int G(v) a exp(nu (v . p - 1)) dv`` of an ASG with an SG of unit ``axis p (..., 3)``,
    ``sharpness nu (..., 1) >= 0`` and ``amplitude a (..., C)`` -> ``(..., C)``.

    Closed form after [Xu13 Sec. 4.3]: the SG's exponent is ``-nu |v - p|^2 / 2`` exactly; in the
    ASG's disk coordinates ``(s, t)`` it is taken as ``-nu ((s - p_x)^2 + (t - p_y)^2 +
    (1 - p_z)^2) / 2`` (``v . z ~ 1`` where the ASG lives) and the Gaussian integral over the plane
    gives

        c a pi / sqrt((bx + nu/2)(by + nu/2))
            * exp(-bx' p_x^2 - by' p_y^2 - nu (1 - p_z)^2 / 2),  bx' = bx nu / (2 bx + nu)

    (and likewise ``by'``), with ``p_x = p . x`` etc. Every exponent is non-positive, so it is
    finite for any bandwidths and sharpness (no cancellation as ``nu -> 0`` or ``bx -> inf``).
    Exact in the limits: ``nu -> 0`` gives :func:`asg_integral` times ``a``; ``bx, by -> inf``
    gives the integral times the SG at ``z``. Between them, approximate: within 2% of quadrature
    of the definitions where the light meets the ASG near its centre (bandwidths 10 to 1000,
    sharpness 0.5 to 30, light axis within 0.3 rad of ``z``; tested). It falls short for a light
    sharper than the ASG and away from its centre, where the product lives near the light's axis
    rather than ``z`` (measured: -58% for sharpness 30 at 0.8 rad from a lobe of bandwidths 10).
    """
    half = 0.5 * sharpness
    px = (axis * lobe.x).sum(-1, keepdim=True)
    py = (axis * lobe.y).sum(-1, keepdim=True)
    pz = (axis * lobe.z).sum(-1, keepdim=True)
    bx_eff = lobe.bx * half / (lobe.bx + half)
    by_eff = lobe.by * half / (lobe.by + half)
    exponent = -bx_eff * px * px - by_eff * py * py - half * (1.0 - pz) ** 2
    scale = math.pi * torch.rsqrt((lobe.bx + half) * (lobe.by + half))
    return lobe.amplitude * amplitude * scale * torch.exp(exponent)


def reflection_frame(normal: Tensor, view: Tensor, cos_nv: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The frame of the mirror lobe: ``z = r = 2 (n . v) n - v``, ``x`` in the plane of ``n`` and
    ``v`` (perpendicular to ``r``, towards ``n``), ``y = z x x``. ``normal, view (..., 3)`` unit,
    ``cos_nv (..., 1)`` in ``(0, 1]``.

    At normal incidence (``n = v = r``) the plane is undefined; a frame built from ``r`` alone
    (Frisvad's, in the branch-free form of Duff et al. 2017) is used below a plane component of
    ``1e-6``, where the warped lobe is isotropic to within that amount, so the choice does not
    change it. Both branches are computed with safe denominators (finite gradients everywhere).
    """
    r = 2.0 * cos_nv * normal - view
    in_plane = normal - (normal * r).sum(-1, keepdim=True) * r
    length = torch.linalg.vector_norm(in_plane, dim=-1, keepdim=True)
    degenerate = length < _DEGENERATE_PLANE
    x_plane = in_plane / torch.where(degenerate, torch.ones_like(length), length)
    # Duff et al. 2017: an orthonormal basis from r alone, continuous except at r_z = -1 exactly
    sign = torch.where(r[..., 2:3] >= 0, torch.ones_like(length), -torch.ones_like(length))
    a = -1.0 / (sign + r[..., 2:3])
    b = r[..., 0:1] * r[..., 1:2] * a
    x_any = torch.cat([1.0 + sign * r[..., 0:1] ** 2 * a, sign * b, -sign * r[..., 0:1]], dim=-1)
    x = torch.where(degenerate, x_any, x_plane)
    y = torch.linalg.cross(r, x)
    return x, y, r


def warp_ndf_to_asg(normal: Tensor, view: Tensor, ndf_sharpness: Tensor, ndf_amplitude: Tensor, cos_nv: Tensor) -> ASG:
    """The SG normal distribution ``D(h) = mu exp(lam (h . n - 1))`` seen in the light domain,
    ``D(h(l))`` with ``h(l) = normalize(l + v)``, as an ASG [Xu13 Sec. 5.2].

    Derivation: with ``v`` at angle ``theta`` from ``n`` (``cos theta = n . v``), a half vector
    tilted by small angles ``a`` (in the plane of ``n`` and ``v``) and ``b`` (out of it) reflects
    to ``l = 2 (v . h) h - v``, which moves from ``r`` by ``2a`` in the plane and by
    ``2 b cos theta`` out of it (the product, ``4 cos theta``, is the half-vector Jacobian
    [Wang09]). ``D ~ mu exp(-lam (a^2 + b^2) / 2)`` therefore becomes an ASG at ``r`` with
    bandwidths ``bx = lam / 8`` in the plane and ``by = lam / (8 cos^2 theta)`` out of it, and the
    same amplitude. The isotropic warp's sharpness ``lam / (4 cos theta)`` is twice their geometric
    mean: it matches the lobe's integral and is wrong in both directions near grazing, where the
    reflection stretches along the plane (tested: the ASG follows ``D(h(l))`` far closer there).

    ``normal, view (..., 3)`` unit, ``ndf_sharpness (..., 1) > 0``, ``ndf_amplitude (..., C)``,
    ``cos_nv (..., 1)`` in ``(0, 1]`` (kept positive by :func:`stages.render.shading.face_viewer`).
    """
    x, y, z = reflection_frame(normal, view, cos_nv)
    bx = ndf_sharpness / 8.0
    by = ndf_sharpness / (8.0 * cos_nv * cos_nv)
    return ASG(x, y, z, bx, by, ndf_amplitude)
