"""CLIP's image tower on a faster path: the same mathematics, shaped for a CPU's matrix kernels.

open_clip's vision transformer keeps its tokens batch-first ``(N, L, E)`` and calls
``torch.nn.MultiheadAttention(batch_first=True)``, which transposes them to ``(L, N, E)`` and runs
every projection on the strided view. On a CPU the backward of those projections goes through
``matmul``'s broadcast path (one copy of the weight per image, then ``bmm``): measured with
``python -m benchmarks.training.optimize --clip-only`` on this project's 2-core CPU, that made ViT-B-32's
forward+backward for 5 images about 1.5 times slower than needed in float32, and three times
slower in bfloat16 than in float32 (65% of it in ``aten::copy_``). Two more costs show under
bfloat16 autocast: the patch embedding's convolution backward (oneDNN's bfloat16 path, about 0.1 s
for 5 images) and the cast of the frozen weights to bfloat16 at every forward.

:func:`use_fast_tower` removes the three, each exactly:

* attention: :class:`BatchedMultiheadAttention` is ``nn.MultiheadAttention`` with the same
  parameters and state dict; for self-attention without masks (every block of CLIP's image tower)
  it computes multi-head scaled dot-product attention (Vaswani et al. 2017, "Attention Is All You
  Need", eq. 1 and Sec. 3.2.2) with plain matrix products on ``(N, H, L, D)`` tensors (on a GPU
  with torch's fused kernel: :func:`fused_attention`);
  anything else (masks, cross-attention, dropout while training) goes to the parent's forward;
* patch embedding: a convolution whose stride equals its kernel (ViT's ``conv1``) is a linear map
  of the non-overlapping patches (:class:`PatchEmbedding`, Dosovitskiy et al. 2021, eq. 1);
* under bfloat16 autocast the frozen weights that autocast would cast at every call (linear,
  attention and patch projections, the output projection) are cast once, to the same values;
* every linear map (the attention's and patch embedding's projections, the MLPs' layers) goes
  through :func:`stages.render.products.linear`, which a float32 training step on a CPU may route
  to oneDNN's kernels (``optimize.onednn_products``); ATen's ``linear`` everywhere else.

The parents are the references: ``tests/guidance/test_vit.py`` checks the paths agree in value
and gradient.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from ..config.sections import CLIP_TOWERS
from ..render.products import linear, route_linear_modules

__all__ = ["CLIP_TOWERS", "BatchedMultiheadAttention", "PatchEmbedding", "fused_attention", "self_attention", "use_fast_tower"]


def fused_attention(device: torch.device) -> bool:
    """Whether :func:`self_attention` runs torch's fused kernel (``scaled_dot_product_attention``)
    on ``device``: on a GPU, where a step is bound by kernel launches and the fused kernel is one
    launch each way where the plain products take about six forward and eight backward per block
    (``python -m benchmarks.training.launches --part CLIP``); not on a CPU, where it measured 2.2 times
    slower under bfloat16 autocast (8.5 ms against 3.9 ms for one ViT-B-32 block's forward and
    backward on 5 images) and about as fast in float32 (13.8 against 13.3 ms)."""
    return device.type == "cuda"


def self_attention(
    x: Tensor,
    in_weight: Tensor,
    in_bias: Tensor | None,
    out_weight: Tensor,
    out_bias: Tensor | None,
    heads: int,
    fused: bool | None = None,
) -> Tensor:
    """Multi-head self-attention of batch-first tokens ``x (N, L, E)``: ``[q k v] = x W_in^T + b_in``
    split into ``heads`` heads of width ``D = E / heads``, ``softmax(q k^T / sqrt(D)) v`` per head,
    heads concatenated, then ``W_out``, ``b_out``. Shapes: ``in_weight (3E, E)``, ``in_bias (3E,)``,
    ``out_weight (E, E)``, ``out_bias (E,)``; returns ``(N, L, E)``. Exact (no approximation):
    the same function as ``nn.MultiheadAttention`` without masks or dropout, up to float rounding.
    ``fused``: the heads' attention by torch's fused kernel rather than plain products (None:
    :func:`fused_attention` decides by the device); the same function either way."""
    n, length, e = x.shape
    d = e // heads
    qkv = linear(x, in_weight, in_bias).view(n, length, 3, heads, d).permute(2, 0, 3, 1, 4)
    q, k, v = qkv.unbind(0)  # (N, H, L, D) each
    if fused_attention(x.device) if fused is None else fused:
        out = F.scaled_dot_product_attention(q, k, v)
    else:
        out = torch.softmax((q * d**-0.5) @ k.transpose(-1, -2), dim=-1) @ v
    return linear(out.transpose(1, 2).reshape(n, length, e), out_weight, out_bias)


class BatchedMultiheadAttention(nn.MultiheadAttention):
    """``nn.MultiheadAttention`` whose unmasked self-attention without dropout (evaluation mode,
    or ``dropout=0``) runs :func:`self_attention` (see the module's docstring); same parameters,
    same state dict."""

    def forward(self, query, key, value, key_padding_mask=None, need_weights=True, attn_mask=None, **kwargs):
        plain = (
            query is key
            and key is value
            and query.dim() == 3
            and self.batch_first
            and self._qkv_same_embed_dim
            and self.bias_k is None
            and not self.add_zero_attn
            and key_padding_mask is None
            and attn_mask is None
            and not need_weights
            and not kwargs.get("is_causal", False)
            and (self.dropout == 0.0 or not self.training)
        )
        if not plain:
            return super().forward(query, key, value, key_padding_mask, need_weights, attn_mask, **kwargs)
        out = self_attention(
            query, self.in_proj_weight, self.in_proj_bias, self.out_proj.weight, self.out_proj.bias, self.num_heads
        )
        return out, None


class PatchEmbedding(nn.Module):
    """A ``Conv2d`` whose stride equals its kernel and that has no padding, dilation or groups
    (ViT's patch embedding), computed as the linear map it is: each ``p x p`` patch of
    ``x (N, C, H, W)`` flattened in ``(C, p, p)`` order times the flattened kernel ``(O, C p p)``,
    plus the bias; returns ``(N, O, H / p, W / p)`` like the convolution. Exact up to float
    rounding. Holds the convolution's own parameters (``weight``, ``bias``)."""

    def __init__(self, conv: nn.Conv2d) -> None:
        super().__init__()
        if not self.applies(conv):
            raise ValueError(f"not a patch embedding: {conv}")
        self.weight, self.bias = conv.weight, conv.bias
        self.patch = conv.kernel_size[0]

    @staticmethod
    def applies(conv: nn.Module) -> bool:
        return (
            type(conv) is nn.Conv2d
            and conv.kernel_size[0] == conv.kernel_size[1] == conv.stride[0] == conv.stride[1]
            and conv.padding in ((0, 0), "valid")
            and conv.dilation == (1, 1)
            and conv.groups == 1
        )

    def forward(self, x: Tensor) -> Tensor:
        n, c, h, w = x.shape
        p = self.patch
        patches = x.reshape(n, c, h // p, p, w // p, p).permute(0, 2, 4, 1, 3, 5).reshape(n, h // p, w // p, c * p * p)
        return linear(patches, self.weight.reshape(len(self.weight), -1), self.bias).permute(0, 3, 1, 2)


def use_fast_tower(visual: nn.Module, bf16: bool = False) -> int:
    """Put CLIP's image tower ``visual`` (frozen) on the fast path in place, see the module's
    docstring: batched attention, the patch embedding as a linear map, the linear layers by
    :func:`stages.render.products.linear`, and with ``bf16`` the weights autocast would cast stored
    in bfloat16 once. Returns how many modules changed.

    With ``bf16`` the model is changed for good: it must then only run under bfloat16 autocast
    (as :class:`~stages.guidance.clip.ClipGuide` does); load a fresh model for anything else."""
    count = 0
    for m in visual.modules():
        if type(m) is nn.MultiheadAttention:
            m.__class__ = BatchedMultiheadAttention
            count += 1
    for parent in list(visual.modules()):
        for name, child in parent.named_children():
            if PatchEmbedding.applies(child):
                setattr(parent, name, PatchEmbedding(child))
                count += 1
    count += route_linear_modules(visual)
    if bf16:
        with torch.no_grad():
            for m in visual.modules():
                if isinstance(m, nn.Linear | nn.MultiheadAttention | PatchEmbedding):
                    for p in m.parameters(recurse=False):
                        p.data = p.data.to(torch.bfloat16)
            proj = getattr(visual, "proj", None)
            if isinstance(proj, nn.Parameter):
                proj.data = proj.data.to(torch.bfloat16)
    return count
