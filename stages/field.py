"""The stylisation field: SVBRDF network, optional normal network and SG light, built from the
optimisation settings, with one function that shades cached hit points."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from .networks import Material, NormalNet, SGLightModule, SVBRDFNet, make_encoding, symmetric
from .render.shading import SGLight, Shading, face_viewer, shade


@dataclass(frozen=True)
class FieldOutput:
    shading: Shading
    material: Material
    normal: Tensor  # (N, 3) shading normal (predicted, facing the viewer)


class StyleField(nn.Module):
    """Material + normals + light. ``settings`` is an :class:`~stages.optimize.OptimizeSettings`."""

    def __init__(self, settings) -> None:
        super().__init__()
        s = settings
        gen = torch.Generator().manual_seed(s.seed + 7919)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(s.seed)
            mat_enc = make_encoding(
                s.material_encoding,
                frequencies=s.material_frequencies,
                count=s.material_fourier_count,
                sigma=s.material_fourier_sigma,
                generator=gen,
            )
            self.svbrdf = SVBRDFNet(
                mat_enc,
                width=s.width,
                specular=s.specular,
                init_specular=s.init_specular,
                init_roughness=s.init_roughness,
                min_roughness=s.min_roughness,
            )
            self.normal_net = None
            if s.normal_network and s.normal_max_delta > 0:
                nrm_enc = make_encoding(
                    s.normal_encoding,
                    frequencies=s.normal_frequencies,
                    count=s.normal_fourier_count,
                    sigma=s.normal_fourier_sigma,
                    generator=gen,
                )
                self.normal_net = NormalNet(nrm_enc, width=s.width, max_delta=s.normal_max_delta)
            self.light = SGLightModule(
                s.light_lobes,
                rgb=s.light_rgb,
                total_energy=s.light_energy,
                init_sharpness=s.light_init_sharpness,
            )
        self.symmetry = s.symmetry

    def symmetric_points(self, points: Tensor) -> Tensor:
        """The points as the networks see them (``(x, y, |z|)`` under the symmetry prior)."""
        return symmetric(points) if self.symmetry else points

    def forward(self, points: Tensor, normals: Tensor, view: Tensor, light: SGLight | None = None) -> FieldOutput:
        """Shade hit ``points (N, 3)`` with flat ``normals (N, 3)`` seen along ``view (N, 3)``
        (unit, surface -> eye). Geometric normals are first turned towards the viewer (two-sided
        surfaces: the inside of an open vase is visible)."""
        flip = (normals * view).sum(-1, keepdim=True) < 0
        normals = torch.where(flip, -normals, normals)
        p = self.symmetric_points(points)
        if self.normal_net is not None:
            normals = self.normal_net(p, normals)
        normals = face_viewer(normals, view)
        mat = self.svbrdf(p)
        light = light if light is not None else self.light()
        return FieldOutput(shade(normals, view, mat.albedo, light, mat.specular, mat.roughness), mat, normals)
