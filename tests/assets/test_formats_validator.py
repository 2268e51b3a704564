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


def test_without_node_an_input_document_has_no_faults_to_hand_on(monkeypatch, tmp_path):
    """The path of a user without Node.js: the glTF input is not validated (its record says so)
    and nothing is counted as the input's."""
    import uvmeshes

    from stages.assets.ownformat import input_faults
    from stages.geometry.sourcemesh import read_source

    uvmeshes.skinned_glb(tmp_path / "in.glb")
    monkeypatch.setattr(formats.shutil, "which", lambda name: None)
    assert input_faults(read_source(tmp_path / "in.glb")) == ({}, {"ran": False})


def test_only_the_faults_the_input_lacks_fail_the_check(tmp_path):
    """check_reports: an error whose code and pointer the input has is counted as inherited and
    said; one the input lacks still stops the export."""
    import pytest

    from stages.assets.formats import check_reports, message_key
    from stages.core.errors import StageInputError

    theirs = "ACCESSOR_WEIGHTS_NON_NORMALIZED at /meshes/0/primitives/0/attributes/WEIGHTS_0: sum 0.68"
    ours = "MESH_PRIMITIVE_TOO_FEW_TEXCOORDS at /meshes/0/primitives/1/material: too few"
    report = {"ran": True, "errors": 2, "warnings": 0, "messages": [theirs, theirs.replace("0.68", "0.57")]}
    check_reports({"model.glb": report}, tmp_path, {"model.glb": {message_key(theirs)}})
    assert report["errors"] == 0 and report["inherited_errors"] == 2
    report = {"ran": True, "errors": 2, "warnings": 0, "messages": [theirs, ours]}
    with pytest.raises(StageInputError, match="1 error"):
        check_reports({"model.glb": report}, tmp_path, {"model.glb": {message_key(theirs)}})
