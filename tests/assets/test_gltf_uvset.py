"""A second UV set written into an input's own glTF document (stages.assets.gltfuvset): every input
vertex kept at its index, each appended seam vertex a copy of every attribute of the vertex it
splits (in its own component type), every triangle still drawing the same corners, the new set
read back per corner as it was given, and the document valid for the Khronos glTF-Validator."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pygltflib as g
import pytest
import uvmeshes
from conftest import require_tool
from PIL import Image

from stages.assets.formats.gltf import validate_glb
from stages.assets.gltfuvset import SecondSet, set_refusal
from stages.assets.ownformat import write_document_glb
from stages.geometry.sourcemesh import accessor_array, load_gltf_document, read_source


def grid(n: int) -> tuple[np.ndarray, np.ndarray]:
    """An ``n x n`` vertex grid in the xy plane: positions and ``(2 (n-1)^2, 3)`` triangles."""
    y, x = np.mgrid[0:n, 0:n].astype(np.float64) / (n - 1)
    pos = np.stack([x.ravel(), y.ravel(), 0.1 * np.sin(6 * x.ravel())], axis=1)
    k = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel()
    faces = np.concatenate([np.stack([k, k + 1, k + n], 1), np.stack([k + 1, k + n + 1, k + n], 1)])
    return pos, faces


def document(path: Path, n: int = 12) -> dict:
    """A GLB whose one vertex set carries every kind of attribute the rewrite must copy: normals,
    tangents, an overlapping first UV set, normalised uint8 RGB colours (3-byte elements, padded
    views), uint8 joints, weights, an application-specific ``_ID``, and a morph target with position
    and tangent deltas; drawn by two triangle primitives (two materials) and a line primitive
    without indices over the same positions, the mesh instanced by a plain and a mirroring node."""
    pos, faces = grid(n)
    b = uvmeshes._Blob(g)
    f32 = np.float32
    rng = np.random.default_rng(3)
    normals = np.tile([0.0, 0.0, 1.0], (len(pos), 1)).astype(f32)
    tangents = np.tile([1.0, 0.0, 0.0, 1.0], (len(pos), 1)).astype(f32)
    uv0 = (np.abs(pos[:, :2] - 0.5)).astype(f32)  # folded: four copies overlap
    colours = rng.integers(0, 255, (len(pos), 3)).astype(np.uint8)
    joints = np.tile(np.array([0, 1, 0, 0], np.uint8), (len(pos), 1))
    weights = np.zeros((len(pos), 4), f32)
    weights[:, 0] = rng.uniform(0.1, 0.9, len(pos))
    weights[:, 1] = 1.0 - weights[:, 0]
    ids = np.arange(len(pos), dtype=f32)[:, None]
    attrs = g.Attributes(
        POSITION=b.add(pos.astype(f32), g.VEC3, g.FLOAT, g.ARRAY_BUFFER, True),
        NORMAL=b.add(normals, g.VEC3, g.FLOAT, g.ARRAY_BUFFER),
        TANGENT=b.add(tangents, g.VEC4, g.FLOAT, g.ARRAY_BUFFER),
        TEXCOORD_0=b.add(uv0, g.VEC2, g.FLOAT, g.ARRAY_BUFFER),
        COLOR_0=b.add(colours, g.VEC3, g.UNSIGNED_BYTE, g.ARRAY_BUFFER),
        JOINTS_0=b.add(joints, g.VEC4, g.UNSIGNED_BYTE, g.ARRAY_BUFFER),
        WEIGHTS_0=b.add(weights, g.VEC4, g.FLOAT, g.ARRAY_BUFFER),
        _ID=b.add(ids, g.SCALAR, g.FLOAT, g.ARRAY_BUFFER),
    )
    b.accessors[attrs.COLOR_0].normalized = True
    target = {
        "POSITION": b.add((0.01 * pos).astype(f32), g.VEC3, g.FLOAT, g.ARRAY_BUFFER, True),
        "TANGENT": b.add(np.zeros((len(pos), 3), f32), g.VEC3, g.FLOAT, g.ARRAY_BUFFER),
    }
    half = len(faces) // 2
    prims = [
        g.Primitive(
            attributes=attrs,
            indices=b.add(part.reshape(-1).astype(np.uint16), g.SCALAR, g.UNSIGNED_SHORT, g.ELEMENT_ARRAY_BUFFER),
            material=k,
            targets=[dict(target)],
        )
        for k, part in enumerate((faces[:half], faces[half:]))
    ]
    points = g.Attributes(POSITION=attrs.POSITION)
    prims.append(g.Primitive(attributes=points, mode=g.POINTS, targets=[{"POSITION": target["POSITION"]}]))
    doc = g.GLTF2(
        asset=g.Asset(version="2.0"),
        scene=0,
        scenes=[g.Scene(nodes=[0, 1, 2])],
        nodes=[
            g.Node(mesh=0, skin=0, translation=[2.0, 0.0, 0.0]),
            g.Node(mesh=0, skin=0, scale=[-1.0, 1.0, 1.0]),
            g.Node(name="Hip", children=[3]),
            g.Node(name="Knee", translation=[0.0, 0.5, 0.0]),
        ],
        skins=[g.Skin(joints=[2, 3])],
        meshes=[g.Mesh(primitives=prims, weights=[0.0])],
        materials=[g.Material(name="A"), g.Material(name="B")],
        accessors=b.accessors,
        bufferViews=b.views,
        buffers=[g.Buffer(byteLength=len(b.data))],
    )
    doc.set_binary_blob(bytes(b.data))
    doc.save_binary(str(path))
    return {"positions": pos, "faces": faces, "half": half}


def textures(folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for key in ("basecolor", "metallic_roughness", "normal", "specular"):
        Image.fromarray(np.full((8, 8, 3), 128, np.uint8)).save(folder / f"{key}.png")
    return folder


def per_triangle_layout(src) -> np.ndarray:
    """A layout that gives every triangle its own corner of UV space (each a chart: every vertex
    splits), the same for every instance of a primitive (the bake's rule), mirrored ones turned."""
    t = len(src.triangles)
    side = int(np.ceil(np.sqrt(t)))
    k = np.arange(t)
    base = np.stack([k % side, k // side], 1)[:, None, :] + np.array([[0.1, 0.1], [0.9, 0.1], [0.1, 0.9]])
    corner = base / side
    for mirrored, plain in ((2, 0), (3, 1)):  # the mirroring node's primitives: the same coordinates, winding turned
        corner[src.part == mirrored] = corner[src.part == plain][:, [0, 2, 1]]
    return corner


@pytest.fixture
def written(tmp_path):
    path = tmp_path / "input.glb"
    made = document(path)
    src = read_source(path)
    corner = per_triangle_layout(src)
    second = SecondSet(corner)
    out = tmp_path / "model.glb"
    notes = write_document_glb(out, src, textures(tmp_path / "textures"), {"run": "test"}, "tango", False, second=second)
    return path, out, src, corner, second.written, notes, made


def test_every_input_vertex_keeps_its_index_and_every_appended_one_copies_its_source(written):
    path, out, src, corner, done, notes, made = written
    a_doc, a_blobs = load_gltf_document(path)
    b_doc, b_blobs = load_gltf_document(out)
    prim_a, prim_b = a_doc.meshes[0].primitives[0], b_doc.meshes[0].primitives[0]
    count = len(made["positions"])
    assert done.texcoord == 1 and done.primitives == 2 and done.vertices == count
    # a per-triangle layout splits every vertex once per further triangle around it
    assert done.appended == 3 * len(made["faces"]) - count == b_doc.accessors[prim_b.attributes.POSITION].count - count
    assert "TEXCOORD_1 to 2 primitive(s)" in notes[0] and f"{done.appended:,} seam vertices" in notes[0]
    names = [n for n, i in vars(prim_a.attributes).items() if isinstance(i, int) and n != "TANGENT"]
    b_indices = np.concatenate([accessor_array(b_doc, b_blobs, p.indices) for p in b_doc.meshes[0].primitives[:2]]).reshape(-1)
    a_indices = np.concatenate([accessor_array(a_doc, a_blobs, p.indices) for p in a_doc.meshes[0].primitives[:2]]).reshape(-1)
    for name in names:
        old = accessor_array(a_doc, a_blobs, getattr(prim_a.attributes, name))
        new = accessor_array(b_doc, b_blobs, getattr(prim_b.attributes, name))
        np.testing.assert_array_equal(new[:count], old, err_msg=name)  # every input vertex as it was
        np.testing.assert_array_equal(new[b_indices], old[a_indices], err_msg=name)  # every corner the same
    for key in ("POSITION",):  # the morph target's deltas follow their vertices too
        old = accessor_array(a_doc, a_blobs, prim_a.targets[0][key])[a_indices]
        np.testing.assert_array_equal(accessor_array(b_doc, b_blobs, prim_b.targets[0][key])[b_indices], old)
    assert "TANGENT" not in prim_b.targets[0]  # the first set's frame, dropped
    # the colours stay 3-byte normalised elements, in a view padded to a 4-byte stride
    colours = b_doc.accessors[prim_b.attributes.COLOR_0]
    assert colours.componentType == g.UNSIGNED_BYTE and colours.normalized
    assert b_doc.bufferViews[colours.bufferView].byteStride == 4


def test_the_new_set_reads_back_per_corner_and_the_materials_read_it(written):
    path, out, src, corner, done, notes, made = written
    doc, blobs = load_gltf_document(out)
    first = src.part < 2
    rows = np.flatnonzero(first)
    tri = np.concatenate([accessor_array(doc, blobs, p.indices) for p in doc.meshes[0].primitives[:2]]).reshape(-1, 3)
    uv1 = accessor_array(doc, blobs, doc.meshes[0].primitives[0].attributes.TEXCOORD_1)
    np.testing.assert_allclose(uv1[tri], corner[rows], atol=1e-7)
    again = read_source(out)  # the input's own first set and every triangle's corners, as they were
    np.testing.assert_array_equal(again.positions[again.triangles], src.positions[src.triangles])
    np.testing.assert_array_equal(again.corner_uv, src.corner_uv)
    for m in doc.materials:
        assert m.pbrMetallicRoughness.baseColorTexture.texCoord == 1 and m.normalTexture.texCoord == 1
        assert m.extensions["KHR_materials_specular"]["specularColorTexture"]["texCoord"] == 1
    # the points over the same positions got indices, so they still draw the input's vertices only
    points = doc.meshes[0].primitives[2]
    np.testing.assert_array_equal(accessor_array(doc, blobs, points.indices), np.arange(len(made["positions"])))
    # the 12 x 12 grid's indices were 16-bit and still are; the tangents are the new set's
    assert doc.accessors[doc.meshes[0].primitives[0].indices].componentType == g.UNSIGNED_SHORT
    t = accessor_array(doc, blobs, doc.meshes[0].primitives[0].attributes.TANGENT)
    np.testing.assert_allclose(np.linalg.norm(t[:, :3], axis=1), 1.0, atol=1e-5)


def test_a_document_with_a_second_set_passes_the_khronos_validator(written):
    report = validate_glb(written[1])
    require_tool(report.get("ran", False), "the Khronos glTF-Validator (Node.js) is not installed")
    assert report["errors"] == 0, report["messages"]


def test_indices_widen_where_16_bits_no_longer_count_the_vertices(tmp_path):
    path = tmp_path / "big.glb"
    document(path, n=250)  # 62,500 vertices in 16-bit indices; a per-triangle set appends ~310,000
    src = read_source(path)
    second = SecondSet(per_triangle_layout(src))
    write_document_glb(tmp_path / "m.glb", src, textures(tmp_path / "t"), {}, "gltf", False, second=second)
    doc, blobs = load_gltf_document(tmp_path / "m.glb")
    assert second.written.vertices + second.written.appended > 65535
    for p in doc.meshes[0].primitives[:2]:
        assert doc.accessors[p.indices].componentType == g.UNSIGNED_INT
    again = read_source(tmp_path / "m.glb")
    np.testing.assert_array_equal(again.positions[again.triangles], src.positions[src.triangles])


def test_compressed_or_sparse_vertices_cannot_take_a_set(tmp_path):
    path = tmp_path / "input.glb"
    document(path)
    doc = g.GLTF2().load(str(path))
    assert set_refusal(doc) is None
    doc.accessors[doc.meshes[0].primitives[0].attributes.NORMAL].sparse = g.Sparse(count=1)
    assert "NORMAL (accessor 1) is sparse" in set_refusal(doc)
    doc = g.GLTF2().load(str(path))
    doc.meshes[0].primitives[1].extensions = {"KHR_draco_mesh_compression": {"bufferView": 0, "attributes": {}}}
    assert "primitive 1 is compressed (KHR_draco_mesh_compression)" in set_refusal(doc)
    assert json.loads(doc.to_json())["meshes"]  # the document itself untouched by the check


def test_a_primitive_without_uvs_reads_the_new_set_under_every_number_up_to_it(tmp_path):
    """glTF numbers a primitive's UV sets from 0 without gaps: a primitive without UVs beside one with
    ``TEXCOORD_0`` gets the bake's set as ``TEXCOORD_0`` and ``TEXCOORD_1`` (the materials read 1)."""
    path = tmp_path / "input.glb"
    document(path)
    doc = g.GLTF2().load(str(path))
    bare = g.Attributes(**{k: v for k, v in vars(doc.meshes[0].primitives[1].attributes).items() if k != "TEXCOORD_0"})
    doc.meshes[0].primitives[1].attributes = bare
    doc.save_binary(str(path))
    src = read_source(path)
    write_document_glb(
        tmp_path / "m.glb", src, textures(tmp_path / "t"), {}, "gltf", False, second=SecondSet(per_triangle_layout(src))
    )
    out = g.GLTF2().load(str(tmp_path / "m.glb"))
    first, second = out.meshes[0].primitives[:2]
    assert first.attributes.TEXCOORD_1 == second.attributes.TEXCOORD_1 == second.attributes.TEXCOORD_0
    assert first.attributes.TEXCOORD_0 != first.attributes.TEXCOORD_1  # the input's own set, kept
    report = validate_glb(tmp_path / "m.glb")
    require_tool(report.get("ran", False), "the Khronos glTF-Validator (Node.js) is not installed")
    assert report["errors"] == 0, report["messages"]


def test_a_material_other_primitives_use_stays_theirs(tmp_path):
    """The points over the surface's positions use the surface's material too: it stays theirs (they
    have no new set to read), and the surface gets a new material reading the bake."""
    path = tmp_path / "input.glb"
    document(path)
    doc = g.GLTF2().load(str(path))
    doc.meshes[0].primitives[2].material = 0
    doc.save_binary(str(path))
    src = read_source(path)
    second = SecondSet(per_triangle_layout(src))
    write_document_glb(tmp_path / "m.glb", src, textures(tmp_path / "t"), {}, "gltf", False, second=second)
    out = g.GLTF2().load(str(tmp_path / "m.glb"))
    surface, _, points = out.meshes[0].primitives
    assert points.material == 0 and out.materials[0].pbrMetallicRoughness is None  # the input's own, untextured
    assert surface.material == len(out.materials) - 1 and out.materials[surface.material].name == "A"
    assert out.materials[surface.material].pbrMetallicRoughness.baseColorTexture.texCoord == 1
    report = validate_glb(tmp_path / "m.glb")
    require_tool(report.get("ran", False), "the Khronos glTF-Validator (Node.js) is not installed")
    assert report["errors"] == 0, report["messages"]


def test_a_mirrored_first_instance_takes_a_second_set_through_the_bakes_layout(tmp_path):
    """The mesh drawn first by the mirroring node: the traced mesh's faces are the input's (winding
    turned back as viewers turn it), the bake's layout gives both instances one set (the plain one's
    corners in turned order), and the document reads it back per corner in its file's winding."""
    from stages.assets.layouts import choose_layout, second_layout
    from stages.config.sections import NormalizeSettings
    from stages.geometry.normalization import normalize_mesh

    path = tmp_path / "input.glb"
    document(path)
    doc = g.GLTF2().load(str(path))
    doc.scenes[0].nodes = [1, 0, 2]  # the mirroring node first
    doc.save_binary(str(path))
    norm = normalize_mesh(str(path), NormalizeSettings())
    choice, layout = choose_layout("second", str(path), norm.transform, norm.mesh, 128, 0.01)
    assert choice.layout == "second" and choice.why == "bake.uv: second"
    made = second_layout(layout, norm.mesh, 128, 2, None)
    src = read_source(path)
    assert src.parts[0]["mirrored"] and not src.parts[2]["mirrored"]
    corner = np.empty((len(src.triangles), 3, 2))
    corner[made.source_face] = made.uv
    for mirrored, plain in ((0, 2), (1, 3)):
        np.testing.assert_array_equal(corner[src.part == plain], corner[src.part == mirrored][:, [0, 2, 1]])
    assert made.check.overlapping == 0 and made.check.unmapped == 0
    write_document_glb(tmp_path / "m.glb", src, textures(tmp_path / "t"), {}, "gltf", False, second=SecondSet(corner))
    out, blobs = load_gltf_document(tmp_path / "m.glb")
    tri = np.concatenate([accessor_array(out, blobs, p.indices) for p in out.meshes[0].primitives[:2]]).reshape(-1, 3)
    uv1 = accessor_array(out, blobs, out.meshes[0].primitives[0].attributes.TEXCOORD_1)
    np.testing.assert_allclose(uv1[tri], corner[src.part == 2].tolist() + corner[src.part == 3].tolist(), atol=1e-6)
    report = validate_glb(tmp_path / "m.glb")
    require_tool(report.get("ran", False), "the Khronos glTF-Validator (Node.js) is not installed")
    assert report["errors"] == 0, report["messages"]
