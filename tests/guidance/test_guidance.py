"""CLIP loading: the tiny test model, local checkpoints, and failing fast without weights."""

from __future__ import annotations

import time

import pytest
import torch

from stages.config.sections import ClipSpec
from stages.core import device as policy
from stages.guidance import clip as guidance
from stages.guidance.clip import TEST_ONLY_WEIGHTS, TINY_MODEL, ClipWeightsUnavailable, load_clip
from stages.guidance.compat import import_open_clip


def test_open_clip_imports():
    open_clip = import_open_clip()
    assert hasattr(open_clip, "create_model")


def test_tiny_clip_is_marked_and_differentiable():
    g = load_clip(ClipSpec(tiny_test=True))
    assert g.test_only and g.weights_id == TEST_ONLY_WEIGHTS and "TEST ONLY" in g.weights_id
    text = g.embed_text("a vase made of wood")
    assert text.shape == (64,) and abs(text.norm().item() - 1) < 1e-5
    imgs = torch.rand(3, 3, g.image_size, g.image_size, requires_grad=True)
    sim = g.similarity(imgs, text)
    sim.backward()
    assert -1 <= sim.item() <= 1 and torch.isfinite(imgs.grad).all() and imgs.grad.abs().sum() > 0
    assert not any(p.requires_grad for p in g.model.parameters())


def test_a_prompt_past_clips_context_is_cut_with_a_warning_naming_it(caplog):
    """CLIP reads 77 tokens (its start and end markers included): a longer prompt is cut by the
    tokenizer, so its embedding equals that of its first 75 words, and a warning names the prompt
    and both counts; a prompt that fits gives none."""
    g = load_clip(ClipSpec(tiny_test=True))
    limit = g.tokenizer.context_length
    words = [f"w{i % 10}" for i in range(200)]  # "w0".."w9": two BPE tokens each
    per_word = len(g.tokenizer.encode("w1"))
    fits = " ".join(words[: (limit - 2) // per_word])
    caplog.clear()
    with caplog.at_level("WARNING", logger="stages.guidance.clip"):
        g.embed_text(fits)
    assert not caplog.records
    long = " ".join(words)
    with caplog.at_level("WARNING", logger="stages.guidance.clip"):
        cut = g.embed_text(long)
    (record,) = caplog.records
    assert f"makes {200 * per_word + 2} tokens; CLIP reads the first {limit}" in record.getMessage()
    assert "'w0 w1 w2" in record.getMessage() and "shorten it" in record.getMessage()
    torch.testing.assert_close(cut, g.embed_text(" ".join(words[: (limit - 2) // per_word + 1])))


def test_local_checkpoint_loads_through_open_clip(tmp_path):
    g = load_clip(ClipSpec(tiny_test=True))
    path = tmp_path / "tiny.bin"
    torch.save(g.model.state_dict(), path)
    g2 = load_clip(ClipSpec(model=TINY_MODEL, checkpoint=str(path)))
    assert not g2.test_only and g2.weights_id == f"{TINY_MODEL}:tiny.bin"
    torch.testing.assert_close(g2.embed_text("a lamp"), g.embed_text("a lamp"))


def test_missing_checkpoint_says_how_to_supply_one(tmp_path):
    with pytest.raises(ClipWeightsUnavailable, match="does not exist") as info:
        load_clip(ClipSpec(checkpoint=str(tmp_path / "nope.bin")))
    assert "clip_checkpoint" in str(info.value)


@pytest.mark.parametrize("offline_env", [True, False])
def test_unavailable_weights_fail_within_5_seconds(monkeypatch, tmp_path, offline_env):
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))  # an empty cache
    monkeypatch.setenv("HUGGINGFACE_HUB_CACHE", str(tmp_path / "hf" / "hub"))
    if offline_env:
        monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    else:
        monkeypatch.delenv("HF_HUB_OFFLINE", raising=False)
        # an address that refuses at once, so the test does not depend on this machine's network
        monkeypatch.setattr(guidance, "HUB_HOST", ("127.0.0.1", 9))
    monkeypatch.setattr(guidance, "_cached_hub_file", lambda hub: None)
    import_open_clip()  # the import itself is not what is timed
    t0 = time.perf_counter()
    with pytest.raises(ClipWeightsUnavailable) as info:
        load_clip(ClipSpec(model="ViT-B-32", pretrained="openai"))
    assert time.perf_counter() - t0 < 5.0
    msg = str(info.value)
    assert "ViT-B-32 with the weights 'openai'" in msg and "clip_checkpoint" in msg
    assert ("HF_HUB_OFFLINE is set" if offline_env else "unreachable from here") in msg


def test_unknown_pretrained_tag():
    with pytest.raises(ClipWeightsUnavailable, match="knows no weights 'no-such-tag'") as info:
        load_clip(ClipSpec(model="ViT-B-32", pretrained="no-such-tag"))
    assert "'laion2b_s34b_b79k'" in str(info.value) and "set optimize.clip_pretrained to one of" in str(info.value)


def _clip_pair():
    spec = ClipSpec(model=TINY_MODEL, pretrained="", tiny_test=True)
    return load_clip(spec, bf16="off"), load_clip(spec, bf16="on")


def test_bf16_autocast_on_cpu_agrees_with_float32():
    """The same random tiny CLIP in float32 and under bfloat16 autocast (where the CPU runs it
    natively): image embeddings and the gradient of the similarity with respect to the images
    point the same way (cosines written out here), and stay finite for black, white and
    saturated noise images; the guide says which precision ran."""
    fp32, bf16 = _clip_pair()
    supported, why = policy.bf16_support(torch.device("cpu"))
    if not supported:
        assert bf16.precision.startswith("float32") and why in bf16.precision and not bf16.bf16
        pytest.skip(f"no native bfloat16 here: {why}")
    assert fp32.precision == "float32" and bf16.precision.startswith("bfloat16 autocast")
    g = torch.Generator().manual_seed(0)
    text = fp32.embed_text("a vase made of wood")
    for images in (torch.rand(4, 3, 64, 64, generator=g), torch.zeros(2, 3, 64, 64), torch.ones(2, 3, 64, 64)):
        grads, embs = [], []
        for guide in (fp32, bf16):
            x = images.clone().requires_grad_()
            emb = guide.embed_images(x)
            guide.similarity(x, text).backward()
            assert torch.isfinite(emb).all() and torch.isfinite(x.grad).all()
            embs.append(emb.detach().flatten())
            grads.append(x.grad.flatten())
        cos_emb = float(embs[0] @ embs[1] / (embs[0].norm() * embs[1].norm()))
        cos_grad = float(grads[0] @ grads[1] / (grads[0].norm() * grads[1].norm()))
        assert cos_emb > 0.999 and cos_grad > 0.98, (cos_emb, cos_grad)


def test_bf16_is_not_silently_ignored(monkeypatch):
    """Asked for where the device has no native bfloat16: float32 runs, and the precision says why."""
    monkeypatch.setattr(policy, "bf16_support", lambda device: (False, "no native bfloat16 in this test"))
    _, bf16 = _clip_pair()
    assert not bf16.bf16 and bf16.precision == "float32 (no native bfloat16 in this test)"
