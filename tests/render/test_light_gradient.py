"""The light's gradient summed over many points, in float32, against float64's.

A step's gradient to the light is one sum over every point it shades. Under the light's
parametrisation (a lobe's energy held, :class:`~stages.model.lights.sg.SGLightModule`) the terms of
that sum cancel: over normals spread on the sphere a lobe's irradiance depends on neither its
shape nor its direction. A float32 rounding that leans one way in every term then adds up over the
points while the terms themselves cancel: the amplitudes' and axes' gradients, sums over the points
in the renderer's float32 matrix products, left the diffuse term's log-sharpness gradient 2.1e-2 of
its norm off float64's at 100,000 points, and the axes' 1.3e-3. The renderer now takes the
products that carry a light's gradient in float64 (the cosines, the amplitudes' weighted sum) and
broadcasts the sharpnesses through float64 (:func:`~stages.render.shading.lobes_at_points`)."""

from __future__ import annotations

import copy

import pytest
import torch

from stages.model.lights.sg import SGLightModule
from stages.render import shading as sh
from stages.render.brdf import GLTF
from stages.render.brdf.gltf import diffuse_radiance_gltf, gltf_f0
from stages.render.fitted_lobe import specular_radiance_fitted
from stages.render.isotropic_lobe import specular_radiance

F64 = torch.float64
POINTS = 100_000
LOBES = 32
#: the largest relative error of each leaf's float32 gradient (measured: axes 1.6e-5, log-sharpness
#: 5.8e-5, log-energy 9.3e-7 at the worst term; before: 1.7e-3, 2.5e-2 and 6.0e-5)
BOUNDS = {"axis_raw": 1e-4, "log_sharpness": 2e-4, "log_energy": 1e-5}

TERMS = {
    "diffuse (TANGO)": lambda p, light: sh.diffuse_radiance(p["normal"], p["albedo"], light, p["shares"]),
    "diffuse (glTF)": lambda p, light: diffuse_radiance_gltf(
        p["normal"], p["view"], p["albedo"] * (1 - p["metallic"]), light, p["shares"]
    ),
    "specular fitted (glTF)": lambda p, light: specular_radiance_fitted(
        p["normal"], p["view"], gltf_f0(p["albedo"], p["metallic"]), p["roughness"], light, GLTF, p["shares"]
    ),
    "specular isotropic (TANGO)": lambda p, light: specular_radiance(
        p["normal"], p["view"], p["albedo"], p["roughness"], light, p["shares"]
    ),
}


def _points() -> dict[str, torch.Tensor]:
    """Random normals over the sphere, views near them, materials, shadows' shares in [0.5, 1] and
    positive weights of the colours (a loss brightening every point), float64."""
    g = torch.Generator().manual_seed(2)
    normal = torch.nn.functional.normalize(torch.randn(POINTS, 3, generator=g, dtype=F64), dim=-1)
    view = torch.nn.functional.normalize(normal + 0.3 * torch.randn(POINTS, 3, generator=g, dtype=F64), dim=-1)
    return {
        "normal": sh.face_viewer(normal, view),
        "view": view,
        "albedo": torch.rand(POINTS, 3, generator=g, dtype=F64),
        "metallic": torch.rand(POINTS, 1, generator=g, dtype=F64),
        "roughness": 0.1 + 0.9 * torch.rand(POINTS, 1, generator=g, dtype=F64),
        "shares": 0.5 + 0.5 * torch.rand(POINTS, LOBES, generator=g, dtype=F64),
        "weights": torch.rand(POINTS, 3, generator=g, dtype=F64),
    }


@pytest.mark.parametrize("term", TERMS)
def test_the_lights_gradient_over_many_points_is_float64s(term):
    points, module = _points(), SGLightModule(LOBES, init="tango")
    grads = {}
    for dtype in (F64, torch.float32):
        light = copy.deepcopy(module).to(dtype)
        p = {k: v.to(dtype) for k, v in points.items()}
        (TERMS[term](p, light()) * p["weights"]).sum().backward()
        grads[dtype] = {k: v.grad.to(F64) for k, v in light.named_parameters()}
    for leaf, bound in BOUNDS.items():
        want, got = grads[F64][leaf], grads[torch.float32][leaf]
        assert float((got - want).norm() / want.norm()) < bound, (term, leaf)


def _lobe_sum(lam: torch.Tensor, x: torch.Tensor, w: torch.Tensor, rows) -> torch.Tensor:
    return (w * torch.exp(rows(lam, x.shape[0]) * x)).sum()


@pytest.mark.slow(minutes=0.5)
def test_a_compiled_broadcast_of_the_sharpnesses_sums_their_gradient_in_float64():
    """torch.compile sums a broadcast row's gradient over the points in its own float32 loop
    (sequential per vector lane): for ``sum(w exp(lam x))`` over 35,000 x 4 terms the compiled
    gradient of ``lam`` erred by 9.7e-7 of its norm, eager's by 6.9e-8. Broadcast through float64
    (:func:`~stages.render.shading.lobes_at_points`) it is summed in float64, as eager's or better
    (measured 6.1e-8); the plain broadcast (``row.expand``) fails the bound."""
    g = torch.Generator().manual_seed(0)
    x = torch.rand(35_000, 4, generator=g, dtype=F64) * 2 - 1
    w = torch.randn(35_000, 4, generator=g, dtype=F64)
    lam0 = torch.rand(1, 4, generator=g, dtype=F64) + 0.5
    want = lam0.clone().requires_grad_()
    _lobe_sum(want, x, w, sh.lobes_at_points).backward()
    compiled = torch.compile(_lobe_sum, dynamic=True, fullgraph=True)
    lam = lam0.float().requires_grad_()
    compiled(lam, x.float(), w.float(), sh.lobes_at_points).backward()
    assert float((lam.grad.double() - want.grad).norm() / want.grad.norm()) < 3e-7
