"""What a kept glTF layout hands on of the input's document: its names and extras stay the user's,
but ``model.glb`` stands alone and names nothing of the machine it was made on (an image beside
the input is embedded, one at a remote or absolute URI dropped, local paths in ``extras`` removed,
each change said in the log); and a validator's failure or verdict is one line."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
from gltf_quad import buffers, glb_bytes
from PIL import Image

from stages.assets import formats
from stages.assets.formats import gltf
from stages.assets.formats.gltf import validate_glb
from stages.assets.ownformat import write_document_glb
from stages.core.errors import StageInputError
from stages.geometry.sourcemesh import glb_chunks, read_source

#: image URIs of the input, and what becomes of each
URIS = {
    "https://evil.example/p.png?victim=1": "dropped: its uri is of the https: scheme (a viewer would fetch it)",
    "/home/alice/secret/x.png": "dropped: its uri is an absolute path",
    "C:\\Users\\bob\\x.png": "dropped: its uri is an absolute path",
    "file:///home/alice/x.png": "dropped: its uri is of the file: scheme (a viewer would fetch it)",
    "../outside.png": "dropped: its uri is a path that leaves the input's folder",
    "link.png": "dropped: its uri is not a plain file in the input's folder",
    "maps/wood%20grain.png": "embedded from the input's folder",
}
EXTRAS = {
    "author": "<script>alert(1)</script>",
    "source": "/home/alice/secret/x.png",
    "deep": {"list": ["kept", "C:\\Users\\bob\\scene.blend", {"u": "file:///etc/passwd"}]},
    "/home/alice/as-a-key": 1,
}


def input_glb(folder: Path) -> Path:
    """A quad whose document carries scripts in its names, local paths in its extras and an image
    at each of :data:`URIS`, each shown by a material no primitive uses (so that it would stay)."""
    (folder / "maps").mkdir(parents=True)
    Image.fromarray(np.full((4, 4, 3), 200, np.uint8)).save(folder / "maps" / "wood grain.png")
    Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(folder.parent / "outside.png")
    (folder / "link.png").symlink_to(folder / "maps" / "wood grain.png")
    doc = {
        "asset": {"version": "2.0", "extras": json.loads(json.dumps(EXTRAS))},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "<script>alert('node')</script>", "extras": {"blend": "/home/alice/scene.blend"}}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2, "material": 0}]}],
        "materials": [{"name": "<script>alert('material')</script>"}]
        + [{"name": f"spare{k}", "pbrMetallicRoughness": {"baseColorTexture": {"index": k}}} for k in range(len(URIS))],
        "textures": [{"source": k} for k in range(len(URIS))],
        "images": [{"uri": uri} for uri in URIS],
        **buffers(),
    }
    path = folder / "asset.glb"
    path.write_bytes(glb_bytes(doc))
    return path


def baked_textures(folder: Path) -> Path:
    folder.mkdir(parents=True)
    for key in ("basecolor", "metallic_roughness", "normal", "specular"):
        Image.fromarray(np.full((8, 8, 3), 128, np.uint8)).save(folder / f"{key}.png")
    return folder


@pytest.fixture
def exported(tmp_path, caplog):
    src = input_glb(tmp_path / "input")
    out = tmp_path / "model.glb"
    with caplog.at_level(logging.WARNING, logger="stages.assets.ownformat"):
        notes = write_document_glb(out, read_source(src), baked_textures(tmp_path / "textures"), {"run": "test"}, "tango", False)
    raw, binary = glb_chunks(out.read_bytes())
    return {"notes": notes, "text": raw.decode(), "doc": json.loads(raw), "binary": binary, "log": caplog.text, "out": out}


def test_a_kept_glb_embeds_or_drops_every_image_uri_and_says_so(exported, tmp_path):
    doc, text = exported["doc"], exported["text"]
    expected = [f"image {k} {what}" for k, what in enumerate(URIS.values())]
    assert [n for n in exported["notes"] if n.startswith("image")] == expected
    for note in expected:
        assert f"asset.glb: {note}" in exported["log"]
    assert all("uri" not in image for image in doc["images"])
    for gone in ("evil.example", "victim", "alice", "Users", "outside", "link.png", "wood"):
        assert gone not in text, gone
    # the one image beside the input is inside the file now, its bytes as they were
    embedded = [i for i in doc["images"] if "name" not in i]
    assert len(embedded) == 1 and embedded[0]["mimeType"] == "image/png"
    view = doc["bufferViews"][embedded[0]["bufferView"]]
    data = exported["binary"][view.get("byteOffset", 0) : view.get("byteOffset", 0) + view["byteLength"]]
    assert data == (tmp_path / "input" / "maps" / "wood grain.png").read_bytes()
    # the materials that showed a dropped image lost that texture, and nothing points past the lists
    spare = {m["name"]: m for m in doc["materials"] if m["name"].startswith("spare")}
    assert [k for k, m in sorted(spare.items()) if "baseColorTexture" in m.get("pbrMetallicRoughness", {})] == ["spare6"]
    assert all(t["source"] < len(doc["images"]) for t in doc["textures"])


def test_a_kept_glb_keeps_names_and_extras_but_no_local_path(exported):
    doc = exported["doc"]
    assert doc["nodes"][0]["name"] == "<script>alert('node')</script>"
    assert doc["materials"][0]["name"] == "<script>alert('material')</script>"
    assert doc["asset"]["extras"] == {
        "author": "<script>alert(1)</script>",
        "deep": {"list": ["kept", {}]},
        "tango_stylize": {"run": "test"},
    }
    assert doc["nodes"][0].get("extras", {}) == {}
    removed = [n for n in exported["notes"] if not n.startswith("image")]
    assert sorted(removed) == sorted(
        [
            "/asset/extras: a key that is a local file path, removed",
            "/asset/extras/source: a local file path, removed",
            "/asset/extras/deep/list/1: a local file path, removed",
            "/asset/extras/deep/list/2/u: a local file path, removed",
            "/nodes/0/extras/blend: a local file path, removed",
        ]
    )
    for note in removed:
        assert "alice" not in note and "bob" not in note and note in exported["log"]


def test_a_kept_glb_passes_the_khronos_validator(exported):
    report = validate_glb(exported["out"])
    if not report["ran"]:
        pytest.skip(report["reason"])
    assert report["errors"] == 0, report["messages"]
    formats.check_reports({"model.glb": report}, exported["out"].parent)


def test_validation_errors_stop_in_one_line(tmp_path):
    reports = {
        "model.usda": {"errors": 0, "messages": []},
        "model.glb": {"ran": True, "errors": 2, "messages": ["IO_ERROR at /images/0/uri: could not\nload 'x\r\ny'", "W"]},
    }
    with pytest.raises(StageInputError) as info:
        formats.check_reports(reports, tmp_path)
    line = str(info.value)
    assert line == (
        f"{tmp_path / 'model.glb'}: failed validation with 2 error(s), the first: IO_ERROR at /images/0/uri: could not "
        "load 'x y'. Every message is in the log above (2 error(s) in all)."
    )


@pytest.mark.parametrize(
    ("script", "said"),
    [
        (
            "process.stderr.write('file:///x/validate_gltf.mjs:3\\n  throw e;\\nError: boom\\n    at main\\n'); process.exit(1);",
            "the Khronos glTF-Validator could not check it (Error: boom)",
        ),
        ("process.stdout.write('not json');", "the Khronos glTF-Validator's report cannot be read (JSONDecodeError)"),
    ],
)
def test_a_validator_that_fails_says_so_in_one_line(monkeypatch, tmp_path, script, said):
    if shutil.which("node") is None:
        pytest.skip("Node.js (node) is not on PATH")
    (tmp_path / "scripts").mkdir()
    (tmp_path / "scripts" / "validate_gltf.mjs").write_text(script)
    monkeypatch.setattr(gltf, "REPO_ROOT", tmp_path)
    monkeypatch.setattr(gltf, "GLTF_VALIDATOR", tmp_path)
    with pytest.raises(StageInputError) as info:
        validate_glb(tmp_path / "model.glb")
    assert (
        str(info.value)
        == f"{tmp_path / 'model.glb'}: {said}. Check the validator with python -m stages.doctor (npm ci reinstalls it)."
    )
