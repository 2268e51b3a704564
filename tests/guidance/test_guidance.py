"""CLIP loading: the tiny test model, local checkpoints, and failing fast without weights."""

from __future__ import annotations

import time

import pytest
import torch

from stages.config.sections import ClipSpec
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
    assert "ViT-B-32/openai" in msg and "clip_checkpoint" in msg and "unreachable" in msg


def test_unknown_pretrained_tag():
    with pytest.raises(ClipWeightsUnavailable, match="no pretrained weights"):
        load_clip(ClipSpec(model="ViT-B-32", pretrained="no-such-tag"))
