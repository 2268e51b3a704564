"""glTF 2.0's metallic-roughness BRDF (``optimize.brdf: gltf``): base colour, metallic and
roughness (``alpha = r^2``), the specification's GGX normal distribution and separable Smith-GGX
visibility, Schlick's Fresnel of ``F0 = lerp(0.04, base, metallic)``, and a diffuse layer of colour
``base (1 - metallic)`` that gives way to the specular one (glTF 2.0, Appendix B). Its specular
term by the ``fitted`` or ``split_sum`` lobe model with its own table
(``data/specular_albedo_gltf.npz``); TANGO's isotropic closed form is TANGO's own BRDF and has no
glTF counterpart. Its assets: USD's metallic workflow, glTF's core material with no extension.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from ..fitted_lobe import specular_radiance_fitted
from ..sg import COS_LAMBDA
from ..shading import (
    SGLight,
    Shading,
    cosine_weighted_hemisphere,
    lobe_cosines,
    lobes_at_points,
    product_terms,
    sum_over_lobes,
    view_frame,
)
from ..specular_albedo import DATA_DIR
from ..split_sum import specular_radiance_split_sum
from .base import Brdf, Channels

#: glTF 2.0's dielectric reflectance at normal incidence (IOR 1.5)
GLTF_DIELECTRIC_F0 = 0.04


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
    along the normal: float32's value was 150 times too small there; ``benchmarks/render/precision.py``).
    Held at 1e-6 where ``q = -v`` (``h`` undefined; the square root's derivative infinite).
    ``cos_n (N, K)``: the lobes' cosines with the normal; ``lam (N, K)``: their sharpnesses at the
    points (:func:`~stages.render.shading.lobes_at_points`)."""
    tangent, across, v_t, v_b = view_frame(normal, view, cos_nv)
    cos_t, cos_b = lobe_cosines(tangent, light.axis), lobe_cosines(across, light.axis)
    # lam_q is positive (held at its floor by product_terms)
    lam_q, _ = product_terms(lam, torch.as_tensor(COS_LAMBDA, dtype=lam.dtype, device=lam.device), cos_n)
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

    Per light lobe the cosine-weighted integral is
    :func:`~stages.render.shading.diffuse_radiance`'s closed form, and the
    Fresnel weight ``1 - F`` is taken at the half vector of ``v`` and the axis of that lobe's product
    with the clamped cosine's SG (where the integrand sits): exact for a lobe far sharper than the
    cosine (a sun), and for a broad one the weight at ``h`` between ``v`` and ``n``. Tested against
    Monte Carlo of the specification's formula. ``visibility (N, K)``: each lobe's visible share."""
    cos_nv = (normal * view).sum(-1, keepdim=True)
    cos_n = lobe_cosines(normal, light.axis)  # (N, K)
    lam = lobes_at_points(light.sharpness.T, len(normal))
    per_lobe = cosine_weighted_hemisphere(lam, cos_n, torch.zeros_like(light.sharpness.T))
    weight = (1.0 - GLTF_DIELECTRIC_F0) * _one_minus_schlick(_diffuse_half_vector_cosine(normal, view, cos_nv, cos_n, lam, light))
    irradiance = sum_over_lobes(per_lobe * weight, visibility, light.amplitude)
    return diffuse_color / math.pi * torch.clamp(irradiance, min=0.0)


def log_ndf_times_visibility(one_minus_nh: Tensor, nl: Tensor, nv: Tensor, roughness: Tensor) -> Tensor:
    """``log(D(h) G(l, v) / (4 (n.l)(n.v)))`` of glTF's BRDF from ``1 - n.h``, ``n.l`` and ``n.v``
    (broadcasting): GGX ``alpha^2 / (pi ((n.h)^2 (alpha^2 - 1) + 1)^2)`` and the separable
    Smith-GGX visibility ``1 / ((n.l + sqrt(alpha^2 + (1 - alpha^2) (n.l)^2)) (n.v + sqrt(...)))``
    with ``alpha = r^2`` (glTF 2.0, Appendix B.3.2), the GGX denominator written ``alpha^2 (n.h)^2
    + (1 - n.h)(1 + n.h)`` so that a sharp lobe keeps its precision near its peak."""
    a2 = roughness**4
    nh = 1.0 - one_minus_nh
    denom = a2 * nh * nh + one_minus_nh * (2.0 - one_minus_nh)
    vis = (nl + torch.sqrt(a2 + (1.0 - a2) * nl * nl)) * (nv + torch.sqrt(a2 + (1.0 - a2) * nv * nv))
    return torch.log(a2 / math.pi) - 2.0 * torch.log(denom) - torch.log(vis)


def ndf_quadrature(x: np.ndarray, w: np.ndarray, roughness: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Half vectors for the table's quadrature (:meth:`~stages.render.brdf.Brdf.ndf_quadrature`):
    with GGX of ``alpha = r^2``, ``u = tan^2 / (alpha^2 + tan^2)`` in [0, 1) is the distribution's
    own cumulative of ``D cos``, so ``D(h) dh = du dphi / (2 pi cos theta_h)`` with ``cos^2 = (1 -
    u) / (1 + (alpha^2 - 1) u)``: uniform in ``u``, every part of the long tail weighted as it
    counts."""
    a2 = roughness**4
    u = 0.5 * (x + 1.0)
    wu = 0.5 * w
    cos2 = (1.0 - u) / (1.0 + (a2 - 1.0) * u)
    cos_t = np.sqrt(cos2)
    sin_t = np.sqrt(np.clip(a2 * u / (1.0 + (a2 - 1.0) * u), 0.0, None))  # 1 - cos^2 without cancellation
    return cos_t, sin_t, wu / cos_t


def shadowing(nl: np.ndarray, c: float, roughness: float) -> np.ndarray:
    """``G(l, v) / (n . v)`` for ``n.l`` values ``nl`` (> 0) and ``n.v = c``: the separable
    Smith-GGX ``G1(x) = 2 x / (x + sqrt(alpha^2 + (1 - alpha^2) x^2))`` (glTF 2.0, Appendix B)."""
    a2 = roughness**4
    g1_l = 2.0 * nl / (nl + np.sqrt(a2 + (1.0 - a2) * nl * nl))
    return g1_l * 2.0 / (c + math.sqrt(a2 + (1.0 - a2) * c * c))


class Gltf(Brdf):
    """glTF 2.0's metallic-roughness BRDF: base colour, metallic and roughness."""

    name = "gltf"
    widths = (3, 1, 1)
    table_path = DATA_DIR / "specular_albedo_gltf.npz"

    def channels(self, colour: Tensor, specular: Tensor | None, roughness: Tensor | None) -> dict[str, Tensor | None]:
        """What the material was made of, ``base (N, 3)`` and ``metallic (N, 1)``, and its TANGO
        equivalents, ``albedo = base (1 - metallic)`` and ``specular = lerp(0.04, base, metallic)``
        (:func:`gltf_f0`), so that figures and material errors read both models alike."""
        if specular is None or roughness is None:
            raise ValueError("the glTF BRDF needs its metallic and roughness heads (specular: true)")
        return {
            "albedo": colour * (1.0 - specular),
            "specular": gltf_f0(colour, specular),
            "roughness": roughness,
            "base": colour,
            "metallic": specular,
        }

    def head_start(self, value: float) -> Tensor:
        """The metallic ``value``, held inside (0, 1) by 1e-3 (a sigmoid reaches 0 and 1 only in
        the limit)."""
        return torch.tensor([float(value)]).clamp(1e-3, 1 - 1e-3)

    def radiance(
        self, normal: Tensor, view: Tensor, material: Channels, light: SGLight, lobe: str, visibility: Tensor | None
    ) -> Shading:
        """The diffuse layer (:func:`diffuse_radiance_gltf`) of colour ``base (1 - metallic)``; the
        specular layer of ``F0 = lerp(0.04, base, metallic)`` (:func:`gltf_f0`: Schlick's Fresnel is
        linear in ``F0``, so the dielectric and metal lobes of the specification's ``mix`` are one
        lobe) with GGX and the separable Smith-GGX, by ``lobe``: ``fitted``
        (:func:`~stages.render.fitted_lobe.specular_radiance_fitted`) or ``split_sum``'s energy
        with TANGO's isotropic shape (:func:`~stages.render.split_sum.specular_radiance_split_sum`),
        both with its table. Both from the material's ``base`` and ``metallic``."""
        base, metallic, roughness = material.base, material.metallic, material.roughness
        diffuse = diffuse_radiance_gltf(normal, view, base * (1.0 - metallic), light, visibility)
        f0 = gltf_f0(base, metallic)
        if lobe == "fitted":
            return Shading(diffuse, specular_radiance_fitted(normal, view, f0, roughness, light, self, visibility))
        if lobe == "split_sum":
            return Shading(diffuse, specular_radiance_split_sum(normal, view, f0, roughness, light, self, visibility))
        raise self.refused(lobe)

    def diffuse_layer(self, vh: Tensor) -> Tensor:
        """``1 - F(v . h)`` with the dielectric's ``F = 0.04 + 0.96 (1 - v.h)^5`` (glTF 2.0,
        Appendix B ``fresnel_mix``), as :func:`diffuse_radiance_gltf` weights its lobes."""
        return (1.0 - GLTF_DIELECTRIC_F0) * _one_minus_schlick(vh)

    # the module's own functions above, as the base class asks for them
    log_ndf_times_visibility = staticmethod(log_ndf_times_visibility)
    ndf_quadrature = staticmethod(ndf_quadrature)
    shadowing = staticmethod(shadowing)


#: glTF 2.0's metallic-roughness BRDF
GLTF = Gltf()
#: the registry's handle on the model (:func:`stages.render.brdf.get`)
MODEL = GLTF
