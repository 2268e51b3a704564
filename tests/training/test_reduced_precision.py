"""Training stays finite when the matrix products run at reduced precision: TF32 emulated on the
CPU by rounding every float32 input of a matrix product to TF32's 10-bit mantissa (as the tensor
cores of an Ampere or later GPU do with ``allow_tf32``)."""

from __future__ import annotations

import math

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from stages.config.sections import OptimizeSettings
from stages.core.provenance import Timer
from stages.geometry.raycache import RayCache
from stages.render.sg import COS_LAMBDA, sg_hemisphere_integral
from stages.render.shading import product_terms
from stages.training.optimizer import Optimizer


def tf32(x: torch.Tensor) -> torch.Tensor:
    """float32 rounded to a 10-bit mantissa (to nearest, ties to even), on the bits."""
    i = x.contiguous().view(torch.int32)
    i = (i + 0x0FFF + ((i >> 13) & 1)) & ~0x1FFF
    return i.view(torch.float32)


MATRIX_PRODUCTS = {
    torch.ops.aten.mm.default,
    torch.ops.aten.addmm.default,
    torch.ops.aten.bmm.default,
    torch.ops.aten.baddbmm.default,
    torch.ops.mkldnn._linear_pointwise.default,  # float32 linear layers by oneDNN (optimize.onednn_products)
}


class EmulatedTF32(TorchDispatchMode):
    """Every float32 input of a matrix product rounded to TF32 (accumulation stays float32)."""

    def __init__(self) -> None:
        super().__init__()
        self.products = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if func in MATRIX_PRODUCTS:
            self.products += 1
            args = tuple(tf32(a) if isinstance(a, torch.Tensor) and a.dtype == torch.float32 else a for a in args)
        return func(*args, **(kwargs or {}))


def test_the_emulation_rounds_to_ten_mantissa_bits():
    # the textbook rounding in [1, 2): to the nearest multiple of 2^-10, ties to even (Python's round)
    x = torch.tensor([1.0 + k * 2.0**-12 for k in range(64)] + [1.5 - 2.0**-20], dtype=torch.float32)
    expected = [round(float(v) * 2**10) / 2**10 for v in x]
    assert tf32(x).tolist() == expected
    y = torch.tensor([-3.0e-5, 7.7e3], dtype=torch.float32)  # sign and exponent kept
    for v, r in zip(y.tolist(), tf32(y).tolist(), strict=True):
        m, e = math.frexp(v)
        assert r == math.ldexp(round(m * 2**11) / 2**11, e)


def test_lobes_of_equal_sharpness_and_opposite_axes_have_finite_gradients():
    """The product of two lobes of equal sharpness and opposite axes has sharpness 0; its hemisphere
    integral is then 2 pi (a lobe that is 1 everywhere), with finite gradients."""
    lam = torch.tensor([[COS_LAMBDA]], requires_grad=True)
    cos = torch.tensor([[-1.0]], requires_grad=True)
    lam_q, log_q = product_terms(lam, torch.tensor(COS_LAMBDA), cos)
    value = sg_hemisphere_integral(lam_q, torch.ones_like(lam_q))
    assert float(value) == pytest.approx(2 * math.pi, rel=1e-6)
    (value + log_q).sum().backward()
    assert torch.isfinite(lam.grad).all() and torch.isfinite(cos.grad).all()
    zero = torch.zeros(1, 1, requires_grad=True)
    sg_hemisphere_integral(zero, torch.tensor([[0.3]])).sum().backward()
    assert torch.isfinite(zero.grad).all()


@pytest.mark.slow
def test_200_steps_with_emulated_tf32_stay_finite(cache):
    """Light lobes started at the cosine lobe's own sharpness: a light lobe's cosine with a normal
    rounded to -1 by a TF32 product made the product of the two lobes sharpness 0, the hemisphere
    integral 0/0 and the loss non-finite at step 1 (float32 stayed finite)."""
    s = OptimizeSettings(
        iterations=200,
        guidance="image",
        target_renderer="sg",
        image_size=64,
        width=32,
        light_lobes=16,
        crops=0,
        light_init="broad",
        light_init_sharpness=COS_LAMBDA,
        bf16_networks="off",
        compile_shading="off",
        lr=5e-3,
        milestones=(120, 170),
        gamma=0.3,
    )
    run = Optimizer(s, RayCache(cache / "train.npz"), "p", "cpu")
    mode = EmulatedTF32()
    with mode:
        losses = [run.step(Timer())["loss"] for _ in range(200)]
    assert mode.products > 200 and all(math.isfinite(x) for x in losses)
    assert losses[-1] < losses[0]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_half_vector_terms_finite_where_the_product_axis_is_opposite_the_view(dtype):
    """The fitted lobe's half vector between a product lobe's axis and the view: where that axis is
    exactly opposite the view (``xi' + v = 0``, the half vector undefined) and where the half vector
    lies below the horizon, values and gradients stay finite. ``|xi' + v|`` as a bare square root
    had an infinite derivative at 0: a 3,560-step run's loss was non-finite at step 1,499."""
    from stages.render.fitted_lobe import LightCosines, LobeMean, _half_vector_terms

    nv = torch.tensor([[0.6], [0.6], [0.2]], dtype=dtype)
    sin_nv = torch.sqrt(1 - nv**2)
    theta = torch.tensor([[0.3], [0.3], [1.2]], dtype=dtype)
    kappa = torch.tensor([[5.0], [5.0], [40.0]], dtype=dtype)
    # one light lobe; its sharpness and axis chosen so that xi' = (kappa mu + nu xi) / lam_p is -v
    # (rows 0 and 1: exactly, and 1e-7 off) or points below the horizon (row 2)
    nl = torch.tensor([[-0.6], [-0.6 + 1e-7], [-0.9]], dtype=dtype, requires_grad=True)
    tl = (-sin_nv).clone().requires_grad_()
    bl = torch.zeros(3, 1, dtype=dtype, requires_grad=True)
    nu = torch.ones(1, 1, dtype=dtype, requires_grad=True)
    lam_p = torch.ones(3, 1, dtype=dtype, requires_grad=True)
    sharp = nu.expand(1, 1)
    # with nu = lam_p = 1 and kappa sin(theta) folded into tl, t_x = tl - kappa sin(theta) / lam_p
    tl_in = tl + kappa * torch.sin(theta)
    c = LightCosines(nl, nl, tl_in, nv, sin_nv, bl)
    # the lobe's mean at theta from the normal; mu . xi as the product lobe's sharpness implies it,
    # lam_p^2 = kappa^2 + nu^2 + 2 kappa nu (mu . xi), so that lam_p - kappa is what it is here
    mean = LobeMean(torch.cos(theta), torch.sin(theta), torch.zeros_like(theta), sin_nv - torch.sin(theta))
    cos_ml = (lam_p**2 - kappa**2 - nu**2) / (2 * kappa * nu)
    one_minus_nh, one_minus_vh = _half_vector_terms(nl, tl_in, c, mean, cos_ml, kappa, sharp, lam_p)
    assert torch.isfinite(one_minus_nh).all() and torch.isfinite(one_minus_vh).all()
    assert float(one_minus_vh[0]) == pytest.approx(1.0)  # v.h = |xi' + v| / 2 = 0
    grads = torch.autograd.grad((one_minus_nh.sum() + one_minus_vh.sum()), [nl, tl, bl, nu, lam_p])
    assert all(torch.isfinite(g).all() for g in grads)
