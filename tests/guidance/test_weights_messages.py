"""First contact: when CLIP weights are missing, one message per model the run needs (guidance,
evaluation), each naming the model, its weights tag, where it was looked for, the config keys that
point at a local file with the architecture that matches those weights, and the way to run
without it; tested for every combination of what a config asks for."""

from __future__ import annotations

import itertools

import pytest

from stages.config.workflow import WorkflowConfig
from stages.guidance import clip as guidance
from stages.guidance.clip import missing_weights

GUIDANCE = {
    "missing": {"clip_model": "ViT-B-32", "clip_pretrained": "openai"},
    "local": {"clip_model": "ViT-B-32-quickgelu", "clip_checkpoint": "{ckpt}"},
    "bad_path": {"clip_model": "ViT-B-32-quickgelu", "clip_checkpoint": "{missing}"},
    "test_only": {"clip_tiny_test": True},
    "image": {"guidance": "image", "target_material": "wood", "target_renderer": "sg"},
}
EVALUATION = {
    "missing": {"clip_model": "ViT-B-16", "clip_pretrained": "openai"},
    "local": {"clip_model": "ViT-B-16-quickgelu", "clip_checkpoint": "{ckpt}"},
    "bad_path": {"clip_model": "ViT-B-16-quickgelu", "clip_checkpoint": "{missing}"},
    "off": {"clip": False},
}


@pytest.fixture
def offline(monkeypatch, tmp_path):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setattr(guidance, "_cached_hub_file", lambda hub: None)  # an empty cache
    return tmp_path


def config(guidance_kind, eval_kind, tmp_path):
    ckpt = tmp_path / "open_clip_pytorch_model.bin"
    ckpt.write_bytes(b"weights")

    def fill(d):
        return {k: v.format(ckpt=ckpt, missing=tmp_path / "nope.bin") if isinstance(v, str) else v for k, v in d.items()}

    return WorkflowConfig(
        {
            "meshes": {"vase": {"builtin": "vase"}},
            "prompts": {"wood": "a {object} made of wood"},
            "optimize": fill(GUIDANCE[guidance_kind]),
            "metrics": fill(EVALUATION[eval_kind]),
        }
    )


@pytest.mark.parametrize(("guidance_kind", "eval_kind"), list(itertools.product(GUIDANCE, EVALUATION)))
def test_one_message_per_missing_model(offline, guidance_kind, eval_kind):
    messages = missing_weights(config(guidance_kind, eval_kind, offline).clip_specs())
    want_guidance = guidance_kind in ("missing", "bad_path")
    want_eval = eval_kind in ("missing", "bad_path")
    assert len(messages) == want_guidance + want_eval
    if want_guidance:
        m = messages[0]
        assert m.startswith("The guidance CLIP (the model the optimisation follows), ViT-B-32")
        assert "  optimize:\n    clip_checkpoint: /path/to/open_clip_pytorch_model.bin\n    clip_model: ViT-B-32-quickgelu" in m
        assert "metrics:" not in m and "config/demo.yaml" in m and "config/overlays/offline.yaml" in m
    if want_eval:
        m = messages[-1]
        assert m.startswith("The evaluation CLIP (the metrics' CLIP score and R-precision), ViT-B-16")
        assert "  metrics:\n    clip_checkpoint: /path/to/open_clip_pytorch_model.bin\n    clip_model: ViT-B-16-quickgelu" in m
        assert "Or switch the evaluation off: metrics: {clip: false}" in m and "optimize:" not in m
    kinds = [k for k, want in ((guidance_kind, want_guidance), (eval_kind, want_eval)) if want]
    for m, kind in zip(messages, kinds, strict=True):
        assert "with the weights 'openai'" in m
        if kind == "missing":  # where it looked: the cache folder of these weights and the hub
            assert "Looked for it in: the Hugging Face cache (" in m and "HF_HUB_OFFLINE is set" in m
            assert "open_clip.create_model('ViT-B-" in m and "/snapshots/<hash>/" in m
        else:
            assert "nope.bin set as " in m and "does not exist" in m and f"Looked for it in: {offline / 'nope.bin'}." in m


def test_the_doctor_checks_weights_the_hub_would_give_without_downloading_them(monkeypatch, tmp_path):
    """With the hub reachable and nothing cached, the doctor says the workflow will download the
    weights; it never fetches hundreds of megabytes itself."""
    import sys

    from stages import doctor

    guidance.import_open_clip()  # (as the stages import it)
    pretrained = sys.modules["open_clip.pretrained"]

    def refuse(*args, **kwargs):
        raise AssertionError("the doctor downloaded CLIP weights")

    monkeypatch.setattr(guidance, "_cached_hub_file", lambda hub: None)
    monkeypatch.setattr(guidance, "_hub_reachable", lambda: True)
    monkeypatch.setattr(pretrained, "download_pretrained", refuse)
    checks = doctor.check_clip(config("missing", "missing", tmp_path))
    assert [c.ok for c in checks] == [True, True]
    for check in checks:
        assert "not cached here; the model hub answers, so the workflow downloads them when it starts" in check.detail
    with pytest.raises(AssertionError, match="downloaded"):  # the workflow's own start does fetch them
        missing_weights(config("missing", "off", tmp_path).clip_specs())
