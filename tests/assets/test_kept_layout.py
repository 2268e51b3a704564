"""Your asset in, your asset out (``bake.uv``): meshes with their own UV layouts go through normalize,
ray cache, two optimisation steps with the tiny test CLIP, the bake and the export, and come out
with their own layout, topology, materials and (for glTF) document: a skinned, animated,
two-material GLB; a GLB of two meshes whose layouts overlap each other (one texture set per slot);
an OBJ with two materials. Blender imports each in the input's own format and the round trip
compares it with its import of the input."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pygltflib
import pytest
import uvmeshes
from conftest import REPO, require_blender, require_tool

from stages import bake, export, optimize, roundtrip
from stages.assets.baking import kept_texels
from stages.assets.formats.gltf import validate_glb
from stages.assets.layouts import InputMesh, choose_layout, second_set
from stages.config.sections import (
    BakeSettings,
    ExportSettings,
    NormalizeSettings,
    OptimizeSettings,
    RaycacheSettings,
    RoundtripSettings,
)
from stages.core.errors import StageInputError
from stages.geometry.meshio import load_mesh, save_ply
from stages.geometry.normalization import normalize_mesh
from stages.geometry.sourcemesh import ObjLines, accessor_array, load_gltf_document, read_source
from stages.raycache import run as raycache_run

BAKE = {"texture_size": 128, "eval_width": 32}


def trained(src: Path, d: Path) -> Path:
    """``src`` normalised, traced and trained for two steps in ``d``."""
    d.mkdir(parents=True, exist_ok=True)
    res = normalize_mesh(str(src), NormalizeSettings())
    save_ply(d / "mesh.ply", res.mesh)
    (d / "transform.json").write_text(json.dumps({"source": str(src), **res.transform.to_json()}))
    rc = RaycacheSettings(views=3, resolution=48, eval_azimuths=3, eval_elevations_deg=(0.0, 30.0), eval_resolution=32)
    raycache_run(d / "mesh.ply", d / "train.npz", d / "eval.npz", d / "rc.json", rc)
    s = OptimizeSettings(
        iterations=2,
        clip_tiny_test=True,
        image_size=64,
        width=16,
        crops=1,
        light_lobes=8,
        eval_width=32,
        shading_normals="smooth",
    )
    optimize.run(d / "train.npz", d / "eval.npz", "a vase made of wood", d / "opt", s, "cpu")
    return d


def baked(src: Path, d: Path, uv: str = "auto", **extra) -> dict:
    stats = bake.run(
        d / "mesh.ply",
        d / "opt" / "field.pt",
        d / "eval.npz",
        d / f"bake_{uv}",
        BakeSettings(**BAKE, uv=uv, **extra),
        "cpu",
        InputMesh(str(src), d / "transform.json"),
    )
    export.run(
        d / "mesh.ply",
        d / "transform.json",
        d / f"bake_{uv}",
        d / f"bake_{uv}" / "preview.png",
        d / f"export_{uv}",
        ExportSettings(),
        "m",
        str(src),
    )
    return stats


@pytest.fixture(scope="module")
def cells(tmp_path_factory):
    """The four inputs (the fourth an OBJ over two UDIM tiles), each trained once and baked with
    ``bake.uv: auto``: ``{name: (input, folder)}``."""
    root = tmp_path_factory.mktemp("kept")
    inputs = {"skinned": root / "skinned.glb", "multi": root / "multi.glb", "obj": root / "vase.obj", "udim": root / "tiles.obj"}
    uvmeshes.skinned_glb(inputs["skinned"])
    uvmeshes.multi_glb(inputs["multi"])
    uvmeshes.write_obj(inputs["obj"], materials=("Glaze", "Foot"))
    uvmeshes.write_obj(inputs["udim"], udim=True)
    out = {}
    for name, src in inputs.items():
        d = trained(src, root / name)
        baked(src, d)
        out[name] = (src, d)
    return out


def meta(d: Path, stage: str) -> dict:
    return json.loads((d / stage / "meta.json").read_text())


def test_auto_keeps_a_usable_layout_and_says_why(cells):
    for name, (_, d) in cells.items():
        uv = meta(d, "bake_auto")["stats"]["uv"]
        assert uv["layout"] == "kept", name
        assert uv["why"].startswith("usable:")
        assert uv["check"]["unmapped"] == uv["check"]["degenerate"] == 0
        stats = meta(d, "bake_auto")["stats"]
        assert stats["uv_layout"] == "kept" and stats["uv_why"] == uv["why"]
        assert meta(d, "export_auto")["stats"]["topology"].startswith("the input's own")


def test_skinned_document_keeps_everything_but_its_materials(cells):
    src, d = cells["skinned"]
    a, b = pygltflib.GLTF2().load(str(src)), pygltflib.GLTF2().load(str(d / "export_auto" / "model.glb"))
    ja, jb = json.loads(a.to_json()), json.loads(b.to_json())
    for key in ("scene", "scenes", "nodes", "skins", "animations", "cameras", "meshes"):
        assert ja.get(key) == jb.get(key), key
    assert b.asset.extras["author"] == "test" and "tango_stylize" in b.asset.extras

    def data(doc, i):
        acc = doc.accessors[i]
        view = doc.bufferViews[acc.bufferView]
        start = (view.byteOffset or 0) + (acc.byteOffset or 0)
        return doc.binary_blob()[start : start + view.byteLength], acc.to_dict()

    # every accessor the document had (positions, normals, UVs, joints, weights, morph targets,
    # indices, inverse bind matrices, animation keys): the same values
    for i in range(len(a.accessors)):
        (da, ma), (db, mb) = data(a, i), data(b, i)
        assert da == db and {k: v for k, v in ma.items() if k != "bufferView"} == {
            k: v for k, v in mb.items() if k != "bufferView"
        }
    assert [m.name for m in b.materials] == ["Body", "Rim"]
    assert all(m.pbrMetallicRoughness.baseColorTexture is not None for m in b.materials)
    textures = 3 if meta(d, "bake_auto")["stats"]["brdf"] == "gltf" else 4  # TANGO's adds its specular colour
    assert len(b.images) == textures and all(im.mimeType == "image/png" for im in b.images)
    assert b.samplers[-1].wrapS == pygltflib.REPEAT


def test_every_kept_asset_passes_the_khronos_validator(cells):
    report = validate_glb(cells["obj"][1] / "export_auto" / "model.glb")
    require_tool(report.get("ran", False), "the Khronos glTF-Validator (Node.js) is not installed")
    for name, (_, d) in cells.items():
        stats = meta(d, "export_auto")["stats"]
        assert stats["gltf_validation_errors"] == 0 and stats["usd_validation_errors"] == 0, name


def test_slots_that_overlap_each_other_get_one_texture_set_each(cells):
    src, d = cells["multi"]
    uv = meta(d, "bake_auto")["stats"]["uv"]
    assert [ts["slots"] for ts in uv["texture_sets"]] == [["Glaze"], ["default"]]
    assert uv["texture_sets_why"].startswith("one texture set per slot")
    assert (d / "bake_auto" / "textures" / "default" / "basecolor.png").is_file()
    assert (d / "export_auto" / "textures" / "default" / "basecolor.png").is_file()
    doc = pygltflib.GLTF2().load(str(d / "export_auto" / "model.glb"))
    vase, knot = doc.meshes
    assert vase.primitives[1].mode == pygltflib.LINES and vase.primitives[1].material is None  # not surface: untouched
    glaze, default = doc.materials[vase.primitives[0].material], doc.materials[knot.primitives[0].material]
    assert (glaze.name, default.name) == ("Glaze", "default")
    a = glaze.pbrMetallicRoughness.baseColorTexture.index
    b = default.pbrMetallicRoughness.baseColorTexture.index
    assert doc.textures[a].source != doc.textures[b].source  # two sets
    usd = (d / "export_auto" / "model.usda").read_text()
    assert "textures/default/basecolor.png" in usd and "textures/basecolor.png" in usd


def test_obj_comes_back_as_its_own_lines_with_a_new_material_library(cells):
    src, d = cells["obj"]
    lines = (d / "export_auto" / "model.obj").read_text().splitlines()
    assert lines[0] == "mtllib model.mtl"
    assert lines[1:] == [ln for ln in ObjLines.read(src).lines if not ln.startswith("mtllib")]
    mtl = (d / "export_auto" / "model.mtl").read_text()
    assert "newmtl Glaze" in mtl and "newmtl Foot" in mtl and "map_Kd textures/basecolor.png" in mtl
    for f in ("roughness", "metallic"):
        assert (d / "export_auto" / "textures" / f"{f}.png").is_file()
    # the glTF holds one vertex per distinct OBJ corner, in first-use order, and the faces in order
    s = read_source(src)
    doc = pygltflib.GLTF2().load(str(d / "export_auto" / "model.glb"))
    prim = doc.meshes[0].primitives
    assert [doc.materials[p.material].name for p in prim] == ["Glaze", "Foot"]
    assert doc.accessors[prim[0].attributes.POSITION].count == len(s.positions)
    got = read_source(d / "export_auto" / "model.glb")
    np.testing.assert_allclose(got.positions, s.positions, atol=1e-6 * np.ptp(s.positions))
    np.testing.assert_allclose(got.uv, s.uv, atol=1e-7)
    np.testing.assert_array_equal(got.triangles, s.triangles)  # the two slots hold consecutive runs of faces
    usd = (d / "export_auto" / "model.usda").read_text()
    assert 'def GeomSubset "Glaze"' in usd and 'def GeomSubset "Foot"' in usd


def test_texels_of_a_kept_layout_lie_on_their_faces():
    pos, uv, faces = uvmeshes.unwrapped("vase")
    from stages.geometry.meshio import TriMesh

    mesh = TriMesh(pos, faces)
    corner_uv = uv[faces]
    texels = kept_texels(mesh, corner_uv, 64, 1)
    rows, cols = np.nonzero(texels.filled)
    b = texels.bary
    tri = corner_uv[texels.face]
    at = tri[:, 0] + b[:, :1] * (tri[:, 1] - tri[:, 0]) + b[:, 1:] * (tri[:, 2] - tri[:, 0])
    np.testing.assert_allclose(at, np.stack([(cols + 0.5) / 64, (rows + 0.5) / 64], 1), atol=1e-5)
    half = kept_texels(mesh, corner_uv, 64, 1, faces=np.arange(len(faces)) % 2 == 0)
    assert (half.face % 2 == 0).all() and 0 < half.filled.sum() < texels.filled.sum()


def test_a_traced_mesh_that_is_not_the_input_takes_an_atlas(cells, tmp_path):
    src, d = cells["obj"]
    other = normalize_mesh("builtin:candle", NormalizeSettings())
    tf = normalize_mesh(str(src), NormalizeSettings()).transform
    choice, layout = choose_layout("auto", str(src), tf, other.mesh, 128, 0.01)
    assert not choice.kept and layout is None and "faces are not the input's" in choice.why
    with pytest.raises(StageInputError, match="bake.uv: keep, but the traced mesh's faces are not the input's"):
        choose_layout("keep", str(src), tf, other.mesh, 128, 0.01)
    with pytest.raises(StageInputError, match="builtin:vase has no UV layout"):
        choose_layout("keep", "builtin:vase", tf, other.mesh, 128, 0.01)
    choice, _ = choose_layout("atlas", str(src), tf, load_mesh(src), 128, 0.01)
    assert not choice.kept and choice.why == "bake.uv: atlas"


def test_atlas_is_todays_bake_and_export(cells):
    src, d = cells["obj"]
    baked(src, d, "atlas")
    assert meta(d, "bake_atlas")["stats"]["uv"] == {"setting": "atlas", "layout": "atlas", "why": "bake.uv: atlas"}
    with np.load(d / "bake_atlas" / "atlas.npz") as z:
        assert "source_face" not in z.files
    assert not (d / "export_atlas" / "model.obj").exists()
    assert meta(d, "export_atlas")["stats"]["topology"] == "the traced mesh, welded"


def test_export_refuses_an_input_that_changed_since_the_bake(cells, tmp_path):
    src, d = cells["obj"]
    changed = tmp_path / "vase.obj"
    lines = src.read_text().splitlines()
    first_vt = next(i for i, ln in enumerate(lines) if ln.startswith("vt "))
    lines[first_vt] = "vt 0.123 0.456"  # one texture coordinate moved
    changed.write_text("\n".join(lines) + "\n")
    with pytest.raises(StageInputError, match="is not the mesh whose triangles the bake baked"):
        export.run(
            d / "mesh.ply",
            d / "transform.json",
            d / "bake_auto",
            d / "bake_auto" / "preview.png",
            tmp_path / "e",
            ExportSettings(),
            "m",
            str(changed),
        )
    with pytest.raises(StageInputError, match="the input mesh was not given"):
        export.run(
            d / "mesh.ply",
            d / "transform.json",
            d / "bake_auto",
            d / "bake_auto" / "preview.png",
            tmp_path / "e",
            ExportSettings(),
            "m",
            None,
        )


def blender_roundtrip(src: Path, d: Path, uv: str) -> tuple[dict, dict]:
    """The round trip of the cell in ``d`` baked and exported with ``bake.uv: uv`` (one view, 4
    samples, the GLB): its record and its own-format check."""
    settings = RoundtripSettings(enabled=True, views=1, spp=4, split_lobes=False, formats=("glb",))
    bake_dir, export_dir, out = d / f"bake_{uv}", d / f"export_{uv}", d / f"rt_{uv}"
    args = (d / "mesh.ply", d / "transform.json", d / "opt" / "field.pt", d / "eval.npz", bake_dir, export_dir, out)
    record = roundtrip.run(*args, settings, "cpu", str(src))
    return record, json.loads((out / "meta.json").read_text())["own_format"]


@pytest.mark.parametrize("name", ["skinned", "multi", "obj", "udim"])
def test_blender_imports_the_own_format_as_it_imports_the_input(cells, name):
    require_blender()
    src, d = cells[name]
    out, own = blender_roundtrip(src, d, "auto")
    assert own["problems"] == [] and own["uv_error"] == 0.0
    assert own["input"]["vertices"] == own["output"]["vertices"] > 0
    assert own["output"]["file"] == ("model.obj" if name in ("obj", "udim") else "model.glb")
    if name == "skinned":  # one mesh object: every corner compared with what was exported
        assert out["formats"]["glb"]["import"]["problems"] == []
        assert out["formats"]["glb"]["import"]["uv_error"] < 1e-5


def test_the_measured_meshes_fetch_and_read_with_their_layouts(tmp_path):
    """scripts/fetch_uv_meshes.sh (benchmarks/assets/kept_layout.py's artist-made meshes) fetches Debian's
    assimp test models and converts them; each reads back with texture coordinates on every face."""
    import shutil
    import subprocess

    require_tool(shutil.which("apt-get") is not None and shutil.which("dpkg-deb") is not None, "apt-get and dpkg-deb (Debian)")
    out = tmp_path / "uv-meshes"
    script = REPO / "scripts" / "fetch_uv_meshes.sh"
    proc = subprocess.run(["bash", str(script), str(out)], capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    faces = {}
    for name in ("duck", "milktruck", "jeep"):
        s = read_source(out / f"{name}.glb")
        assert s.mapped.all()
        faces[name] = len(s.triangles)
    assert faces == {"duck": 4212, "milktruck": 3624, "jeep": 2032}  # as benchmarks/SOURCES.md lists them


@pytest.mark.slow(minutes=1)
def test_the_published_gltf_assets_fetch_with_their_checksums(tmp_path):
    """scripts/fetch_gltf_assets.sh fetches the nine glTF 2.0 assets benchmarks/SOURCES.md lists from
    the Debian archive's source tarballs, each as published (read here with its own layout, rig and
    morph targets); a tarball that is not the one pinned stops it."""
    import shutil
    import subprocess

    require_tool(shutil.which("curl") is not None, "curl")
    reach = subprocess.run(["curl", "-fsI", "--max-time", "20", "http://deb.debian.org/debian/"], capture_output=True)
    require_tool(reach.returncode == 0, "the Debian archive (deb.debian.org) is not reachable")
    script = REPO / "scripts" / "fetch_gltf_assets.sh"
    out = tmp_path / "assets"
    proc = subprocess.run(["bash", str(script), str(out)], capture_output=True, text=True, timeout=900, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    faces = {p.parent.name: len(read_source(p).triangles) for p in out.glob("*/*.gl[tb]*")}
    assert faces == {
        "box-textured": 12,
        "duck": 4212,
        "milk-truck": 3624,
        "cesium-man": 4672,
        "fox": 576,
        "spider": 500,
        "morph-cube": 12,
        "test-scene": 1096,
        "sparse-morph": 12,
    }
    man = pygltflib.GLTF2().load(str(out / "cesium-man" / "CesiumMan.gltf"))
    assert len(man.skins[0].joints) == 19 and len(man.animations) == 1
    # a local mirror whose tarball is not the pinned one: the checksum stops the script
    mirror = tmp_path / "mirror" / "d" / "draco"
    mirror.mkdir(parents=True)
    (mirror / "draco_1.5.5+dfsg.orig.tar.xz").write_bytes(b"not the tarball")
    env = {**os.environ, "TANGO_DEBIAN_POOL": str(tmp_path / "mirror")}
    proc = subprocess.run(["bash", str(script), str(tmp_path / "bad")], capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode != 0 and "draco_1.5.5+dfsg.orig.tar.xz: checksum mismatch" in proc.stderr


def test_udim_tiles_of_an_obj_get_one_texture_set_each(cells):
    """An OBJ whose one material spans two UDIM tiles: one texture set per tile, a material per
    tile (``Glaze.1001``, ``Glaze.1002``) in every format, and ``usemtl`` lines before each run of
    faces in a tile, the OBJ's other lines as they were."""
    src, d = cells["udim"]
    stats = meta(d, "bake_auto")["stats"]
    sets = stats["uv"]["texture_sets"]
    assert [(ts["folder"], ts["tile"]) for ts in sets] == [("", 1001), ("1002", 1002)]
    assert "one texture set per UDIM tile (2 tiles)" in stats["uv"]["why"]
    export_dir = d / "export_auto"
    assert (export_dir / "textures" / "1002" / "basecolor.png").is_file()
    lines = (export_dir / "model.obj").read_text().splitlines()
    original = ObjLines.read(src).lines
    assert [ln for ln in lines if not ln.startswith(("usemtl", "mtllib"))] == [
        ln for ln in original if not ln.startswith(("usemtl", "mtllib"))
    ]
    uses = [ln for ln in lines if ln.startswith("usemtl")]
    assert uses == ["usemtl Glaze.1001", "usemtl Glaze.1002"]
    mtl = (export_dir / "model.mtl").read_text()
    assert "newmtl Glaze.1002\n" in mtl and "map_Kd textures/1002/basecolor.png" in mtl
    doc = pygltflib.GLTF2().load(str(export_dir / "model.glb"))
    assert [m.name for m in doc.materials] == ["Glaze.1001", "Glaze.1002"]
    a, b = (m.pbrMetallicRoughness.baseColorTexture.index for m in doc.materials)
    assert doc.textures[a].source != doc.textures[b].source
    assert meta(d, "export_auto")["stats"]["gltf_validation_errors"] == 0
    # the fidelity reads each face's tile's set: as good as one tile's (the field is the same)
    assert stats["bake_psnr_db"] > 35.0


@pytest.fixture(scope="module")
def second(cells, tmp_path_factory):
    """A second UV set: the skinned GLB with ``bake.uv: second`` (its own layout usable), and the
    same GLB with its layout folded onto itself under ``auto`` (not usable: a second set)."""
    root = tmp_path_factory.mktemp("second")
    src, d = cells["skinned"]
    baked(src, d, "second")
    folded = root / "folded.glb"
    uvmeshes.skinned_glb(folded, fold=True)
    f = trained(folded, root / "folded")
    baked(folded, f)
    return {"skinned": (src, d, "second"), "folded": (folded, f, "auto")}


def test_auto_makes_a_second_set_where_the_input_layout_overlaps_and_says_why(second):
    _, d, uv = second["folded"]
    stats = meta(d, f"bake_{uv}")["stats"]
    assert stats["uv"]["layout"] == stats["uv_layout"] == "second"
    assert "overlap other faces in UV space" in stats["uv"]["why"] and "a second UV set" in stats["uv"]["why"]
    assert stats["uv"]["check"]["overlapping"] > 0.1 * stats["uv"]["check"]["faces"]  # what was measured: the input's
    assert [ts["folder"] for ts in stats["uv"]["texture_sets"]] == [""]
    assert meta(d, f"export_{uv}")["stats"]["topology"] == "the input's own, with a second UV set for the bake"


@pytest.mark.parametrize("name", ["skinned", "folded"])
def test_a_second_set_keeps_the_document_and_adds_texcoord_1(second, name):
    src, d, uv = second[name]
    a, b = pygltflib.GLTF2().load(str(src)), pygltflib.GLTF2().load(str(d / f"export_{uv}" / "model.glb"))
    ja, jb = json.loads(a.to_json()), json.loads(b.to_json())
    for key in ("scene", "scenes", "nodes", "skins", "animations", "cameras"):
        assert ja.get(key) == jb.get(key), key
    added = meta(d, f"export_{uv}")["stats"]["second_uv_set"]
    assert added["attribute"] == "TEXCOORD_1" and added["primitives"] == 2
    for pa, pb in zip(a.meshes[0].primitives, b.meshes[0].primitives, strict=True):
        assert pb.attributes.TEXCOORD_1 is not None and pb.attributes.TEXCOORD_0 is not None
        assert b.accessors[pb.attributes.POSITION].count == a.accessors[pa.attributes.POSITION].count + added["appended_vertices"]
    assert all(m.pbrMetallicRoughness.baseColorTexture.texCoord == 1 for m in b.materials)
    # TEXCOORD_1 per corner is the layout the bake baked (atlas.npz, per traced face)
    with np.load(d / f"bake_{uv}" / "atlas.npz") as z:
        baked = second_set({"uv": {"layout": "second"}}, {"uv": z["uv"], "source_face": z["source_face"]})
    doc, blobs = load_gltf_document(d / f"export_{uv}" / "model.glb")
    tri = np.concatenate([accessor_array(doc, blobs, p.indices) for p in doc.meshes[0].primitives]).reshape(-1, 3)
    uv1 = accessor_array(doc, blobs, doc.meshes[0].primitives[0].attributes.TEXCOORD_1)
    np.testing.assert_allclose(uv1[tri], baked, atol=1e-6)
    assert meta(d, f"bake_{uv}")["stats"]["uv"]["second_check"]["overlapping"] == 0  # the new set's own check
    # every triangle draws the corners it drew, with the input's own UVs; the bake's set is the bake's
    before, after = read_source(src), read_source(d / f"export_{uv}" / "model.glb")
    np.testing.assert_array_equal(after.positions[after.triangles], before.positions[before.triangles])
    np.testing.assert_array_equal(after.corner_uv, before.corner_uv)
    report = validate_glb(d / f"export_{uv}" / "model.glb")
    require_tool(report.get("ran", False), "the Khronos glTF-Validator (Node.js) is not installed")
    assert report["errors"] == 0, report["messages"]


def test_second_stops_for_an_obj_and_keep_stops_for_a_folded_layout(cells, second):
    src, d = cells["obj"]
    tf = normalize_mesh(str(src), NormalizeSettings()).transform
    with pytest.raises(StageInputError, match="bake.uv: second, but an OBJ holds one UV set"):
        choose_layout("second", str(src), tf, load_mesh(d / "mesh.ply"), 128, 0.01)
    folded, f, _ = second["folded"]
    tf = normalize_mesh(str(folded), NormalizeSettings()).transform
    with pytest.raises(StageInputError, match="bake.uv: keep, but .* overlap other faces"):
        choose_layout("keep", str(folded), tf, load_mesh(f / "mesh.ply"), 128, 0.01)


@pytest.mark.parametrize("name", ["skinned", "folded"])
def test_blender_imports_a_second_set_with_the_rig_and_the_bake_on_it(second, name):
    require_blender()
    src, d, uv = second[name]
    out, own = blender_roundtrip(src, d, uv)
    assert own["problems"] == [] and own["uv_error"] == 0.0
    appended = meta(d, f"export_{uv}")["stats"]["second_uv_set"]["appended_vertices"]
    assert own["input"]["vertices"] < own["output"]["vertices"] <= own["input"]["vertices"] + appended
    # the rig, its animation and the morph target arrive as they did from the input
    assert own["output"]["bones"] == own["input"]["bones"] == 2 and own["output"]["actions"] == own["input"]["actions"] >= 1
    assert own["output"]["shape_keys"] == own["input"]["shape_keys"] > 0
    check = out["formats"]["glb"]["import"]
    assert check["problems"] == [] and check["uv_error"] < 1e-5  # the bake's set, as the material reads it
