"""sRGB encoding (IEC 61966-2-1) in torch and numpy: one curve, written out here from the standard."""

import numpy as np
import pytest
import torch

from stages.render.color import linear_to_srgb, srgb_decode, srgb_encode, to_u8

X = np.concatenate([np.linspace(0, 0.01, 101), np.linspace(0.01, 1, 991), [1.5, -0.2]])


def srgb_reference(x: float) -> float:
    """IEC 61966-2-1: 12.92 C below 0.0031308, else 1.055 C^(1/2.4) - 0.055, on C clamped to [0, 1]."""
    c = min(max(x, 0.0), 1.0)
    return 12.92 * c if c <= 0.0031308 else 1.055 * c ** (1 / 2.4) - 0.055


def test_torch_and_numpy_encodings_follow_the_standard():
    expected = np.array([srgb_reference(x) for x in X])
    np.testing.assert_allclose(srgb_encode(X), expected, rtol=0, atol=1e-15)
    np.testing.assert_allclose(linear_to_srgb(torch.from_numpy(X)).numpy(), expected, rtol=0, atol=1e-12)


def test_decode_inverts_encode_and_quantisation_rounds():
    x = np.linspace(0, 1, 1001)
    np.testing.assert_allclose(srgb_decode(srgb_encode(x)), x, atol=1e-12)
    assert to_u8(np.array([0.0, 0.5 / 255, 0.6 / 255, 1.0, 2.0])).tolist() == [0, 0, 1, 255, 255]


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_gradient_is_finite_at_and_below_zero(dtype):
    x = torch.tensor([-1.0, 0.0, 1e-8, 0.5, 1.0], dtype=dtype, requires_grad=True)
    linear_to_srgb(x).sum().backward()
    assert torch.isfinite(x.grad).all()
