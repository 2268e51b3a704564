"""Each light lobe's visible share by quadrature of the stored directions: the matrix form against
its definition, against the continuous integral (a cap of blocked directions, integrated in the
test over a fine polar grid), finite values and gradients at the extremes, and the shading's
every term scaled by it."""

import contextlib
import math

import numpy as np
import pytest
import torch

from stages.geometry.visibility import fibonacci_directions
from stages.model.networks import Material
from stages.render import visibility as visibility_module
from stages.render.brdf import GLTF, TANGO
from stages.render.brdf.gltf import diffuse_radiance_gltf
from stages.render.fitted_lobe import specular_radiance_fitted
from stages.render.isotropic_lobe import specular_radiance, specular_radiance_reference
from stages.render.sg import COS_LAMBDA, COS_MU, COS_OFFSET
from stages.render.shading import SGLight, diffuse_radiance, diffuse_radiance_reference
from stages.render.split_sum import specular_radiance_split_sum
from stages.render.visibility import (
    VISIBILITY_BLOCK,
    blend_traced,
    lobe_visibility,
    lobe_visibility_bits,
    lobe_visibility_reference,
    resolvable_sharpness,
    unpack_bits,
    visibility_block,
)


def _unit(x):
    return torch.nn.functional.normalize(x, dim=-1)


def _cap_blocked(dirs: torch.Tensor, centre: torch.Tensor, half_angle: float) -> torch.Tensor:
    """1 where a direction is visible: outside the cap of ``half_angle`` around ``centre``."""
    return (dirs @ centre < math.cos(half_angle)).to(dirs.dtype)


def test_matrix_form_is_its_definition():
    g = torch.Generator().manual_seed(0)
    dirs = torch.tensor(fibonacci_directions(256))
    normal = _unit(torch.randn(40, 3, generator=g, dtype=torch.float64))
    visible = (torch.rand(40, 256, generator=g, dtype=torch.float64) > 0.4).double()
    axis = _unit(torch.randn(6, 3, generator=g, dtype=torch.float64))
    sharp = torch.tensor([[1e-4], [0.5], [3.0], [20.0], [300.0], [1e4]], dtype=torch.float64)
    torch.testing.assert_close(
        lobe_visibility(normal, visible, dirs, axis, sharp),
        lobe_visibility_reference(normal, visible, dirs, axis, sharp),
        rtol=1e-12,
        atol=1e-14,
    )


def _continuous_share(lam: float, axis_tilt: float, cap_tilt: float, cap_angle: float) -> float:
    """The definition integrated over a fine grid of the upper hemisphere (normal +z), with the
    lobe tilted by ``axis_tilt`` and the blocked cap by ``cap_tilt`` towards +x."""
    t = np.linspace(0.0, math.pi / 2, 721)
    p = np.linspace(0.0, 2 * math.pi, 1441)
    tt, pp = np.meshgrid(t, p, indexing="ij")
    d = np.stack([np.sin(tt) * np.cos(pp), np.sin(tt) * np.sin(pp), np.cos(tt)], -1)
    xi = np.array([math.sin(axis_tilt), 0.0, math.cos(axis_tilt)])
    c = np.array([math.sin(cap_tilt), 0.0, math.cos(cap_tilt)])
    f = np.exp(lam * (d @ xi - 1.0)) * np.cos(tt) * np.sin(tt)
    vis = (d @ c < math.cos(cap_angle)).astype(float)
    return float(np.trapezoid(np.trapezoid(f * vis, p, axis=1), t) / np.trapezoid(np.trapezoid(f, p, axis=1), t))


@pytest.mark.parametrize("count,lam", [(1024, 0.01), (1024, 1.0), (1024, 5.0), (1024, 20.0), (4096, 20.0), (4096, 80.0)])
@pytest.mark.parametrize("axis_tilt,cap_tilt,cap_angle", [(0.0, 0.0, 0.6), (0.5, 0.9, 0.5), (1.2, 0.3, 0.9)])
def test_quadrature_against_the_continuous_integral(count, lam, axis_tilt, cap_tilt, cap_angle):
    """Up to the sharpness the set resolves (1024 directions: 20.4; 4096: 81.5) the quadrature is
    within 0.04 of the continuous share, whatever the cap and the lobe (measured: at most 0.038,
    with the cap's edge on the lobe's axis, the second case)."""
    assert lam <= resolvable_sharpness(count)
    dirs = torch.tensor(fibonacci_directions(count))
    cap = torch.tensor([math.sin(cap_tilt), 0.0, math.cos(cap_tilt)], dtype=torch.float64)
    visible = _cap_blocked(dirs, cap, cap_angle)[None]
    axis = torch.tensor([[math.sin(axis_tilt), 0.0, math.cos(axis_tilt)]], dtype=torch.float64)
    got = lobe_visibility(torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64), visible, dirs, axis, torch.tensor([[lam]]))
    assert float(got) == pytest.approx(_continuous_share(lam, axis_tilt, cap_tilt, cap_angle), abs=0.04)


def _extreme_lobes(dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """Seven lobes (raw axes, sharpnesses; both leaves needing gradients) for points whose normal
    is +z: sharpness 1e-4 to 1e5, on the normal, on the horizon, below it, straight down, and two
    of 1e5 beside each other."""
    raw = torch.tensor([[0, 0, 1], [1, 0, 0], [0.3, 0.2, -0.9], [0, 0.1, 1], [0.2, 0, 1], [0, 0, -1], [0.01, 0, 1]], dtype=dtype)
    sharp = torch.tensor([[1e-4], [1e-2], [1.0], [1e2], [1e4], [1e5], [1e5]], dtype=dtype)
    return raw.requires_grad_(True), sharp.requires_grad_(True)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_finite_at_the_extremes(dtype):
    """Fully open and fully blocked points, lobes below the horizon, sharpness 1e-4 to 1e5 (and a
    bfloat16 normal, computed in float32): values in [0, 1], finite gradients in axis and
    sharpness."""
    dirs = torch.tensor(fibonacci_directions(512), dtype=dtype)
    normal = torch.tensor([[0.0, 0.0, 1.0]] * 3, dtype=dtype)
    visible = torch.stack([torch.ones(512), torch.zeros(512), (torch.arange(512) % 2).float()]).to(dtype)
    raw, sharp = _extreme_lobes(dtype)
    for n in (normal, normal.to(torch.bfloat16)):
        v = lobe_visibility(n, visible, dirs, _unit(raw), sharp)
        assert torch.isfinite(v).all() and (v >= 0).all() and (v <= 1 + 1e-6).all()
        v.sum().backward()
        assert torch.isfinite(sharp.grad).all() and torch.isfinite(raw.grad).all()
    v = lobe_visibility(normal, visible, dirs, _unit(raw), sharp).detach()
    torch.testing.assert_close(v[0], torch.ones(7, dtype=dtype))  # fully open
    # fully blocked: no light, except where a lobe lies wholly below the horizon (it lights nothing)
    assert (v[1, [0, 1, 2, 3, 4, 6]] < 1e-6).all()


def test_gradient_in_axis_and_sharpness_matches_finite_differences():
    dirs = torch.tensor(fibonacci_directions(256))
    cap = torch.tensor([0.4, 0.0, 0.9165], dtype=torch.float64)
    visible = _cap_blocked(dirs, cap, 0.5).expand(2, -1)
    normal = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.6, 0.8]], dtype=torch.float64)

    def f(raw, log_lam):
        return lobe_visibility(normal, visible, dirs, _unit(raw), torch.exp(log_lam))

    raw = torch.tensor([[0.3, 0.1, 1.0], [-0.2, 0.4, 0.9]], dtype=torch.float64, requires_grad=True)
    log_lam = torch.tensor([[1.0], [2.5]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(f, (raw, log_lam))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_fused_blocks_equal_the_matrix_form_in_value_and_gradient(dtype):
    """``lobe_visibility_bits`` (the training's path: packed bits, blocks of points, a hand-written
    backward) against :func:`lobe_visibility` under autograd: a count of points not a multiple of
    the block, fully open, fully blocked and random points, lobes of sharpness 1e-4 to 1e5 (the
    sharp ones' far weights below float's smallest normal, which the fused path flushes to 0),
    pointing anywhere, under the horizon included; values and the gradients to axes and
    sharpnesses."""
    g = torch.Generator().manual_seed(3)
    n_pts, count = 2 * VISIBILITY_BLOCK + 37, 512
    dirs = torch.tensor(fibonacci_directions(count), dtype=dtype)
    normal = _unit(torch.randn(n_pts, 3, generator=g, dtype=dtype))
    seen = torch.rand(n_pts, count, generator=g) > 0.4
    seen[0], seen[1] = True, False
    bits = torch.from_numpy(np.packbits(seen.numpy(), axis=1))
    raw = torch.randn(9, 3, generator=g, dtype=dtype)
    raw[0] = -normal[0]  # wholly below the first point's horizon
    lam = torch.tensor([1e-4, 1e-2, 1.0, 5.0, 30.0, 3e2, 1e3, 1e4, 1e5], dtype=dtype)[:, None]
    weight = torch.rand(n_pts, 9, generator=g, dtype=dtype)
    results = []
    for fn, vis in ((lobe_visibility_bits, bits), (lobe_visibility, seen.to(dtype))):
        a, s_ = raw.clone().requires_grad_(), lam.clone().requires_grad_()
        out = fn(normal, vis, dirs, _unit(a), s_)
        (out * weight).sum().backward()
        results.append((out.detach(), a.grad, s_.grad))
    tol = 1e-10 if dtype == torch.float64 else 2e-4
    torch.testing.assert_close(results[0][0], results[1][0], rtol=tol, atol=tol / 100)
    # gradients relative to their largest: the two sharpest lobes' (1e4, 1e5: one stored direction
    # within reach, the share all but constant) are rounding, 1e-12 against 100 for the others in
    # float64, and in float32 the matrix form's subnormal weights leave 0.05 of it there
    for got, want in zip(results[0][1:], results[1][1:], strict=True):
        scale = float(want.abs().max())
        torch.testing.assert_close(got / scale, want / scale, rtol=0, atol=tol if dtype == torch.float64 else 1e-3)
    assert torch.isfinite(results[0][1]).all() and torch.isfinite(results[0][2]).all()


def test_a_gpus_single_block_equals_the_cpus_blocks(monkeypatch):
    """On a GPU a step's points go in one block (a block's operations are launches whose cost does
    not depend on its size): the shares and their gradients are those of the CPU's blocks of
    :data:`VISIBILITY_BLOCK` points to float32's rounding of sums taken in another order, and one
    block is one unpacking of the bits each way."""
    g = torch.Generator().manual_seed(5)
    n_pts, count = 3 * VISIBILITY_BLOCK + 11, 512
    dirs = torch.tensor(fibonacci_directions(count), dtype=torch.float32)
    normal = _unit(torch.randn(n_pts, 3, generator=g))
    bits = torch.from_numpy(np.packbits((torch.rand(n_pts, count, generator=g) > 0.4).numpy(), axis=1))
    raw, lam = torch.randn(6, 3, generator=g), torch.logspace(-2, 3, 6)[:, None]
    weight = torch.rand(n_pts, 6, generator=g)
    unpacked = []
    monkeypatch.setattr(
        visibility_module, "unpack_bits", lambda *a, real=visibility_module.unpack_bits: unpacked.append(1) or real(*a)
    )
    results = []
    for block in (None, 10**9):  # the CPU's, then one block for every point
        if block:
            monkeypatch.setattr(visibility_module, "visibility_block", lambda *a, b=block: b)
        unpacked.clear()
        a, s_ = raw.clone().requires_grad_(), lam.clone().requires_grad_()
        out = lobe_visibility_bits(normal, bits, dirs, _unit(a), s_)
        (out * weight).sum().backward()
        results.append((out.detach(), a.grad, s_.grad, len(unpacked)))
    assert (results[0][3], results[1][3]) == (2 * 4, 2)  # 4 blocks forward and backward, then 1
    for got, want in zip(results[1][:3], results[0][:3], strict=True):
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)
    sizes = [
        visibility_block(torch.device(d), 512, t)
        for d, t in (("cpu", torch.float32), ("cuda", torch.float32), ("cuda", torch.bfloat16))
    ]
    assert sizes == [VISIBILITY_BLOCK, 65536, 131072]  # a paper step's 25,000 points: one block on a GPU


def test_the_fused_blocks_gradient_in_float32_where_a_share_is_nearly_1():
    """A sharp lobe (sharpness 1,000 to 10,000) on an open stored direction whose neighbour is
    blocked, that neighbour's weight e^-15 of the nearest's: the share is 1 - 3e-7 and its
    gradient small but real. The backward summed the lit and the whole sums' gradients over the
    points apart, terms that cancel per point, and float32's rounding of each, times the
    sharpness, swamped it (found by ``benchmarks/render/precision.py``: a sun's axis gradient 1e4 times
    too large). Against the same function in float64, each lobe's within 1e-3 of its norm."""
    g = torch.Generator().manual_seed(12)
    count = 512
    dirs = torch.tensor(fibonacci_directions(count), dtype=torch.float64)
    seen = torch.ones(100, count, dtype=torch.bool)
    blocked = 0
    seen[:, blocked] = False
    near = int(torch.topk(dirs @ dirs[blocked], 2).indices[1])  # the blocked direction's neighbour
    lam = torch.tensor([1e3, 3e3, 1e4], dtype=torch.float64)[:, None]
    axes = []
    for x in lam[:, 0].tolist():
        # on the open direction, moved towards or away from the blocked one until its weight is e^-15
        s = torch.linspace(-0.3, 0.45, 20001, dtype=torch.float64)[:, None]
        cand = _unit(dirs[near] + s * (dirs[blocked] - dirs[near]))
        gap = x * (cand @ dirs[near] - cand @ dirs[blocked])
        axes.append(cand[int((gap - 15.0).abs().argmin())])
    axes = torch.stack(axes)
    normal = _unit(dirs[near] + 0.3 * torch.randn(100, 3, generator=g, dtype=torch.float64))
    bits = torch.from_numpy(np.packbits(seen.numpy(), axis=1))
    grads = {}
    for dtype in (torch.float64, torch.float32):
        a = axes.to(dtype, copy=True).requires_grad_()
        out = lobe_visibility_bits(normal.to(dtype), bits, dirs.to(dtype), a, lam.to(dtype))
        assert (out < 1).any() and (out > 1 - 1e-5).all()
        out.sum().backward()
        grads[dtype] = a.grad.double()
    ref = grads[torch.float64]
    err = (grads[torch.float32] - ref).norm(dim=1) / ref.norm(dim=1)
    assert err.max() < 1e-3, err


def test_the_fused_blocks_gradient_matches_finite_differences():
    dirs = torch.tensor(fibonacci_directions(256))
    cap = torch.tensor([0.4, 0.0, 0.9165], dtype=torch.float64)
    seen = (_cap_blocked(dirs, cap, 0.5) > 0).expand(3, -1).numpy()
    bits = torch.from_numpy(np.packbits(seen, axis=1))
    normal = _unit(torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.6, 0.8], [0.3, 0.0, 0.9]], dtype=torch.float64))

    def f(raw, log_lam):
        return lobe_visibility_bits(normal, bits, dirs, _unit(raw), torch.exp(log_lam))

    raw = torch.tensor([[0.3, 0.1, 1.0], [-0.2, 0.4, 0.9]], dtype=torch.float64, requires_grad=True)
    log_lam = torch.tensor([[1.0], [2.5]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(f, (raw, log_lam))


def test_a_wrong_block_in_the_backward_is_caught(monkeypatch):
    """Mutation: every block one point short (its last point's cosines and visibility zeroed);
    the comparison above must fail."""
    real = visibility_module._VisibleSums._blocks

    def short(normal, bits, directions, products):
        for start, stop, both in real(normal, bits, directions, products):
            both, n = both.clone(), stop - start
            both[n - 1], both[-1] = 0.0, 0.0  # the last point's lit and whole rows
            yield start, stop, both

    monkeypatch.setattr(visibility_module._VisibleSums, "_blocks", staticmethod(short))
    with pytest.raises(AssertionError):
        test_the_fused_blocks_equal_the_matrix_form_in_value_and_gradient(torch.float64)


def test_unpack_bits_is_numpys_layout():
    rng = np.random.default_rng(0)
    visible = rng.random((7, 40)) > 0.5
    packed = np.packbits(visible, axis=1)
    np.testing.assert_array_equal(unpack_bits(torch.from_numpy(packed), 40).numpy(), visible.astype(np.float32))


def test_blend_traced_is_continuous_in_the_sharpness():
    q = torch.full((1, 4), 0.2)
    t = torch.full((1, 4), 0.8)
    lam = torch.tensor([[10.0], [20.0], [30.0], [40.0]])
    out = blend_traced(q, t, lam, resolvable=20.0)
    torch.testing.assert_close(out, torch.tensor([[0.2, 0.2, 0.2 + 0.6 * math.log2(1.5), 0.8]]))


def _scene(n=30, k=5, seed=0):
    g = torch.Generator().manual_seed(seed)
    normal = _unit(torch.randn(n, 3, generator=g, dtype=torch.float64))
    view = _unit(normal + 0.6 * _unit(torch.randn(n, 3, generator=g, dtype=torch.float64)))
    light = SGLight(
        _unit(torch.randn(k, 3, generator=g, dtype=torch.float64)),
        torch.rand(k, 1, generator=g, dtype=torch.float64) * 30 + 1,
        torch.rand(k, 3, generator=g, dtype=torch.float64),
    )
    rough = torch.rand(n, 1, generator=g, dtype=torch.float64) * 0.8 + 0.15
    colour = torch.rand(n, 3, generator=g, dtype=torch.float64)
    return normal, view, light, rough, colour


@pytest.mark.parametrize(
    "term",
    ["diffuse", "diffuse_reference", "diffuse_gltf", "isotropic", "isotropic_reference", "split_sum", "fitted"],
)
def test_each_term_scales_each_lobe_by_its_share(term):
    """A share the same at every point is the light with that lobe dimmed by it: every term of the
    shading, shadowed, against the same term under the dimmed light."""
    normal, view, light, rough, colour = _scene()
    share = torch.tensor([0.0, 0.25, 1.0, 0.6, 0.9], dtype=torch.float64)
    dimmed = SGLight(light.axis, light.sharpness, light.amplitude * share[:, None])
    per_point = share.expand(normal.shape[0], -1)
    fns = {
        "diffuse": lambda lt, v: diffuse_radiance(normal, colour, lt, v),
        "diffuse_reference": lambda lt, v: diffuse_radiance_reference(normal, colour, lt, v),
        "diffuse_gltf": lambda lt, v: diffuse_radiance_gltf(normal, view, colour, lt, v),
        "isotropic": lambda lt, v: specular_radiance(normal, view, colour, rough, lt, v),
        "isotropic_reference": lambda lt, v: specular_radiance_reference(normal, view, colour, rough, lt, v),
        # the split sum's average is clamped to the light's brightest sum, which dimming changes:
        # keep it from binding with a tiny share offset in neither case
        "split_sum": lambda lt, v: specular_radiance_split_sum(normal, view, colour, rough, lt, GLTF, v),
        "fitted": lambda lt, v: specular_radiance_fitted(normal, view, colour, rough, lt, GLTF, v),
    }
    fn = fns[term]
    torch.testing.assert_close(fn(light, per_point), fn(dimmed, None), rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_shade_passes_the_shares_to_both_terms(seed):
    """Shares scale each lobe in both terms: they darken, except by at most the clamped cosine's
    SG fit's dip below zero at the horizon (``mu e^-lambda - offset``, -0.0063), which a shadowed
    lobe no longer subtracts: per lobe at most that dip times the lobe's integral ``2 pi / lambda``.
    (The shares were unseeded: a draw that shadowed such a lobe brightened a point by 5.7e-4.)"""
    normal, view, light, rough, colour = _scene()
    share = torch.rand(normal.shape[0], light.axis.shape[0], dtype=torch.float64, generator=torch.Generator().manual_seed(seed))
    dip = -(COS_MU * math.exp(-COS_LAMBDA) - COS_OFFSET)
    brighter = colour / math.pi * (dip * 2 * math.pi / light.sharpness * light.amplitude).sum(0)
    tango = Material(colour, colour, rough)
    for lobe in ("isotropic", "split_sum", "fitted"):
        s = TANGO.shade(normal, view, tango, light, lobe, visibility=share)
        u = TANGO.shade(normal, view, tango, light, lobe)
        assert (s.diffuse < u.diffuse + brighter + 1e-12).all() and (s.specular < u.specular + 1e-12).all()
        assert (s.diffuse < u.diffuse - 1e-6).any() and (s.specular < u.specular - 1e-6).any()
    gltf = Material.gltf(colour, torch.full_like(rough, 0.5), rough)
    s = GLTF.shade(normal, view, gltf, light, "fitted", visibility=share)
    u = GLTF.shade(normal, view, gltf, light, "fitted")
    assert (s.diffuse < u.diffuse - 1e-6).any() and (s.specular < u.specular - 1e-6).any()
    blocked = GLTF.shade(normal, view, gltf, light, "fitted", visibility=torch.zeros_like(share))
    assert float(blocked.rgb.abs().max()) == 0.0


def _bf16_case(n_pts: int = 3000, count: int = 1024, lobes: int = 16, seed: int = 5):
    """Points with the visibility of a tilted plane through them (a half-space blocked, as beside
    a wall), lobes of sharpness 1 to 1,000 (the training's quadrature takes every lobe, sharp ones
    included) pointing anywhere."""
    g = torch.Generator().manual_seed(seed)
    dirs = torch.tensor(fibonacci_directions(count), dtype=torch.float32)
    normal = _unit(torch.randn(n_pts, 3, generator=g))
    wall = _unit(torch.randn(n_pts, 3, generator=g))
    seen = (wall @ dirs.T) > 0.2
    bits = torch.from_numpy(np.packbits(seen.numpy(), axis=1))
    axis = _unit(torch.randn(lobes, 3, generator=g))
    lam = torch.exp(torch.rand(lobes, 1, generator=g) * math.log(1e3))
    weight = torch.rand(n_pts, lobes, generator=g)
    return normal, bits, dirs, axis, lam, weight


def _share_and_grads(normal, bits, dirs, axis, lam, weight, bf16: bool):
    a, s_ = axis.clone().requires_grad_(), lam.clone().requires_grad_()
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
        out = lobe_visibility_bits(normal, bits, dirs, _unit(a), s_)
    assert out.dtype == torch.float32
    (out * weight).sum().backward()
    return out.detach(), a.grad, s_.grad


def test_bfloat16_products_agree_with_float32():
    """Under a bfloat16 autocast (the networks' lever in training) the quadrature's products run in
    bfloat16: each share within 0.01 of float32's (each sum rounded to 8 bits of mantissa: at most
    2^-8 of it, so the ratio within about 2^-7), and the gradients to the axes and sharpnesses at a
    cosine above 0.999 to float32's (the backward's two sums, of opposite sign, meet inside one
    product, from the gradient split in two bfloat16 parts)."""
    case = _bf16_case()
    ref = _share_and_grads(*case, bf16=False)
    got = _share_and_grads(*case, bf16=True)
    assert float((got[0] - ref[0]).abs().max()) < 0.01
    assert float((got[0] - ref[0]).abs().mean()) < 1e-3
    for g, r in zip(got[1:], ref[1:], strict=True):
        assert float(torch.nn.functional.cosine_similarity(g.flatten(), r.flatten(), dim=0)) > 0.999


def test_bfloat16_products_are_taken_and_the_weights_kept_in_float32(monkeypatch):
    """The products really run in bfloat16 under the autocast (their dtype observed), and the
    lobes' weights do not: weights from bfloat16 cosines (the autocast applied to them) err by
    lam / 256 in the exponent (the shares by 0.7 at sharpness 1,000: the mutation below)."""
    seen = []
    real = visibility_module._VisibleSums._blocks

    def spy(normal, bits, directions, products):
        seen.append((products, directions.dtype))
        yield from real(normal, bits, directions, products)

    monkeypatch.setattr(visibility_module._VisibleSums, "_blocks", staticmethod(spy))
    case = _bf16_case(n_pts=600)
    _share_and_grads(*case, bf16=True)
    assert seen and all(p == torch.bfloat16 and d == torch.float32 for p, d in seen)
    seen.clear()
    _share_and_grads(*case, bf16=False)
    assert seen and all(p == torch.float32 for p, _ in seen)
    # float64 work is never rounded
    normal, bits, dirs, axis, lam, _ = case
    with torch.autocast("cpu", dtype=torch.bfloat16):
        lobe_visibility_bits(normal.double(), bits, dirs.double(), axis.double(), lam.double())
    assert seen[-1][0] == torch.float64


def test_the_autocast_left_on_around_the_weights_is_caught(monkeypatch):
    """Mutation: without the float32 region around the weights the agreement test fails."""
    monkeypatch.setattr(visibility_module, "_full_precision", lambda device: contextlib.nullcontext())
    with pytest.raises(AssertionError):
        test_bfloat16_products_agree_with_float32()


def test_bfloat16_products_finite_at_the_extremes():
    """Fully open and fully blocked points, lobes below the horizon, sharpness 1e-4 to 1e5 through
    the bfloat16 products: shares in [0, 1] (to bfloat16's rounding), finite gradients."""
    dirs = torch.tensor(fibonacci_directions(512))
    normal = torch.tensor([[0.0, 0.0, 1.0]] * 3)
    visible = torch.stack([torch.ones(512), torch.zeros(512), (torch.arange(512) % 2).float()]) > 0
    bits = torch.from_numpy(np.packbits(visible.numpy(), axis=1))
    raw, sharp = _extreme_lobes(torch.float32)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        v = lobe_visibility_bits(normal, bits, dirs, _unit(raw), sharp)
    assert torch.isfinite(v).all() and (v >= 0).all() and (v <= 1 + 2**-7).all()
    v.sum().backward()
    assert torch.isfinite(sharp.grad).all() and torch.isfinite(raw.grad).all()
    assert float((v.detach()[0] - 1).abs().max()) <= 2**-7  # fully open
