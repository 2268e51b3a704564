"""The stylisation field: SVBRDF network, optional normal network and light, built from a
:class:`~stages.config.sections.FieldSettings`, and its forward pass, the one path from cached
hits to shaded colour that training, evaluation, relighting (a light override), material editing
(scales), baking (:meth:`StyleField.surface`) and the benchmarks all use, eager. Training runs it
through :class:`~stages.model.compiled.CompiledField` (torch.compile, padding, bfloat16)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from ..config.sections import FieldSettings
from ..geometry.normals import NormalSpec
from ..render import brdf as brdfs
from ..render.light import Light, Visibility
from ..render.shading import Shading, face_viewer
from .lights import build_light
from .networks import Material, NormalNet, SVBRDFNet, make_encoding, symmetric


@dataclass(frozen=True)
class FieldOutput:
    shading: Shading
    material: Material
    normal: Tensor  # (N, 3) shading normal (predicted, facing the viewer)


def shade_material(
    normal: Tensor, view: Tensor, material: Material, light: Light, lobe: str, visibility: Visibility | None = None
) -> Shading:
    """``light`` (a sum of components, :class:`~stages.render.light.Light`) on ``material`` through
    its BRDF (``material.brdf``, :mod:`stages.render.brdf`: TANGO's sum, or glTF's from the base
    colour and metallic); ``visibility``: each component's visibility input (shadows; for SG lobes
    each lobe's visible share ``(N, K)``, :mod:`stages.model.shadows`)."""
    return light.shade(material.brdf, normal, view, material, lobe, visibility)


@dataclass(frozen=True)
class MaterialEdit:
    """TANGO's material editing (Fig. 6): roughness and specular colour scaled, then clamped back
    into their valid ranges (``[min_roughness, 1]`` and ``[0, 1]``); for a glTF material the
    specular scale scales the metalness."""

    roughness_scale: float = 1.0
    specular_scale: float = 1.0

    def apply(self, material: Material, min_roughness: float) -> Material:
        if material.specular is None:
            return material
        colour, specular, roughness = material.parameters().values()  # (the BRDF's, in head order)
        scaled = (specular * self.specular_scale).clamp(0.0, 1.0)  # TANGO's specular colour, glTF's metalness
        return Material.of(material.brdf, colour, scaled, (roughness * self.roughness_scale).clamp(min_roughness, 1.0))


class StyleField(nn.Module):
    """Material + normals + light, built from ``settings`` (networks, encodings, light, seed)."""

    def __init__(self, settings: FieldSettings) -> None:
        super().__init__()
        s = settings
        gen = torch.Generator().manual_seed(s.seed + 7919)
        hashgrid = {
            "levels": s.hashgrid_levels,
            "features": s.hashgrid_features,
            "log2_size": s.hashgrid_log2_size,
            "min_resolution": s.hashgrid_min_resolution,
            "max_resolution": s.hashgrid_max_resolution,
            "step_scale": s.hashgrid_step_scale,
        }
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(s.seed)
            mat_enc = make_encoding(
                s.material_encoding,
                frequencies=s.material_frequencies,
                count=s.material_fourier_count,
                sigma=s.material_fourier_sigma,
                generator=gen,
                hashgrid=hashgrid,
            )
            self.svbrdf = SVBRDFNet(
                mat_enc,
                width=s.width,
                specular=s.specular,
                init_specular=s.init_specular,
                init_roughness=s.init_roughness,
                init_metallic=s.init_metallic,
                min_roughness=s.min_roughness,
                brdf=s.brdf,
            )
            self.normal_net = None
            if s.normal_network and s.normal_max_delta > 0:
                nrm_enc = make_encoding(
                    s.normal_encoding,
                    frequencies=s.normal_frequencies,
                    count=s.normal_fourier_count,
                    sigma=s.normal_fourier_sigma,
                    generator=gen,
                    hashgrid=hashgrid,
                )
                self.normal_net = NormalNet(nrm_enc, width=s.width, max_delta=s.normal_max_delta)
            #: the light: the sum of the components the settings ask for (:mod:`stages.model.lights`)
            self.light = build_light(s)
        self.symmetry = s.symmetry
        self.specular_lobe = s.specular_lobe
        #: the BRDF the field's material is of (its object, :mod:`stages.render.brdf`)
        self.brdf = brdfs.get(s.brdf)
        #: whether the field casts shadows where a ray cache holds visibility (every ViewStore of it)
        self.shadows = s.shadows
        #: the shading normals the field is trained and rendered with (every ViewStore and the bake use them)
        self.normals = NormalSpec(s.shading_normals, s.crease_angle_deg, s.normal_weighting)
        #: the networks' matrix products under bfloat16 autocast in training mode (off: float32;
        #: :meth:`~stages.model.compiled.CompiledField.use_bf16` decides it)
        self.bf16 = False
        #: the settings the field was built from
        self.settings = s

    @property
    def light_learns(self) -> bool:
        """Whether the light is learned (not held at a known environment's fit, ``light: fixed``)."""
        return any(p.requires_grad for p in self.light.parameters())

    def random_material(self, leaf: Callable[..., Tensor], n: int) -> Material:
        """A material of this field's BRDF at ``n`` points, each of its tensors ``leaf(n, channels)``
        (random in ``[0, 1)``, needing a gradient as the networks' outputs do), the roughness mapped
        into ``[0.1, 1)``: what a compiled renderer's first pass shades (:mod:`stages.model.compiled`)."""
        rough = leaf(n, 1) * 0.9 + 0.1
        colour, specular, _ = self.brdf.widths
        return Material.of(self.brdf, leaf(n, colour), leaf(n, specular), rough)

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """As ``nn.Module``'s, the light's components first made to fit the saved state
        (:meth:`~stages.model.lights.base.LightModule.match_state`: a light whose lobes were pruned,
        ``light_prune_after``, is shrunk to the saved number of lobes, its parameters new objects
        then; a state written before lights were sums has its SG lobes moved under ``light.sg.``)."""
        return super().load_state_dict(self.light.match_state(state_dict, "light."), strict, assign)

    def symmetric_points(self, points: Tensor) -> Tensor:
        """The points as the networks see them (``(x, y, |z|)`` under the symmetry prior)."""
        return symmetric(points) if self.symmetry else points

    def surface(self, points: Tensor, normals: Tensor, view: Tensor | None = None) -> tuple[Material, Tensor]:
        """The networks at hit ``points (N, 3)`` with shading ``normals (N, 3)`` (:attr:`normals`):
        the material and the unit shading normal.

        With ``view (N, 3)`` (unit, surface -> eye), normals facing away are first turned towards
        the viewer (two-sided surfaces: the inside of an open vase is visible; a no-op for the
        normals of a :class:`~stages.imaging.views.ViewStore`, which orients them by the face the
        viewer sees) and the predicted normal is kept in the viewer's hemisphere
        (:func:`~stages.render.shading.face_viewer`).
        Without it (texture baking) the normals are taken as given and the prediction returned as is.
        """
        if view is not None:
            flip = (normals * view).sum(-1, keepdim=True) < 0
            normals = torch.where(flip, -normals, normals)
        p = self.symmetric_points(points)
        with torch.autocast(points.device.type, dtype=torch.bfloat16, enabled=self.bf16 and self.training):
            if self.normal_net is not None:
                normals = self.normal_net(p, normals)
            material = self.svbrdf(p)
        if view is not None:
            normals = face_viewer(normals, view)
        return material, normals

    def material(self, points: Tensor) -> Material:
        """The material network alone at ``points (N, 3)``, as :meth:`surface` runs it (the symmetry
        prior, training's bfloat16 autocast), for priors that compare it at nearby points."""
        with torch.autocast(points.device.type, dtype=torch.bfloat16, enabled=self.bf16 and self.training):
            return self.svbrdf(self.symmetric_points(points))

    def forward(
        self,
        points: Tensor,
        normals: Tensor,
        view: Tensor,
        light: Light | None = None,
        edit: MaterialEdit | None = None,
        visibility: Callable[[Light], Visibility] | None = None,
    ) -> FieldOutput:
        """Shade hit ``points (N, 3)`` with flat ``normals (N, 3)`` seen along ``view (N, 3)``
        (unit, surface -> eye) under the learned light, or under ``light`` (relighting), with the
        material optionally edited (``edit``); ``visibility``: a light's visibility inputs (shadows,
        :meth:`~stages.render.light.Light.shadowed_by`; :meth:`~stages.imaging.views.CachedView.shade`
        passes its view's)."""
        material, normal = self.surface(points, normals, view)
        if edit is not None:
            material = edit.apply(material, self.svbrdf.min_roughness)
        return FieldOutput(self.shade(material, normal, view, light, visibility), material, normal)

    def surface_and_shade(
        self, points: Tensor, normals: Tensor, view: Tensor, light: Light, shares: Visibility | None
    ) -> tuple[Material, Tensor, Shading]:
        """Training's forward pass as one function (:meth:`surface`, then the renderer under
        ``light`` with its visibility inputs ``shares``), for the networks and the renderer compiled
        together (``compile_networks``, :class:`~stages.model.compiled.CompiledField`): the
        material, the unit shading normal and the shading."""
        material, normal = self.surface(points, normals, view)
        return material, normal, shade_material(normal, view, material, light, self.specular_lobe, shares)

    def shares(self, visibility: Callable[[Light], Visibility] | None, light: Light) -> Visibility | None:
        """``light``'s visibility inputs at the shaded points (each SG lobe's visible share), where
        ``visibility`` gives them (shadows), in bfloat16 products with the networks'
        (``lobe_visibility_bits``)."""
        if visibility is None:
            return None
        with torch.autocast(light.device.type, dtype=torch.bfloat16, enabled=self.bf16 and self.training):
            return visibility(light)

    def shade(
        self,
        material: Material,
        normal: Tensor,
        view: Tensor,
        light: Light | None = None,
        visibility: Callable[[Light], Visibility] | None = None,
    ) -> Shading:
        """The renderer's half of the forward pass: ``material`` and unit shading ``normal`` (from
        :meth:`surface`) seen along ``view``, under the learned light or ``light``, shadowed by
        ``visibility(light)`` when given."""
        light = light if light is not None else self.light()
        return shade_material(normal, view, material, light, self.specular_lobe, self.shares(visibility, light))
