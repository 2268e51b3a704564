"""What a BRDF model is to the rest of the library: :class:`Brdf`, the base of each model's object.

An object holds everything that differs between models, so that no caller compares their names:
its parameters (what the SVBRDF network's heads predict) and the material channels they make; its
diffuse and specular terms under the SG light, with the specular lobe models it has and those it
refuses; its normal distribution and shadowing, which the fitted lobe evaluates and the table of
directional albedo integrates (:mod:`stages.render.specular_albedo`); and the table's file. The
settings' view of a model (its name, parameters, lobes, the settings it reads) and, as plain data,
the channels its bake and assets write and how USD, glTF, OBJ and Blender read them are its row
in :mod:`stages.config.brdfs` (torch-free, so the exporters read it without torch), which the
object reads (:attr:`Brdf.spec`, and the properties that repeat its asset fields).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar, Protocol

import numpy as np
import torch
from torch import Tensor

from ...config.brdfs import BRDFS, BrdfSpec
from ..shading import FRESNEL_POWER, SGLight, Shading, in_own_precision


class Channels(Protocol):
    """What a BRDF reads of a material (:class:`stages.model.networks.Material`): per point
    ``albedo (N, 3)``, ``specular (N, 3)`` and ``roughness (N, 1)`` (TANGO's terms; the last two
    None for a diffuse-only material) and a model's own parameters (glTF's ``base (N, 3)``,
    ``metallic (N, 1)``)."""

    albedo: Tensor
    specular: Tensor | None
    roughness: Tensor | None
    base: Tensor | None
    metallic: Tensor | None


class Brdf(ABC):
    """A BRDF model: one object per model, registered by name in :mod:`stages.render.brdf`."""

    #: its name (``optimize.brdf``; its row in :data:`stages.config.brdfs.BRDFS`)
    name: ClassVar[str]
    #: the output widths of the SVBRDF network's three heads, in :attr:`parameters`' order
    widths: ClassVar[tuple[int, int, int]]
    #: its shipped table of directional albedo and lobe moments (:mod:`stages.render.specular_albedo`)
    table_path: ClassVar[Path]

    @property
    def spec(self) -> BrdfSpec:
        """Its row in :mod:`stages.config.brdfs`."""
        return BRDFS[self.name]

    @property
    def parameters(self) -> tuple[str, str, str]:
        """The parameters its heads predict, in head order: colour, specular parameter, roughness."""
        return self.spec.parameters

    @property
    def lobes(self) -> tuple[str, ...]:
        """The specular lobe models it has (``optimize.specular_lobe``)."""
        return self.spec.lobes

    @property
    def model_lobe(self) -> str:
        """The specular lobe model that stands for it against a reference (:mod:`stages.reference.limits`)."""
        return self.spec.model_lobe

    # -------------------------------------------- its bake and assets: its row's (BrdfSpec) fields
    @property
    def texture_of(self) -> Mapping[str, str]:
        """Each parameter's baked texture (:attr:`BrdfSpec.texture_of`)."""
        return self.spec.texture_of

    @property
    def exported_textures(self) -> tuple[str, ...]:
        """The bake's textures its assets reference, in a GLB's order (:attr:`BrdfSpec.exported_textures`)."""
        return self.spec.exported_textures

    @property
    def usd_specular_workflow(self) -> int:
        """``UsdPreviewSurface``'s ``useSpecularWorkflow`` (:attr:`BrdfSpec.usd_specular_workflow`)."""
        return self.spec.usd_specular_workflow

    @property
    def gltf_extensions(self) -> tuple[str, ...]:
        """The glTF extensions its material needs (:attr:`BrdfSpec.gltf_extensions`)."""
        return self.spec.gltf_extensions

    def gltf_material_extensions(self, first: int) -> dict[str, Any]:
        """A glTF material's ``extensions`` for the texture set whose first texture is ``first``
        (:meth:`BrdfSpec.gltf_material_extensions`)."""
        return self.spec.gltf_material_extensions(first)

    def mtl_lines(self, folder: str) -> list[str]:
        """An OBJ material's lines for its specular parameter (:meth:`BrdfSpec.mtl_lines`)."""
        return self.spec.mtl_lines(folder)

    @property
    def blender_wiring(self) -> Mapping[str, tuple[str, str, str | None]]:
        """The Principled BSDF inputs its specular parameter arrives in when Blender imports its
        assets (:attr:`BrdfSpec.blender_wiring`)."""
        return self.spec.blender_wiring

    def __repr__(self) -> str:
        return f"<BRDF {self.name}>"

    def __copy__(self) -> Brdf:
        return self  # a model holds no state: one object per model, also in copies of a field

    def __deepcopy__(self, memo: dict) -> Brdf:
        return self

    # ------------------------------------------------------------------------------ material
    @abstractmethod
    def channels(self, colour: Tensor, specular: Tensor | None, roughness: Tensor | None) -> dict[str, Tensor | None]:
        """A material's channels (the fields of :class:`stages.model.networks.Material`) from the
        parameters in head order: ``colour (N, 3)``, the specular parameter and ``roughness (N, 1)``
        (both None for a diffuse-only material, where the model has one)."""

    @abstractmethod
    def head_start(self, value: float) -> Tensor:
        """The specular head's output that :attr:`BrdfSpec.start_setting`'s ``value`` asks for
        everywhere ``(widths[1],)``, inside the open interval a sigmoid reaches."""

    # ------------------------------------------------------------------------------- shading
    def shade(
        self,
        normal: Tensor,
        view: Tensor,
        material: Channels,
        light: SGLight,
        lobe: str | None = None,
        visibility: Tensor | None = None,
    ) -> Shading:
        """Diffuse and specular radiance ``(N, 3)`` of ``material`` at unit ``normal`` and ``view
        (N, 3)`` (``n . v > 0``, :func:`~stages.render.shading.face_viewer`) under ``light``, the
        specular term by the model ``lobe`` names (one of :attr:`lobes`; None: :attr:`model_lobe`),
        each light lobe scaled by its visible share ``visibility (N, K)`` in both terms (shadows,
        :mod:`stages.render.visibility`; None: unshadowed). Any enclosing autocast is switched off
        (:func:`~stages.render.shading.in_own_precision`)."""
        return in_own_precision(self.radiance, normal, view, material, light, lobe or self.model_lobe, visibility)

    @abstractmethod
    def radiance(
        self, normal: Tensor, view: Tensor, material: Channels, light: SGLight, lobe: str, visibility: Tensor | None
    ) -> Shading:
        """:meth:`shade` in the caller's precision."""

    def refused(self, lobe: str) -> ValueError:
        """The error for a specular lobe model it does not have."""
        return ValueError(f"the {self.name} BRDF has no {lobe!r} specular model; use {' or '.join(self.lobes)}")

    def diffuse_layer(self, vh: Tensor) -> Tensor | float:
        """The diffuse term's weight where light arrives with half vector ``h`` of cosine ``vh``
        with the view: 1 for a diffuse term summed with the specular one (TANGO's); a layered
        model's ``1 - F`` (glTF's)."""
        return 1.0

    def at_directions(
        self, normal: Tensor, view: Tensor, directions: Tensor, material: Channels, widen: Tensor | float = 0.0
    ) -> Shading:
        """The reflected radiance ``(N, M, 3)`` per unit irradiance arriving from each of the unit
        ``directions (N or 1, M, 3)`` at unit ``normal`` and ``view (N, 3)`` (``n . v > 0``): ``f(v,
        l) max(n . l, 0)``, evaluated at each direction (no lobe model), split into the diffuse
        and specular terms. The specular term is ``F(v . h) D(h) G(l, v) / (4 (n.l)(n.v)) (n.l)``
        with Schlick's Fresnel at the half vector and the model's normal distribution and
        shadowing (:meth:`log_ndf_times_visibility`), its ``alpha^2 = r^4`` widened by ``widen``
        (broadcasting over ``M``; 0: the model's own): a sampled light's cell is blurred over
        its normal distribution so that a lobe narrower than the cells' spacing does not fall
        between them. A diffuse-only material has no specular term (zeros). ``1 - n . h`` is
        ``|n - h|^2 / 2`` and ``v . h`` is ``|v + l| / 2`` (no cancellation at a sharp lobe's
        peak); ``|v + l|`` is held at 1e-6 where ``l = -v``, below the horizon, where the value
        is zero. Exact for every direction (tested against the formulas written out)."""
        n, v = normal[:, None, :], view[:, None, :]
        nl = (n * directions).sum(-1, keepdim=True)  # (N, M, 1)
        lit = nl > 0.0
        nl = torch.clamp(nl, min=0.0)
        half = v + directions
        length = torch.clamp(torch.linalg.vector_norm(half, dim=-1, keepdim=True), min=1e-6)
        h = half / length
        vh = 0.5 * length
        diffuse = material.albedo[:, None, :] / math.pi * nl * self.diffuse_layer(vh)
        diffuse = torch.where(lit, diffuse, torch.zeros_like(diffuse))
        if material.specular is None or material.roughness is None:
            return Shading(diffuse, torch.zeros_like(diffuse))
        one_minus_nh = 0.5 * ((n - h) ** 2).sum(-1, keepdim=True)
        nv = (normal * view).sum(-1, keepdim=True)[:, None, :]
        r = material.roughness[:, None, :]
        rough = r if isinstance(widen, float) and widen == 0.0 else (r**4 + widen) ** 0.25
        f0 = material.specular[:, None, :]
        fresnel = f0 + (1.0 - f0) * (1.0 - vh) ** FRESNEL_POWER
        density = torch.exp(self.log_ndf_times_visibility(one_minus_nh, nl, nv, rough))
        specular = torch.where(lit, fresnel * density * nl, torch.zeros_like(diffuse))
        return Shading(diffuse, specular)

    @abstractmethod
    def log_ndf_times_visibility(self, one_minus_nh: Tensor, nl: Tensor, nv: Tensor, roughness: Tensor) -> Tensor:
        """``log(D(h) G(l, v) / (4 (n.l)(n.v)))`` from ``1 - n.h``, ``n.l`` and ``n.v``
        (broadcasting): the density the fitted lobe corrects towards
        (:func:`~stages.render.fitted_lobe.specular_radiance_fitted`)."""

    # ----------------------------------------------------------------- the table's quadrature
    @abstractmethod
    def ndf_quadrature(self, x: np.ndarray, w: np.ndarray, roughness: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Gauss-Legendre nodes ``x`` and weights ``w`` on [-1, 1] ``(U,)`` turned into half
        vectors' polar angles ``cos_t, sin_t (U,)`` and the weight ``D(h) dh`` per unit of
        azimuth over ``2 pi`` ``(U,)``, by the change of variables that resolves its normal
        distribution at every roughness."""

    @abstractmethod
    def shadowing(self, nl: np.ndarray, c: float, roughness: float) -> np.ndarray:
        """``G(l, v) / (n . v)`` for ``n.l`` values ``nl`` (> 0) and ``n.v = c``."""
