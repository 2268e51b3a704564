"""TANGO's BRDF (``optimize.brdf: tango``): a Lambertian diffuse albedo plus a microfacet specular
lobe of specular colour ``F0`` and roughness ``r`` (TANGO Sec. 3.2), the normal distribution
PhySG's SG fit of GGX (``alpha = r^2``), Schlick's Fresnel and Smith-Schlick shadowing with ``k =
(r + 1)^2 / 8``. Its specular term by any of the three lobe models: TANGO's closed form
(``isotropic``), ``split_sum`` or ``fitted``, the last two with its own table
(``data/specular_albedo.npz``). Its assets: USD's specular workflow, glTF's
``KHR_materials_specular`` for the coloured F0.

References: [Zhang21] PhySG (the SG normal distribution and the shadowing term TANGO uses).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ..fitted_lobe import specular_radiance_fitted
from ..isotropic_lobe import ndf_sg, smith_k, specular_radiance
from ..shading import SGLight, Shading, diffuse_radiance
from ..specular_albedo import DATA_DIR
from ..split_sum import specular_radiance_split_sum
from .base import Brdf, Channels

#: the SG NDF's exponent beyond which exp(-u) is below 1e-26: the table's quadrature covers
#: ``u = lam (1 - cos theta_h)`` in [0, min(2 lam, U_MAX)]
U_MAX = 60.0


def log_ndf_times_visibility(one_minus_nh: Tensor, nl: Tensor, nv: Tensor, roughness: Tensor) -> Tensor:
    """``log(D(h) G(l, v) / (4 (n.l)(n.v)))`` of TANGO's BRDF from ``1 - n.h``, ``n.l`` and ``n.v``
    (broadcasting): the SG NDF (:func:`~stages.render.isotropic_lobe.ndf_sg`) and Smith-Schlick
    (:func:`~stages.render.isotropic_lobe.smith_schlick_over_cosines`)."""
    lam_d, mu_d = ndf_sg(roughness)
    k = smith_k(roughness)
    return torch.log(mu_d) - lam_d * one_minus_nh - torch.log(4.0 * (nl * (1.0 - k) + k) * (nv * (1.0 - k) + k))


def ndf_quadrature(x: np.ndarray, w: np.ndarray, roughness: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Half vectors for the table's quadrature (:meth:`~stages.render.brdf.Brdf.ndf_quadrature`):
    with the SG NDF's ``lam = 2 / r^4`` and amplitude ``lam / (2 pi)``, ``u = lam (1 - cos
    theta_h)`` turns ``D(h) dh`` into ``exp(-u) / (2 pi) du dphi`` exactly, which resolves the
    sharpest lobes as well as the broadest."""
    lam = 2.0 / roughness**4
    top = min(2.0 * lam, U_MAX)
    u = 0.5 * top * (x + 1.0)
    wu = 0.5 * top * w
    cos_t = 1.0 - u / lam
    # sin from 1 - cos = u / lam without cancellation: sin^2 = (u / lam)(2 - u / lam)
    sin_t = np.sqrt(np.clip(u / lam * (2.0 - u / lam), 0.0, None))
    return cos_t, sin_t, np.exp(-u) * wu


def shadowing(nl: np.ndarray, c: float, roughness: float) -> np.ndarray:
    """``G(l, v) / (n . v)`` for ``n.l`` values ``nl`` (> 0) and ``n.v = c``: Smith-Schlick
    ``G1(x) = x / (x (1 - k) + k)``, ``k = (r + 1)^2 / 8``."""
    k = (roughness + 1.0) ** 2 / 8.0
    return nl / (nl * (1.0 - k) + k) / (c * (1.0 - k) + k)


class Tango(Brdf):
    """TANGO's BRDF: diffuse albedo, specular colour and roughness, summed."""

    name = "tango"
    widths = (3, 3, 1)
    table_path = DATA_DIR / "specular_albedo.npz"

    def channels(self, colour: Tensor, specular: Tensor | None, roughness: Tensor | None) -> dict[str, Tensor | None]:
        """Its parameters are TANGO's channels themselves."""
        return {"albedo": colour, "specular": specular, "roughness": roughness}

    def head_start(self, value: float) -> Tensor:
        """The specular colour ``value`` in every channel."""
        return torch.full((3,), float(value))

    def radiance(
        self, normal: Tensor, view: Tensor, material: Channels, light: SGLight, lobe: str, visibility: Tensor | None
    ) -> Shading:
        """The diffuse term (:func:`~stages.render.shading.diffuse_radiance`) plus, where the
        material has a specular colour and roughness, the specular term of ``lobe``
        (:meth:`specular`); a diffuse-only material (the ablation without them) skips the specular
        computation entirely."""
        diffuse = diffuse_radiance(normal, material.albedo, light, visibility)
        if material.specular is None or material.roughness is None:
            return Shading(diffuse, torch.zeros_like(diffuse))
        return Shading(diffuse, self.specular(normal, view, material.specular, material.roughness, light, lobe, visibility))

    def specular(
        self, normal: Tensor, view: Tensor, f0: Tensor, roughness: Tensor, light: SGLight, lobe: str, visibility: Tensor | None
    ) -> Tensor:
        """The specular term ``(N, 3)`` of ``F0 (N, 3)`` and ``roughness (N, 1)`` by ``lobe``:
        ``isotropic`` (:func:`~stages.render.isotropic_lobe.specular_radiance`), ``split_sum``
        (:func:`~stages.render.split_sum.specular_radiance_split_sum`) or ``fitted``
        (:func:`~stages.render.fitted_lobe.specular_radiance_fitted`), the last two with its
        table."""
        if lobe == "isotropic":
            return specular_radiance(normal, view, f0, roughness, light, visibility)
        if lobe == "split_sum":
            return specular_radiance_split_sum(normal, view, f0, roughness, light, self, visibility)
        if lobe == "fitted":
            return specular_radiance_fitted(normal, view, f0, roughness, light, self, visibility)
        raise self.refused(lobe)

    # the module's own functions above, as the base class asks for them
    log_ndf_times_visibility = staticmethod(log_ndf_times_visibility)
    ndf_quadrature = staticmethod(ndf_quadrature)
    shadowing = staticmethod(shadowing)


#: TANGO's BRDF
TANGO = Tango()
#: the registry's handle on the model (:func:`stages.render.brdf.get`)
MODEL = TANGO
