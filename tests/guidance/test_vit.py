"""CLIP's fast image tower against its references: the batched self-attention against torch's own
``nn.MultiheadAttention``, the patch embedding against ``nn.Conv2d``, in value and gradient, and
the loaded guide against open_clip's modules in float32 and under bfloat16 autocast."""

from __future__ import annotations

import copy

import pytest
import torch
from conftest import dispatched_ops
from torch import nn

from stages.config.sections import ClipSpec
from stages.guidance import vit
from stages.guidance.clip import TINY_MODEL, load_clip
from stages.guidance.vit import BatchedMultiheadAttention, PatchEmbedding, fused_attention, use_fast_tower
from stages.render.products import Linear, onednn_products


def _pair(heads: int, embed: int = 48, dtype=torch.float64):
    torch.manual_seed(heads)
    ref = nn.MultiheadAttention(embed, heads, batch_first=True).to(dtype).eval()
    with torch.no_grad():  # torch initialises the biases to zero: make them count
        ref.in_proj_bias.normal_()
        ref.out_proj.bias.normal_()
    ours = copy.deepcopy(ref)
    assert use_fast_tower(ours) == 1 and type(ours) is BatchedMultiheadAttention
    assert ours.state_dict().keys() == ref.state_dict().keys()
    return ref, ours


@pytest.mark.parametrize("fused", [False, True], ids=["products", "fused kernel"])
@pytest.mark.parametrize("heads", [1, 3, 12])
def test_batched_self_attention_equals_torch_multihead_attention(heads, fused, monkeypatch):
    """Values, gradients to the tokens and gradients to every weight agree with torch's module to
    float64 rounding, for one and several heads (a head split in the wrong order, a missing or
    wrong 1/sqrt(d) scale, or swapped q/k/v would each fail here), by plain products (a CPU's
    path) and by torch's fused kernel (a GPU's: :func:`fused_attention`), both taken here."""
    monkeypatch.setattr(vit, "fused_attention", lambda device: fused)
    ref, ours = _pair(heads)
    x = torch.randn(5, 7, 48, dtype=torch.float64)
    outs, grads = [], []
    for m in (ref, ours):
        xi = x.clone().requires_grad_()
        m.zero_grad()
        y = m(xi, xi, xi, need_weights=False)[0]
        (y * torch.linspace(-1, 1, y.numel(), dtype=y.dtype).view_as(y)).sum().backward()
        outs.append(y.detach())
        grads.append([xi.grad] + [p.grad for p in m.parameters()])
    torch.testing.assert_close(outs[1], outs[0], rtol=1e-10, atol=1e-10)
    for g_ours, g_ref in zip(grads[1], grads[0], strict=True):
        torch.testing.assert_close(g_ours, g_ref, rtol=1e-9, atol=1e-10)


def test_fused_attention_on_a_gpu_only():
    assert fused_attention(torch.device("cuda")) and fused_attention(torch.device("cuda", 1))
    assert not fused_attention(torch.device("cpu"))


@pytest.mark.parametrize("fused", [False, True])
def test_each_path_runs_its_own_kernels(fused):
    """The fused path dispatches torch's attention kernel and no batched product; the plain path
    the reverse (so neither quietly runs the other)."""
    x, w_in, w_out = torch.randn(2, 9, 16), torch.randn(48, 16), torch.randn(16, 16)
    with dispatched_ops() as names:
        vit.self_attention(x.requires_grad_(), w_in, None, w_out, None, heads=4, fused=fused).sum().backward()
    attention = any("scaled_dot_product" in name for name in names)
    assert attention == fused and ("bmm" in names) != fused


def test_fused_attention_under_bfloat16_autocast_matches_the_products():
    """Under training's bfloat16 autocast both paths give the tower's attention to bfloat16's
    rounding of the float64 function (the fused kernel in bfloat16 operands as the products are)."""
    torch.manual_seed(0)
    x, w_in, b_in = torch.randn(5, 50, 64), torch.randn(192, 64) * 0.1, torch.randn(192) * 0.1
    w_out, b_out = torch.randn(64, 64) * 0.1, torch.randn(64) * 0.1
    want = vit.self_attention(*(t.double() for t in (x, w_in, b_in, w_out, b_out)), heads=4, fused=False)
    for fused in (False, True):
        with torch.autocast("cpu", dtype=torch.bfloat16):
            got = vit.self_attention(x, w_in, b_in, w_out, b_out, heads=4, fused=fused)
        assert got.dtype == torch.bfloat16
        assert (got.double() - want).abs().max() < 2e-2 * want.abs().max()


def test_batched_attention_falls_back_for_masks_and_weights():
    """A mask, cross-attention or a request for the attention weights takes torch's own path."""
    ref, ours = _pair(2)
    x, kv = torch.randn(2, 6, 48, dtype=torch.float64), torch.randn(2, 4, 48, dtype=torch.float64)
    mask = torch.triu(torch.full((6, 6), float("-inf"), dtype=torch.float64), diagonal=1)
    torch.testing.assert_close(
        ours(x, x, x, attn_mask=mask, need_weights=False)[0], ref(x, x, x, attn_mask=mask, need_weights=False)[0]
    )
    torch.testing.assert_close(ours(x, kv, kv, need_weights=False)[0], ref(x, kv, kv, need_weights=False)[0])
    y, w = ours(x, x, x, need_weights=True)
    assert w is not None and w.shape == (2, 6, 6)


@pytest.mark.parametrize("patch", [4, 16])
def test_patch_embedding_equals_convolution(patch):
    """ViT's stride-p convolution as a linear map of patches: values and gradients to the image,
    the kernel and the bias agree with ``nn.Conv2d`` to float64 rounding; a convolution that is
    not a patch embedding is refused."""
    torch.manual_seed(patch)
    conv = nn.Conv2d(3, 20, kernel_size=patch, stride=patch).double()
    ours = PatchEmbedding(copy.deepcopy(conv))
    x = torch.randn(2, 3, 4 * patch, 3 * patch, dtype=torch.float64)
    outs, grads = [], []
    for m in (conv, ours):
        xi = x.clone().requires_grad_()
        y = m(xi)
        (y * torch.linspace(-1, 1, y.numel(), dtype=y.dtype).view_as(y)).sum().backward()
        outs.append(y.detach())
        grads.append([xi.grad, m.weight.grad, m.bias.grad])
    assert outs[1].shape == outs[0].shape == (2, 20, 4, 3)
    torch.testing.assert_close(outs[1], outs[0], rtol=1e-10, atol=1e-10)
    for a, b in zip(grads[1], grads[0], strict=True):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-10)
    for other in (nn.Conv2d(3, 4, 3, stride=1), nn.Conv2d(3, 4, 4, stride=4, padding=1), nn.Conv2d(4, 4, 4, stride=4, groups=2)):
        assert not PatchEmbedding.applies(other)


def _guides(bf16: bool):
    spec = ClipSpec(model=TINY_MODEL, pretrained="", tiny_test=True)
    return load_clip(spec, bf16=bf16, tower="open_clip"), load_clip(spec, bf16=bf16, tower="batched")


def _embeddings_and_gradients(guides, text):
    images = torch.rand(3, 3, 64, 64, generator=torch.Generator().manual_seed(0))
    embs, grads = [], []
    for guide in guides:
        x = images.clone().requires_grad_()
        embs.append(guide.embed_images(x).detach())
        guide.similarity(x, text).backward()
        grads.append(x.grad)
    return embs, grads


def test_fast_tower_equals_open_clips():
    """The tiny CLIP loaded both ways in float32: same image embeddings and image gradients, the
    text tower untouched, and the guide says which path runs and what it changed (2 attention
    blocks, the patch embedding and each linear layer, now :class:`stages.render.products.Linear`)."""
    ref, ours = _guides(bf16=False)
    linears = [m for m in ref.model.visual.modules() if type(m) is nn.Linear]
    assert (ref.tower, ref.tower_changes) == ("open_clip", 0)
    assert len(linears) == 4 and (ours.tower, ours.tower_changes) == ("batched", 3 + len(linears))
    assert sum(type(m) is Linear for m in ours.model.visual.modules()) == len(linears)
    assert not any(type(m) is nn.Linear for m in ours.model.visual.modules())
    assert isinstance(ours.model.visual.conv1, PatchEmbedding)
    text = ref.embed_text("a vase made of wood")
    torch.testing.assert_close(ours.embed_text("a vase made of wood"), text)
    embs, grads = _embeddings_and_gradients((ref, ours), text)
    torch.testing.assert_close(embs[1], embs[0], rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(grads[1], grads[0], rtol=1e-3, atol=1e-6)
    with pytest.raises(ValueError, match="batched, open_clip"):
        load_clip(ClipSpec(model=TINY_MODEL, pretrained="", tiny_test=True), tower="flash")


def test_fast_tower_under_bf16_matches_open_clip_under_autocast():
    """Under bfloat16 autocast the fast tower's weights are stored in bfloat16 once (the values
    autocast casts them to at every call): embeddings and gradients match open_clip's autocast
    path to bfloat16 rounding, and the guide's precision says bfloat16 ran."""
    ref, ours = _guides(bf16=True)
    if not ours.bf16:
        pytest.skip(f"no native bfloat16 here: {ours.precision}")
    assert ours.model.visual.transformer.resblocks[0].mlp.c_fc.weight.dtype == torch.bfloat16
    assert ours.model.visual.ln_pre.weight.dtype == torch.float32  # layer norms stay float32 (autocast runs them so)
    text = ref.embed_text("a vase made of wood")
    embs, grads = _embeddings_and_gradients((ref, ours), text)
    assert float((embs[1] - embs[0]).norm() / embs[0].norm()) < 1e-2
    assert float((grads[1] - grads[0]).norm() / grads[0].norm()) < 5e-2


def test_fast_tower_by_onednn_equals_open_clips():
    """Inside a step that routes float32 products to oneDNN (``optimize.onednn_products``) the
    batched tower's projections, MLPs and patch embedding run oneDNN's kernels (none of them ATen's
    ``addmm``), with the same embeddings and image gradients as open_clip's modules."""
    ref, ours = _guides(bf16=False)
    text = ref.embed_text("a vase made of wood")
    embs, grads = _embeddings_and_gradients((ref,), text)
    with onednn_products(True), dispatched_ops() as ops:
        mine, my_grads = _embeddings_and_gradients((ours,), text)
    assert "_linear_pointwise" in ops and "addmm" not in ops
    torch.testing.assert_close(mine[0], embs[0], rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(my_grads[0], grads[0], rtol=1e-3, atol=1e-6)
