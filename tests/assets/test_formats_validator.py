"""The glTF validator's record when it cannot run: the reason, in words that travel (a pack's
meta.json is shared), naming no path of this machine."""

from __future__ import annotations

from stages.assets.formats import gltf as formats


def test_a_missing_validator_is_named_without_a_local_path(monkeypatch, tmp_path):
    monkeypatch.setattr(formats.shutil, "which", lambda name: "/usr/bin/node")
    monkeypatch.setattr(formats, "GLTF_VALIDATOR", formats.REPO_ROOT / "node_modules" / "no-such-validator")
    report = formats.validate_glb(tmp_path / "model.glb")
    assert report == {"ran": False, "reason": "the validator (node_modules/no-such-validator) is missing: run npm ci"}
    assert str(formats.REPO_ROOT) not in report["reason"]
    monkeypatch.setattr(formats.shutil, "which", lambda name: None)
    assert formats.validate_glb(tmp_path / "model.glb") == {"ran": False, "reason": "Node.js (node) is not on PATH"}
