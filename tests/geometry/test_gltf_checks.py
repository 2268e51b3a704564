"""A GLB or glTF file is checked before any reader builds anything from it: its container (one JSON
chunk, first; at most one binary chunk; lengths within the file), its buffer views within their
buffers and its accessors within their views, its strides as glTF allows and its references in
range. Each refused file stops both readers (trimesh's, for the traced mesh, and the layout's own)
with the same one line; the readers run in a child process, so a crash fails the test instead of
ending the test run."""

from __future__ import annotations

import copy
import json
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from gltf_quad import BINARY, INDICES, POSITIONS, UVS, buffers, chunk, glb, json_chunk

from stages.geometry.sourcemesh import read_source

DOCUMENT = {
    "asset": {"version": "2.0"},
    "scene": 0,
    "scenes": [{"nodes": [0]}],
    "nodes": [{"mesh": 0}],
    "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2}]}],
    **buffers(),
}


def changed(**edits) -> dict:
    """The quad's document with ``edits``: ``"bufferViews.1.byteStride"`` -> value."""
    doc = copy.deepcopy(DOCUMENT)
    for key, value in edits.items():
        *path, last = key.split(".")
        at = doc
        for part in path:
            at = at[int(part)] if isinstance(at, list) else at[part]
        at[int(last) if isinstance(at, list) else last] = value
    return doc


def single(doc: dict) -> bytes:
    return glb(json_chunk(doc), chunk(b"BIN\0", BINARY))


def past_the_end() -> bytes:
    """A BIN chunk whose stated length runs 64 bytes past the end of the file."""
    body = json_chunk(DOCUMENT) + struct.pack("<I4s", len(BINARY) + 64, b"BIN\0") + BINARY
    return glb(body)


#: name -> (the file's bytes, what its one line says)
REFUSED = {
    "two_json_chunks": (
        glb(json_chunk(DOCUMENT), json_chunk(changed(**{"bufferViews.1.byteStride": -65536})), chunk(b"BIN\0", BINARY)),
        "holds 2 JSON chunks; a GLB holds one",
    ),
    "bin_chunk_first": (glb(chunk(b"BIN\0", BINARY), json_chunk(DOCUMENT)), "its first chunk is 'BIN', not the JSON chunk"),
    "two_bin_chunks": (
        glb(json_chunk(DOCUMENT), chunk(b"BIN\0", BINARY), chunk(b"BIN\0", BINARY)),
        "holds 2 BIN chunks; a GLB holds at most one",
    ),
    "chunk_past_the_file": (past_the_end(), "chunk 1 ('BIN') runs 64 bytes past the end of the file"),
    "header_length_not_the_files": (
        glb(json_chunk(DOCUMENT), chunk(b"BIN\0", BINARY), length=4096),
        "its header gives a length of 4,096 bytes, but the file has",
    ),
    "negative_stride": (
        single(changed(**{"bufferViews.1.byteStride": -65536})),
        "buffer view 1 has byteStride -65536; glTF allows 4 to 252, a multiple of 4",
    ),
    "zero_stride": (
        single(changed(**{"bufferViews.1.byteStride": 0})),
        "buffer view 1 has byteStride 0; glTF allows 4 to 252, a multiple of 4",
    ),
    "stride_smaller_than_an_element": (
        single(changed(**{"bufferViews.1.byteStride": 4})),
        "accessor 1's elements (VEC2) take 8 bytes, more than buffer view 1's byteStride of 4",
    ),
    "huge_stride": (
        single(changed(**{"bufferViews.1.byteStride": 1 << 30})),
        "buffer view 1 has byteStride 1073741824; glTF allows 4 to 252, a multiple of 4",
    ),
    "misaligned_stride": (
        single(changed(**{"bufferViews.1.byteStride": 10})),
        "buffer view 1 has byteStride 10; glTF allows 4 to 252, a multiple of 4",
    ),
    "accessor_past_its_view": (
        single(changed(**{"accessors.1.count": 5})),
        "accessor 1 (5 elements of 8 bytes, 8 apart, from byte 0) ends at byte 40 of buffer view 1, which holds 32",
    ),
    "view_past_its_buffer": (
        single(changed(**{"bufferViews.2.byteLength": 400})),
        "buffer view 2 (bytes 80 to 480) runs past the end of buffer 0 (92 bytes)",
    ),
    "negative_count": (single(changed(**{"accessors.1.count": -1})), "accessor 1's count is -1, not a whole number"),
    "unknown_component_type": (
        single(changed(**{"accessors.1.componentType": 5130})),
        "accessor 1 has componentType 5130; glTF's are",
    ),
    "view_index_out_of_range": (
        single(changed(**{"accessors.1.bufferView": 9})),
        "accessor 1's bufferView is 9, but the file has 3 buffer views",
    ),
    "buffer_index_out_of_range": (
        single(changed(**{"bufferViews.1.buffer": 1})),
        "buffer view 1's buffer is 1, but the file has 1 buffers",
    ),
    "node_its_own_child": (single(changed(**{"nodes.0.children": [0]})), "node 0's ancestors form a cycle"),
}

#: the child process: each file through both readers, one JSON line each as it finishes
READERS = """
import json, sys
from stages.core.errors import StageInputError
from stages.geometry.meshio import load_mesh
from stages.geometry.sourcemesh import read_source
for path in sys.argv[1:]:
    said = {}
    for name, read in (("layout", read_source), ("traced", load_mesh)):
        try:
            read(path)
            said[name] = "read"
        except StageInputError as exc:
            said[name] = str(exc)
    print(json.dumps({"path": path, **said}), flush=True)
"""


@pytest.fixture(scope="module")
def refusals(tmp_path_factory) -> dict:
    """What both readers say of each refused file: ``{name: {"layout": line, "traced": line}}``;
    a name is missing where the child process crashed or hung before it."""
    folder = tmp_path_factory.mktemp("refused")
    paths = {}
    for name, (data, _) in REFUSED.items():
        paths[name] = folder / f"{name}.glb"
        paths[name].write_bytes(data)
    try:
        proc = subprocess.run(
            [sys.executable, "-c", READERS, *map(str, paths.values())], capture_output=True, text=True, timeout=120
        )
        out, code = proc.stdout, proc.returncode
    except subprocess.TimeoutExpired as exc:
        out, code = (exc.stdout or b"").decode() if isinstance(exc.stdout, bytes) else exc.stdout or "", "timeout"
    said = {Path(r["path"]).stem: r for r in map(json.loads, out.splitlines())}
    return {"said": said, "code": code, "paths": paths}


@pytest.mark.parametrize("name", list(REFUSED))
def test_a_malformed_glb_is_refused_in_one_line_by_both_readers(refusals, name):
    said = refusals["said"].get(name)
    assert said is not None, f"the readers crashed or hung on {name} (exit status {refusals['code']})"
    path, phrase = str(refusals["paths"][name]), REFUSED[name][1]
    for reader in ("layout", "traced"):
        line = said[reader]
        assert line.startswith(f"{path}: ") and phrase in line, (reader, line)
        assert "\n" not in line and line.endswith("check it with the Khronos glTF-Validator."), line
    assert said["layout"] == said["traced"]


def test_the_reader_copies_no_bytes_outside_a_view_even_unchecked():
    """The accessor reader checks its own bounds: a negative stride given straight to it (the
    file checks bypassed) is refused, in a child process so that a crash fails the test."""
    code = f"""
import json, pygltflib
from stages.geometry.sourcemesh import accessor_array
doc = pygltflib.GLTF2.gltf_from_json({json.dumps(json.dumps(changed(**{"bufferViews.1.byteStride": -65536})))})
try:
    accessor_array(doc, [bytes({len(BINARY)})], 1)
    print("read")
except ValueError as exc:
    print(exc)
"""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip() == "accessor 1 runs past its buffer view"


@pytest.mark.parametrize("uv", ["keep", "auto"])
def test_quick_refuses_a_glb_with_two_json_chunks_before_writing_anything(tmp_path, uv):
    path = tmp_path / "two.glb"
    path.write_bytes(REFUSED["two_json_chunks"][0])
    proc = subprocess.run(
        [sys.executable, "-m", "stages.quick", str(path), "a vase made of wood", "--uv", uv, "--dry-run"]
        + ["--config-dir", str(tmp_path / "configs")],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
    )
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])
    lines = [ln for ln in (proc.stdout + proc.stderr).splitlines() if ln.strip()]
    assert len(lines) == 1 and f"{path}: holds 2 JSON chunks; a GLB holds one" in lines[0], lines
    assert not (tmp_path / "configs").exists()


def test_an_interleaved_view_reads_each_attribute_at_its_stride(tmp_path):
    """Positions and texture coordinates interleaved in one view (20 bytes a vertex) read back
    as written."""
    interleaved = np.concatenate([POSITIONS.view(np.uint8).reshape(4, 12), UVS.view(np.uint8).reshape(4, 8)], 1)
    binary = interleaved.tobytes() + INDICES.tobytes()
    doc = changed(
        **{
            "buffers": [{"byteLength": len(binary)}],
            "bufferViews": [
                {"buffer": 0, "byteOffset": 0, "byteLength": 80, "byteStride": 20},
                {"buffer": 0, "byteOffset": 80, "byteLength": 12},
            ],
            "accessors.1.bufferView": 0,
            "accessors.1.byteOffset": 12,
            "accessors.2.bufferView": 1,
        }
    )
    path = tmp_path / "interleaved.glb"
    path.write_bytes(glb(json_chunk(doc), chunk(b"BIN\0", binary)))
    src = read_source(path)
    assert np.array_equal(src.positions, POSITIONS) and np.array_equal(src.uv, UVS)
    assert src.triangles.tolist() == INDICES.reshape(-1, 3).tolist()


def test_an_applications_own_texture_in_a_materials_extras_is_not_checked(tmp_path):
    """``extras`` are an application's own values: a ``bakedTexture`` there naming a texture of
    its own is not a glTF texture reference, and the file reads."""
    doc = changed(materials=[{"name": "m", "extras": {"bakedTexture": {"index": 3}}}])
    doc["meshes"][0]["primitives"][0]["material"] = 0
    path = tmp_path / "extras.glb"
    path.write_bytes(single(doc))
    assert np.array_equal(read_source(path).positions, POSITIONS)


def test_a_long_chain_of_nodes_passes_and_a_cycle_of_single_parents_is_refused():
    """A 100,000-node chain (each node's parent the one before) is a forest; three nodes each the
    child of the next are a cycle, though each has one parent."""
    from stages.geometry.sourcemesh import _check_references

    n = 100_000
    _check_references({"asset": {"version": "2.0"}, "nodes": [{"children": [i + 1]} for i in range(n - 1)] + [{}]}, [], [])
    cycle = {"asset": {"version": "2.0"}, "nodes": [{"children": [1]}, {"children": [2]}, {"children": [0]}, {}]}
    with pytest.raises(Exception, match="node 0's ancestors form a cycle"):
        _check_references(cycle, [], [])
