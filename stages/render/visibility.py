"""Shadows in the closed-form SG shading: each light lobe's visible share at each point, by
quadrature of the lobe over a fixed direction set whose visibility was traced once
(:mod:`stages.geometry.visibility`), differentiable in the lobe's axis and sharpness (issue 32).

For a point with oriented normal ``n`` seeing direction ``d`` (``v(d)`` 1 or 0) and a unit SG lobe
``G(d) = exp(lam (xi . d - 1))``, the visible share is

    V = int v(d) G(d) max(n . d, 0) dd / int G(d) max(n . d, 0) dd,

and the shading multiplies each lobe's term (diffuse and specular) by it. Over ``D`` directions
of equal solid angle both integrals are sums, so for ``N`` points and ``K`` lobes ``V`` is two
matrix products of ``(N, D)`` by ``(D, K)``. The quadrature resolves a lobe whose angular width
``1 / sqrt(lam)`` is at least twice the directions' spacing ``sqrt(4 pi / D)``: ``lam <= D /
(16 pi)`` (:func:`resolvable_sharpness`; a shadow's edge across the lobe's axis is then within 0.04
of the continuous share, tested); a sharper lobe (a sun) sees the visibility of the few directions
nearest its axis, and is handled by rays traced along it (:func:`blend_traced`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

#: added to both sums: where a lobe lies wholly below a point's horizon (both vanish) its share is
#: 1, and the lobe contributes nothing there anyway
_EMPTY = 1e-20


def resolvable_sharpness(count: int) -> float:
    """The sharpest lobe a set of ``count`` directions resolves: ``count / (16 pi)`` (the lobe's
    angular width ``1 / sqrt(lam)`` twice the spacing ``sqrt(4 pi / count)``): 20 for 1024
    directions, 81 for 4096. Measured against the continuous share with a shadow's edge on the
    lobe's axis (the worst case): 0.038 off at 1024 directions and 0.009 at 4096 there, 0.06 and
    0.05 at four times that sharpness (tests/render/test_visibility.py)."""
    return count / (16.0 * math.pi)


def _weights(directions: Tensor, axis: Tensor, sharpness: Tensor) -> Tensor:
    """``exp(lam_k (xi_k . d - m_k)) (K, D)`` with ``m_k`` the largest ``xi_k . d`` over the set
    (a factor common to both sums: no lobe underflows everywhere, whatever its sharpness)."""
    cos = axis @ directions.T  # (K, D)
    top = cos.detach().amax(dim=1, keepdim=True)
    return torch.exp(sharpness * (cos - top))


def lobe_visibility(normal: Tensor, visible: Tensor, directions: Tensor, axis: Tensor, sharpness: Tensor) -> Tensor:
    """Each lobe's visible share at each point -> ``(N, K)`` in [0, 1] (the module's ``V``).

    ``normal (N, 3)`` unit, oriented to the side the point is seen from (the side its visibility
    was traced for); ``visible (N, D)`` 0/1 (any float dtype: :func:`unpack_bits`);
    ``directions (D, 3)`` unit, of equal solid angle; the light's ``axis (K, 3)`` unit and
    ``sharpness (K, 1)`` in [1e-4, 1e5]. Exact for the stored directions' quadrature; against the
    continuous integral, see :func:`resolvable_sharpness`. Finite with finite gradients in the axis
    and sharpness everywhere, fully open and fully blocked points included."""
    work = torch.promote_types(normal.dtype, torch.float32)
    normal, directions = normal.to(work), directions.to(work)
    w = _weights(directions, axis.to(work), sharpness.to(work))  # (K, D)
    cos = torch.clamp(normal @ directions.T, min=0.0)  # (N, D)
    lit = (cos * visible.to(work)) @ w.T
    whole = cos @ w.T
    return (lit + _EMPTY) / (whole + _EMPTY)


#: points per block of the fused quadrature: a block's (points, directions) matrices (2 MB at
#: 1,024 directions in float32) stay in a core's cache between the operations that use them
VISIBILITY_BLOCK = 512


class _VisibleSums(torch.autograd.Function):
    """``lit = (c * v) @ w.T`` and ``whole = c @ w.T`` with ``c = max(normal @ directions.T, 0)``
    and ``v`` the unpacked bits, block by block of :data:`VISIBILITY_BLOCK` points, without
    keeping the ``(N, D)`` matrices: the backward (to ``w`` alone: the normals and the bits are
    data) rebuilds each block's and adds ``g_lit.T @ (c * v) + g_whole.T @ c``."""

    @staticmethod
    def _blocks(normal: Tensor, bits: Tensor, directions: Tensor):
        for start in range(0, normal.shape[0], VISIBILITY_BLOCK):
            stop = min(start + VISIBILITY_BLOCK, normal.shape[0])
            cos = torch.mm(normal[start:stop], directions.T).clamp_(min=0.0)
            yield start, stop, cos, cos * unpack_bits(bits[start:stop], directions.shape[0], cos.dtype)

    @staticmethod
    def forward(ctx, normal: Tensor, bits: Tensor, directions: Tensor, w: Tensor) -> tuple[Tensor, Tensor]:
        wt = w.T.contiguous()
        lit, whole = [], []
        for _, _, cos, seen in _VisibleSums._blocks(normal, bits, directions):
            lit.append(seen @ wt)
            whole.append(cos @ wt)
        ctx.save_for_backward(normal, bits, directions)
        return torch.cat(lit), torch.cat(whole)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_lit: Tensor, g_whole: Tensor):
        normal, bits, directions = ctx.saved_tensors
        g_w = torch.zeros(g_lit.shape[1], directions.shape[0], dtype=g_lit.dtype, device=g_lit.device)
        for start, stop, cos, seen in _VisibleSums._blocks(normal, bits, directions):
            g_w.addmm_(g_lit[start:stop].T, seen).addmm_(g_whole[start:stop].T, cos)
        return None, None, None, g_w


def lobe_visibility_bits(normal: Tensor, bits: Tensor, directions: Tensor, axis: Tensor, sharpness: Tensor) -> Tensor:
    """:func:`lobe_visibility` from the packed bits ``(N, ceil(D / 8)) uint8`` (as stored,
    :func:`unpack_bits`'s order), fused: the two sums block by block of points with a hand-written
    backward (:class:`_VisibleSums`), so that the ``(N, D)`` matrices of cosines and visibility
    (70 MB each at 17,000 points and 1,024 directions) are never held, nor read back from memory.
    The same value and gradient to the lobes' axes and sharpnesses (tested against
    :func:`lobe_visibility` in float64); no gradient to the normals (fixed data)."""
    work = torch.promote_types(normal.dtype, torch.float32)
    normal, directions = normal.to(work).detach().contiguous(), directions.to(work).detach()
    w = _weights(directions, axis.to(work), sharpness.to(work))  # (K, D)
    # weights below the smallest normal float are 0 to the sums' precision, and as subnormal
    # operands they made the products several times slower (measured: 67 ms against 28 ms)
    w = torch.where(w >= torch.finfo(work).tiny, w, torch.zeros_like(w))
    lit, whole = _VisibleSums.apply(normal, bits, directions, w)
    return (lit + _EMPTY) / (whole + _EMPTY)


def lobe_visibility_reference(normal: Tensor, visible: Tensor, directions: Tensor, axis: Tensor, sharpness: Tensor) -> Tensor:
    """:func:`lobe_visibility` written as its definition, one lobe at a time (the plain reference
    the matrix form is tested against)."""
    out = []
    for k in range(axis.shape[0]):
        g = torch.exp(sharpness[k] * (directions @ axis[k] - (directions @ axis[k]).detach().max()))  # (D,)
        cos = torch.clamp(normal @ directions.T, min=0.0)
        out.append(((visible * cos * g).sum(1) + _EMPTY) / ((cos * g).sum(1) + _EMPTY))
    return torch.stack(out, dim=1)


def unpack_bits(bits: Tensor, count: int, dtype: torch.dtype = torch.float32) -> Tensor:
    """``bits (N, count / 8) uint8`` (numpy's big-endian :func:`numpy.packbits`) -> ``(N, count)``
    0/1 in ``dtype``."""
    shifts = torch.arange(7, -1, -1, device=bits.device, dtype=torch.uint8)
    unpacked = (bits.unsqueeze(-1) >> shifts) & 1  # (N, count / 8, 8)
    return unpacked.reshape(bits.shape[0], -1)[:, :count].to(dtype)


def blend_traced(quadrature: Tensor, traced: Tensor, sharpness: Tensor, resolvable: float) -> Tensor:
    """Each lobe's share from the quadrature where the direction set resolves the lobe and from
    rays traced along the lobe where it does not: weight ``t = clamp(log2(lam / resolvable), 0, 1)``
    on ``traced``, so the quadrature alone up to ``resolvable``, the rays alone from twice it, and a
    blend continuous in the sharpness between. ``quadrature, traced (N, K)``, ``sharpness (K, 1)``."""
    t = torch.clamp(torch.log2(sharpness.T / resolvable), min=0.0, max=1.0)  # (1, K)
    return quadrature * (1.0 - t) + traced.to(quadrature.dtype) * t
