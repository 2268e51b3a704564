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


#: points per block of the fused quadrature on a CPU: a block's two stacked (points, directions)
#: matrices (4 MB at 1,024 directions in float32, 2 MB in bfloat16) stay near the core between the
#: operations that use them
VISIBILITY_BLOCK = 512
#: the most bytes of a block's stacked matrices on a GPU: there a block's operations are kernel
#: launches whose cost does not depend on its size (a step's shares in blocks of 512 points were
#: about 50 blocks of 8 launches forward and 11 backward), and memory is plentiful, so a step's
#: points go in one block (256 MiB: 65,536 points at 512 directions in float32)
GPU_BLOCK_BYTES = 256 * 2**20


def visibility_block(device: torch.device, directions: int, products: torch.dtype) -> int:
    """Points per block of the fused quadrature (:class:`_VisibleSums`) on ``device`` for
    ``directions`` stored directions with products in ``products``: :data:`VISIBILITY_BLOCK` on a
    CPU (cache-sized), else as many as :data:`GPU_BLOCK_BYTES` holds (at least as many). The
    shares do not depend on it beyond the order of float sums (tested)."""
    if device.type == "cpu":
        return VISIBILITY_BLOCK
    itemsize = torch.empty((), dtype=products).element_size()
    return max(VISIBILITY_BLOCK, GPU_BLOCK_BYTES // (2 * directions * itemsize))


class _VisibleSums(torch.autograd.Function):
    """Each lobe's visible share ``(lit + e) / (lit + blocked + e)`` (``e`` :data:`_EMPTY`) from
    ``lit = (c * v) @ w.T`` and ``blocked = (c * (1 - v)) @ w.T``, with ``c = max(normal @
    directions.T, 0)`` and ``v`` the unpacked bits, block by block of points
    (:func:`visibility_block`: cache-sized on a CPU, a whole step's on a GPU), without keeping
    the ``(N, D)`` matrices: the backward (to ``w`` alone: the normals and the bits are data)
    rebuilds each block's and adds ``a.T @ (c * v) + b.T @ (c * (1 - v))`` with the share's
    derivatives ``a = g blocked / S^2`` and ``b = -g (lit + e) / S^2``, ``S`` the
    denominator: products, never differences. (Through autograd's ``1 / S - (lit + e) / S^2``
    the two terms cancel where a point's share is near 1, and their float32 rounding, times a
    sun's sharpness, made its axis's gradient 1e4 times too large at an open point; found by
    ``benchmarks/render/precision.py``.) Each block's two matrices are stacked, ``[c * v; c * (1 - v)]
    (2 n, D)``, so that each block is one product each way; ``products``: the dtype they are built
    and multiplied in (the share is returned in ``w``'s)."""

    @staticmethod
    def _blocks(normal: Tensor, bits: Tensor, directions: Tensor, products: torch.dtype):
        """``(start, stop, [c * v; c * (1 - v)])`` per block of points, ``(2 (stop - start), D)``
        in ``products``."""
        count = directions.shape[0]
        block = visibility_block(normal.device, count, products)
        for start in range(0, normal.shape[0], block):
            stop = min(start + block, normal.shape[0])
            n = stop - start
            both = torch.empty(2 * n, count, dtype=products, device=normal.device)
            cos = both[n:]
            cos.copy_(torch.mm(normal[start:stop], directions.T).clamp_(min=0.0))
            torch.mul(cos, unpack_bits(bits[start:stop], count, products), out=both[:n])
            cos -= both[:n]  # exact: v is 0 or 1
            yield start, stop, both

    @staticmethod
    def forward(ctx, normal: Tensor, bits: Tensor, directions: Tensor, w: Tensor, products: torch.dtype):
        wt = w.T.to(products).contiguous()
        lit, blocked = [], []
        for start, stop, both in _VisibleSums._blocks(normal, bits, directions, products):
            sums = torch.mm(both, wt)
            lit.append(sums[: stop - start])
            blocked.append(sums[stop - start :])
        lit, blocked = torch.cat(lit).to(w.dtype), torch.cat(blocked).to(w.dtype)
        ctx.save_for_backward(normal, bits, directions, lit, blocked)
        ctx.products = products
        return (lit + _EMPTY) / (lit + blocked + _EMPTY)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: Tensor):
        normal, bits, directions, lit, blocked = ctx.saved_tensors
        whole = lit + blocked + _EMPTY  # (its square underflows in float32 where both sums vanish)
        g_lit, g_blocked = grad * (blocked / whole) / whole, -grad * ((lit + _EMPTY) / whole) / whole
        g_w = torch.zeros(grad.shape[1], directions.shape[0], dtype=grad.dtype, device=grad.device)
        k = grad.shape[1]
        for start, stop, both in _VisibleSums._blocks(normal, bits, directions, ctx.products):
            g = torch.cat([g_lit[start:stop], g_blocked[start:stop]])
            sums = torch.mm(_split(g, ctx.products).T, both).to(g_w.dtype)
            g_w += sums if sums.shape[0] == k else sums[:k] + sums[k:]
        return None, None, None, g_w, None


def _split(x: Tensor, dtype: torch.dtype) -> Tensor:
    """``(n, K)`` -> ``(n, 2 K)``: ``x`` rounded to ``dtype`` and the rounding's remainder, side by
    side (their sum holds ``x`` to about twice ``dtype``'s mantissa), or ``(n, K)`` of ``x`` alone
    when ``dtype`` is ``x``'s. Rounded once, the backward's coefficients left the gradients of very
    broad lobes (sharpness 1e-3, whose shares barely move) up to 1.9 times their norm off float32's,
    against 0.5 in two parts (``benchmarks/render/precision.py``'s bfloat16 column; 4% of the norm when the
    backward summed the lit and the whole sums' cancelling terms)."""
    if dtype == x.dtype:
        return x
    high = x.to(dtype)
    return torch.cat([high, (x - high.to(x.dtype)).to(dtype)], dim=1)


def lobe_visibility_bits(normal: Tensor, bits: Tensor, directions: Tensor, axis: Tensor, sharpness: Tensor) -> Tensor:
    """:func:`lobe_visibility` from the packed bits ``(N, ceil(D / 8)) uint8`` (as stored,
    :func:`unpack_bits`'s order), fused: the two sums block by block of points with a hand-written
    backward (:class:`_VisibleSums`), so that the ``(N, D)`` matrices of cosines and visibility
    (35 MB each at 17,000 points and the default 512 directions) are never held, nor read back
    from memory.
    The same value and gradient to the lobes' axes and sharpnesses (tested against
    :func:`lobe_visibility` in float64); no gradient to the normals (fixed data).

    Under a bfloat16 autocast (:func:`products_dtype`: the networks' bfloat16 lever in training)
    the matrix products take bfloat16 operands and results (the CPU's AMX or AVX-512 BF16 units,
    a GPU's tensor cores): the cosines and weights rounded to 8 bits of mantissa, each sum to 8
    bits; the shares within 0.01 of float32's and their gradients' cosine above 0.999 (tested:
    ``tests/render/test_lobe_visibility.py``)."""
    work = torch.promote_types(normal.dtype, torch.float32)
    products = products_dtype(normal.device, work)
    # the weights and cosines in ``work`` whatever the autocast: a lobe's exponent, lam (xi . d - m),
    # from bfloat16 cosines errs by lam / 256 (8% at the resolvable sharpness 20)
    with _full_precision(normal.device):
        normal, directions = normal.to(work).detach().contiguous(), directions.to(work).detach()
        w = _weights(directions, axis.to(work), sharpness.to(work))  # (K, D)
        # weights below the smallest normal float are 0 to the sums' precision, and as subnormal
        # operands they made the products several times slower (measured: 67 ms against 28 ms)
        w = torch.where(w >= torch.finfo(work).tiny, w, torch.zeros_like(w))
        return _VisibleSums.apply(normal, bits, directions, w, products)


def _full_precision(device: torch.device):
    """A region where no autocast applies (the weights and cosines, whatever the caller's)."""
    return torch.autocast(device.type, enabled=False)


def products_dtype(device: torch.device, work: torch.dtype) -> torch.dtype:
    """The dtype of the quadrature's matrix products: bfloat16 inside an enabled bfloat16 autocast
    on ``device`` (the caller's choice: :meth:`~stages.model.field.StyleField.shade` opens one
    where the networks run in bfloat16), else ``work``; float64 work is never rounded."""
    kind = device.type
    if work == torch.float32 and torch.is_autocast_enabled(kind) and torch.get_autocast_dtype(kind) == torch.bfloat16:
        return torch.bfloat16
    return work


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
    0/1 in ``dtype``, by a table of each byte's eight bits (3x faster than shifting and masking
    each bit, measured at 512 x 1,024 on the development machine; tested against numpy)."""
    table = _bit_table(dtype, bits.device)
    unpacked = torch.nn.functional.embedding(bits.long(), table)  # (N, count / 8, 8)
    return unpacked.reshape(bits.shape[0], -1)[:, :count]


_BIT_TABLES: dict[tuple[torch.dtype, torch.device], Tensor] = {}


def _bit_table(dtype: torch.dtype, device: torch.device) -> Tensor:
    """``(256, 8)``: row ``b`` the bits of byte ``b``, most significant first, in ``dtype``."""
    key = (dtype, device)
    if key not in _BIT_TABLES:
        byte = torch.arange(256, device=device)[:, None]
        _BIT_TABLES[key] = ((byte >> torch.arange(7, -1, -1, device=device)) & 1).to(dtype)
    return _BIT_TABLES[key]


def blend_traced(quadrature: Tensor, traced: Tensor, sharpness: Tensor, resolvable: float) -> Tensor:
    """Each lobe's share from the quadrature where the direction set resolves the lobe and from
    rays traced along the lobe where it does not: weight ``t = clamp(log2(lam / resolvable), 0, 1)``
    on ``traced``, so the quadrature alone up to ``resolvable``, the rays alone from twice it, and a
    blend continuous in the sharpness between. ``quadrature, traced (N, K)``, ``sharpness (K, 1)``."""
    t = torch.clamp(torch.log2(sharpness.T / resolvable), min=0.0, max=1.0)  # (1, K)
    return quadrature * (1.0 - t) + traced.to(quadrature.dtype) * t
