"""Colour encoding: the sRGB transfer function and its inverse, for tensors and numpy arrays side by
side, and 8-bit quantisation. IEC 61966-2-1: ``C_srgb = 12.92 C`` for ``C <= 0.0031308``, else
``1.055 C^(1/2.4) - 0.055``; inverse threshold 0.04045. Inputs are clamped to [0, 1] first."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

#: the linear-segment thresholds of the sRGB curve (linear side, encoded side)
SRGB_LINEAR_BELOW = 0.0031308
SRGB_ENCODED_BELOW = 0.04045


def linear_to_srgb(x: Tensor) -> Tensor:
    """sRGB encoding of ``clamp(x, 0, 1)`` (any shape); its linear toe keeps gradients finite at 0."""
    x = x.clamp(0.0, 1.0)
    return torch.where(x <= SRGB_LINEAR_BELOW, 12.92 * x, 1.055 * torch.pow(x.clamp(min=SRGB_LINEAR_BELOW), 1 / 2.4) - 0.055)


def srgb_encode(x: np.ndarray) -> np.ndarray:
    """numpy twin of :func:`linear_to_srgb` (float64 for float64 input)."""
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= SRGB_LINEAR_BELOW, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def srgb_decode(x: np.ndarray) -> np.ndarray:
    """Inverse of :func:`srgb_encode`: sRGB-encoded values in [0, 1] to linear."""
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= SRGB_ENCODED_BELOW, x / 12.92, np.power((x + 0.055) / 1.055, 2.4))


def to_u8(x: np.ndarray) -> np.ndarray:
    """Values in [0, 1] to ``uint8`` (rounded to nearest, clipped)."""
    return np.clip(np.rint(x * 255.0), 0, 255).astype(np.uint8)
