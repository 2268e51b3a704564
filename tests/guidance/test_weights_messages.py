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


class CallsOnLoad:
    """Unpickling it calls ``os.mkdir(marker)`` (harmless here: a folder in the test's own)."""

    def __init__(self, marker: str) -> None:
        self.marker = marker

    def __reduce__(self):
        import os

        return (os.mkdir, (self.marker,))


@pytest.mark.parametrize("writer", ["pickle", "torch.save"])
def test_a_clip_checkpoint_that_is_a_pickle_payload_is_refused_in_one_line(tmp_path, writer):
    """A ``clip_checkpoint`` is read by torch's restricted unpickler (open_clip's ``weights_only``):
    one that names a function is refused with the file's name, and the function never runs."""
    import pickle

    import torch

    from stages.config.sections import ClipSpec
    from stages.core.errors import StageInputError

    path, marker = tmp_path / "open_clip_pytorch_model.bin", tmp_path / "ran"
    with open(path, "wb") as fh:
        if writer == "pickle":
            pickle.dump(CallsOnLoad(str(marker)), fh, protocol=2)
        else:
            torch.save({"state_dict": {"payload": CallsOnLoad(str(marker))}}, fh)
    spec = ClipSpec(model=guidance.TINY_MODEL, checkpoint=str(path), section="metrics")
    with pytest.raises(StageInputError) as err:
        guidance.load_clip(spec)
    message = str(err.value)
    assert message.startswith(f"{path}: refused: not a weights-only file") and "\n" not in message, message
    assert "it names posix.mkdir" in message and "metrics.clip_checkpoint" in message
    assert not marker.exists()


def _doctor_without_its_other_checks(monkeypatch):
    """The doctor with every check but the CLIP weights' replaced by an ok line (they start
    Blender, Chromium, Mitsuba...; none asks the model hub)."""
    from stages import doctor

    def ok(*args, **kwargs):
        return doctor.Check("other", True, False, "stubbed")

    for name in ("check_torch", "check_module", "check_node", "check_blender", "check_chromium", "check_slurm", "check_mitsuba"):
        monkeypatch.setattr(doctor, name, ok)
    monkeypatch.setattr(doctor, "write_probe_glb", lambda path: None)
    return doctor


def _no_connections(monkeypatch) -> None:
    import socket

    def refuse(*args, **kwargs):
        raise AssertionError(f"a connection was opened: {args[1:] or args}")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket.socket, "connect_ex", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)


@pytest.mark.parametrize("how", ["--offline", "HF_HUB_OFFLINE=1"])
def test_the_doctor_offline_opens_no_connection(how, monkeypatch, tmp_path, capsys):
    doctor = _doctor_without_its_other_checks(monkeypatch)
    monkeypatch.setattr(guidance, "_cached_hub_file", lambda hub: None)  # an empty cache
    monkeypatch.delenv("HF_HUB_OFFLINE", raising=False)
    if how == "HF_HUB_OFFLINE=1":
        monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    path = tmp_path / "c.yaml"
    path.write_text("meshes: {vase: {builtin: vase}}\nprompts: {wood: 'a {object} made of wood'}\n")
    _no_connections(monkeypatch)
    args = ["--configfile", str(path), *(["--offline"] if how == "--offline" else [])]
    assert doctor.main(args) == 1  # the weights are not here: a needed piece missing
    captured = capsys.readouterr()
    assert captured.out.count(f"Not checked online ({how}).") == 2, captured.out
    assert "asking the model hub" not in captured.err


def test_the_doctor_says_it_asks_the_model_hub_before_it_does(monkeypatch, tmp_path, caplog):
    import logging
    import socket

    monkeypatch.setattr(guidance, "_cached_hub_file", lambda hub: None)
    monkeypatch.delenv("HF_HUB_OFFLINE", raising=False)
    said_before: list[bool] = []

    def connect(address, timeout=None):
        said_before.append(any(f"asking the model hub {address[0]} (port {address[1]})" in r.message for r in caplog.records))
        raise OSError("no route to the hub here")

    monkeypatch.setattr(socket, "create_connection", connect)
    from stages import doctor

    with caplog.at_level(logging.INFO, logger="stages.guidance.clip"):
        checks = doctor.check_clip(config("missing", "off", tmp_path))
    assert said_before == [True] and "huggingface.co" in caplog.text
    assert not checks[0].ok and "unreachable from here" in checks[0].fix
