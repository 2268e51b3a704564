"""Baking, USD/glTF export, relighting, summary and asset pack."""

from __future__ import annotations

import json
import shutil
import subprocess
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import REPO, assert_not_blank, browser_check, icosphere, page_references, require_tool

from stages import export, optimize, pack, relight, report
from stages.assets.baking import bake_field, decode_textures
from stages.assets.formats import usd
from stages.config.sections import (
    BakeSettings,
    ExportSettings,
    MetricsSettings,
    OptimizeSettings,
    RaycacheSettings,
    RelightSettings,
)
from stages.core.errors import StageInputError
from stages.geometry.atlas import dilate, rasterize_atlas, unwrap
from stages.geometry.normals import NormalSpec
from stages.model.lights import LightModule
from stages.model.lights.sg import SGLightModule
from stages.model.networks import Material
from stages.raycache import run as raycache_run
from stages.render.hdrio import read_exr, read_hdr, write_exr, write_hdr
from stages.results import summary


def analytic_albedo(p: torch.Tensor) -> torch.Tensor:
    return torch.stack([0.5 + 0.4 * torch.sin(3 * p[:, 0]), 0.5 + 0.4 * p[:, 1], 0.3 + 0.2 * torch.cos(2 * p[:, 2])], -1)


class AnalyticField(torch.nn.Module):
    """Colour = a smooth function of position; a known constant tilt of the normal."""

    def __init__(self, tilt: float = 0.2, normals: NormalSpec | None = None):
        super().__init__()
        self.light = LightModule([SGLightModule(8)])
        self.tilt = tilt
        self.normals = normals or NormalSpec()

    def surface(self, p, n, view=None):
        """The field's interface for baking (:meth:`StyleField.surface`): material and normal."""
        return self._material(p), (self._normal(p, n) if self.tilt else n)

    def _material(self, p):
        return Material(analytic_albedo(p), torch.full_like(p, 0.3), torch.full_like(p[:, :1], 0.5))

    def _normal(self, p, n):
        # tilt towards +x of world space, whatever the frame: a known world-space normal
        out = n + self.tilt * torch.tensor([1.0, 0.0, 0.0])
        return out / out.norm(dim=-1, keepdim=True)


@pytest.fixture(scope="module")
def sphere_mesh():
    return icosphere(3)


def test_atlas_uvs_and_rasterisation(sphere_mesh):
    atlas = unwrap(sphere_mesh, 256, 2)
    assert atlas.uv.shape == (len(sphere_mesh.faces), 3, 2)
    assert atlas.uv.min() >= 0 and atlas.uv.max() <= 1
    face, bary = rasterize_atlas(atlas.uv, 256)
    counts = np.bincount(face[face >= 0], minlength=len(sphere_mesh.faces))
    assert (counts > 0).all(), "every face gets texels"
    # texel centres map back inside their face's UV triangle
    rows, cols = np.nonzero(face >= 0)
    f = face[rows, cols]
    uv = atlas.uv[f]
    b = bary[rows, cols].astype(np.float64)
    rec = uv[:, 0] + b[:, :1] * (uv[:, 1] - uv[:, 0]) + b[:, 1:] * (uv[:, 2] - uv[:, 0])
    np.testing.assert_allclose(rec, np.stack([(cols + 0.5) / 256, (rows + 0.5) / 256], 1), atol=1e-4)


def uv_charts(mesh, uv: np.ndarray) -> np.ndarray:
    """Chart id per face, from the atlas alone: faces are in one chart when they share an edge
    (the same two vertices) with the same texture coordinates at both ends."""
    parent = np.arange(len(mesh.faces))

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    seen = {}
    for f, tri in enumerate(mesh.faces):
        for k in range(3):
            a, b = int(tri[k]), int(tri[(k + 1) % 3])
            ua, ub = tuple(np.round(uv[f, k], 7)), tuple(np.round(uv[f, (k + 1) % 3], 7))
            key = (min(a, b), max(a, b), *(ua + ub if a < b else ub + ua))
            if key in seen:
                parent[find(f)] = find(seen[key])
            else:
                seen[key] = f
    return np.array([find(f) for f in range(len(mesh.faces))])


def test_bounded_charts(sphere_mesh):
    """``max_chart_share`` bounds every chart's surface area to that share of the surface (charts
    read back from the texture coordinates), and bounding them makes more, smaller charts."""
    free = unwrap(sphere_mesh, 256, 2)
    bounded = unwrap(sphere_mesh, 256, 2, max_chart_share=0.02)
    areas = sphere_mesh.face_areas
    total = areas.sum()
    for atlas in (free, bounded):
        assert atlas.charts == len(np.unique(uv_charts(sphere_mesh, atlas.uv)))
    ids = uv_charts(sphere_mesh, bounded.uv)
    chart_area = np.bincount(np.unique(ids, return_inverse=True)[1], weights=areas)
    assert chart_area.max() <= 0.02 * total * (1 + 1e-6)
    assert bounded.charts > free.charts and bounded.charts >= 1 / 0.02
    # the free atlas has a chart larger than the bound: the option is what bounded them
    free_area = np.bincount(np.unique(uv_charts(sphere_mesh, free.uv), return_inverse=True)[1], weights=areas)
    assert free_area.max() > 0.02 * total


def test_bake_analytic_field_texels(sphere_mesh):
    field = AnalyticField(tilt=0.0)
    res = bake_field(sphere_mesh, field, BakeSettings(texture_size=256, dilation=2, light_width=32))
    face, bary = rasterize_atlas(res.atlas.uv, 256)
    filled = face >= 0
    f = face[filled]
    b = bary[filled].astype(np.float64)
    tri = sphere_mesh.vertices[sphere_mesh.faces[f]]
    pts = tri[:, 0] + b[:, :1] * (tri[:, 1] - tri[:, 0]) + b[:, 1:] * (tri[:, 2] - tri[:, 0])
    expected = analytic_albedo(torch.from_numpy(pts)).numpy()
    got = decode_textures(res.textures)["albedo"][filled]
    # 8-bit sRGB quantisation: at most half a code step, i.e. < 0.5/255 / (sRGB slope >= 0.4)
    assert np.abs(got - expected).max() < 0.5 / 255 / 0.4 + 1e-6
    rough = res.textures["metallic_roughness"][..., 1][filled] / 255.0
    assert np.abs(rough - 0.5).max() <= 0.5 / 255 + 1e-9
    assert (res.textures["metallic_roughness"][..., 2] == 0).all()  # metalness 0
    # without a normal network the tangent-space normal is +Z everywhere
    nz = res.textures["normal"][filled] / 255.0 * 2 - 1
    assert np.abs(nz - [0, 0, 1]).max() < 2.5 / 255


@pytest.mark.parametrize("mode", ["flat", "smooth"])
def test_tangent_frames_and_normal_map_round_trip(sphere_mesh, mode):
    """Decoding the normal map the way MikkTSpace prescribes (interpolated, unnormalised tangent T
    and normal N, bitangent w (N x T), written out here) gives back the field's world normal."""
    field = AnalyticField(tilt=0.3, normals=NormalSpec(mode))
    res = bake_field(sphere_mesh, field, BakeSettings(texture_size=256, dilation=1, light_width=32))
    fr = res.frames
    assert np.abs((fr.tangents * fr.normals).sum(-1)).max() < 1e-9  # tangents lie in each corner's plane
    np.testing.assert_allclose(np.linalg.norm(fr.tangents, axis=-1), 1.0, atol=1e-9)
    assert set(np.unique(fr.handedness)) <= {-1.0, 1.0}
    face, bary = rasterize_atlas(res.atlas.uv, 256)
    filled = face >= 0
    f, uv = face[filled], bary[filled].astype(np.float64)
    c = np.stack([1 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], 1)[..., None]
    t = (c * fr.tangents[f]).sum(1)
    n = (c * fr.normals[f]).sum(1)
    b = fr.handedness[f][:, None] * np.cross(n, t)
    ts = decode_textures(res.textures)["normal"][filled]
    world = ts[:, :1] * t + ts[:, 1:2] * b + ts[:, 2:3] * n
    world /= np.linalg.norm(world, axis=1, keepdims=True)
    want = n / np.linalg.norm(n, axis=1, keepdims=True) + 0.3 * np.array([1.0, 0, 0])
    want /= np.linalg.norm(want, axis=1, keepdims=True)
    assert np.degrees(np.arccos(np.clip((world * want).sum(1), -1, 1))).max() < 1.0
    if mode == "smooth":  # the icosphere's smooth normals are its radial directions
        p = (c[..., 0:1] * sphere_mesh.vertices[sphere_mesh.faces[f]]).sum(1)
        radial = p / np.linalg.norm(p, axis=1, keepdims=True)
        assert np.degrees(np.arccos(np.clip((n / np.linalg.norm(n, axis=1, keepdims=True) * radial).sum(1), -1, 1))).max() < 0.6


def test_dilation_fills_and_keeps():
    v = np.zeros((8, 8, 1))
    f = np.zeros((8, 8), bool)
    v[3, 3] = 1.0
    f[3, 3] = True
    out = dilate(v, f, 2)
    assert out[3, 3, 0] == 1.0 and out[5, 5, 0] == 1.0 and out[0, 0, 0] == 1.0  # rest: mean fill


def test_hdr_and_exr_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    img = (rng.random((8, 16, 3)) ** 3 * 100).astype(np.float32)
    write_hdr(tmp_path / "a.hdr", img)
    back = read_hdr(tmp_path / "a.hdr")
    # RGBE: 8-bit mantissas with a shared exponent: within 1/128 of each pixel's largest channel
    assert (np.abs(back - img) <= img.max(-1, keepdims=True) / 128 + 1e-30).all()
    write_exr(tmp_path / "a.exr", img)
    np.testing.assert_array_equal(read_exr(tmp_path / "a.exr"), img)


@pytest.fixture(scope="module")
def trained(trained_cell):
    return trained_cell


def results_with_cell(trained, tmp_path, normalize_meta: bool = True):
    """A results tree holding the trained fixture as cell candle/wax/base (optimize, bake, asset),
    with the mesh's normalize metadata; returns ``(results, cell)``."""
    results = tmp_path / "results"
    cell = results / "candle" / "wax" / "base"
    if normalize_meta:
        (results / "candle" / "normalize").mkdir(parents=True)
        (results / "candle" / "normalize" / "meta.json").write_text(
            json.dumps({"stats": {"faces": 13440}, "timings_s": {"total": 0.1}})
        )
    for src, dst in (("opt", "optimize"), ("bake", "bake"), ("export", "export")):
        shutil.copytree(trained / src, cell / dst)
    return results, cell


def test_bake_fidelity_and_metadata(trained):
    meta = json.loads((trained / "bake" / "meta.json").read_text())
    assert meta["stats"]["bake_psnr_db"] >= 35.0
    assert meta["stats"]["texture_size"] == 256
    assert (trained / "bake" / "light.exr").is_file() and (trained / "bake" / "preview.png").is_file()


def test_usd_reopens_with_material_and_textures(trained):
    import zipfile

    from pxr import Usd, UsdGeom, UsdShade

    # the usdz's root layer is the binary crate (its first entry), the usda beside it text
    with zipfile.ZipFile(trained / "export" / "model.usdz") as z:
        first = z.namelist()[0]
        assert first == "model.usdc" and z.read(first)[:8] == b"PXR-USDC"
    assert (trained / "export" / "model.usda").read_bytes().startswith(b"#usda")
    for name in ("model.usda", "model.usdz"):
        stage = Usd.Stage.Open(str(trained / "export" / name))
        assert UsdGeom.GetStageUpAxis(stage) == "Y" and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
        origin = stage.GetRootLayer().customLayerData["tango_stylize"]
        assert origin["test_only"] is True and origin["label"].startswith("TEST ONLY")
        assert "TEST ONLY" in stage.GetRootLayer().documentation
        mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Asset/Geometry/Mesh"))
        assert mesh and UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st").IsDefined()
        material, _ = UsdShade.MaterialBindingAPI(mesh.GetPrim()).ComputeBoundMaterial()
        assert material.GetPath() == "/Asset/Looks/TangoMaterial"
        files = []
        for prim in stage.Traverse():
            for attr in ("inputs:file", "inputs:texture:file"):
                a = prim.GetAttribute(attr)
                if a and a.Get() is not None:
                    files.append(a.Get())
        assert len(files) == 5  # four textures and the dome light's image
        assert all(f.resolvedPath for f in files), files
        checked = usd.validate_usd(trained / "export" / name)
        assert checked["errors"] == 0 and checked["validators"] >= 20, checked["messages"]
        # geometry is back in the input's units: the candle stands at y ~ 20..33 cm
        pts = np.asarray(mesh.GetPointsAttr().Get())
        assert 19 < pts[:, 1].min() < 21 and 32 < pts[:, 1].max() < 34


def _broken_usda(path):
    """A USD layer with four faults usd-core's validators know: no metersPerUnit, no upAxis, no
    default prim, and a primvar reader whose varname is a token (must be a string)."""
    from pxr import Sdf, Usd, UsdGeom, UsdShade

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.Xform.Define(stage, "/A")
    UsdShade.Material.Define(stage, "/A/M")
    reader = UsdShade.Shader.Define(stage, "/A/M/R")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.Token).Set("st")
    stage.GetRootLayer().Save()


def test_usd_validation_is_counted_not_asserted(trained, tmp_path):
    """The export records what its validators found, counted: every validator usd-core registers
    ran (their number and names match the registry, asked here directly), and a faulty layer
    gets its faults counted rather than a constant 0."""
    from pxr import UsdValidation

    registered = sorted(v.GetMetadata().name for v in UsdValidation.ValidationRegistry().GetOrLoadAllValidators())
    meta = json.loads((trained / "export" / "meta.json").read_text())["stats"]
    reports = [meta["validation"][name] for name in ("model.usda", "model.usdz")]
    assert [r["file"] for r in reports] == ["model.usda", "model.usdz"]
    for r in reports:
        assert r["validators"] == len(registered) and r["validator_names"] == registered
    assert meta["usd_validators"] == len(registered)
    assert meta["usd_validation_errors"] == sum(r["errors"] for r in reports) == 0
    _broken_usda(tmp_path / "broken.usda")
    broken = usd.validate_usd(tmp_path / "broken.usda")
    assert broken["errors"] == 4 and broken["validators"] == len(registered)
    assert any(m.startswith("MismatchedPropertyType") for m in broken["messages"])


def test_export_fails_on_validation_errors(trained, tmp_path, monkeypatch):
    """A validator error stops the export in one line and leaves no finished-looking metadata behind."""
    real = usd.validate_usd

    def faulty(path):
        _broken_usda(tmp_path / "broken.usda")
        return {**real(tmp_path / "broken.usda"), "file": Path(path).name}

    monkeypatch.setattr(usd, "validate_usd", faulty)
    out = tmp_path / "export"
    with pytest.raises(
        StageInputError, match=r"model.usda: failed validation with \d+ error\(s\), the first: MismatchedPropertyType"
    ) as err:
        export.run(
            trained / "mesh.ply",
            trained / "transform.json",
            trained / "bake",
            trained / "bake" / "preview.png",
            out,
            ExportSettings(),
        )
    assert not (out / "meta.json").exists() and "\n" not in str(err.value) and ".." not in str(err.value)


def test_glb_reloads_with_all_textures(trained):
    import pygltflib
    import trimesh

    glb = trained / "export" / "model.glb"
    g = pygltflib.GLTF2().load(str(glb))
    assert len(g.images) == 4 and g.extensionsUsed == ["KHR_materials_specular"]
    assert g.asset.extras["tango_stylize"]["test_only"] is True
    mat = g.materials[0]
    assert mat.pbrMetallicRoughness.metallicRoughnessTexture.index == 1 and mat.normalTexture.index == 2
    assert mat.extensions["KHR_materials_specular"]["specularColorTexture"]["index"] == 3
    scene = trimesh.load(glb)
    geom = next(iter(scene.geometry.values()))
    assert len(geom.faces) == 13440
    assert geom.visual.material.baseColorTexture is not None
    assert geom.visual.material.normalTexture is not None


def test_welded_export_shares_vertices_and_keeps_every_corner(trained):
    """The welded GLB holds each distinct (position, normal, UV, tangent) once; read back through
    its indices (pygltflib, not our code) it gives every corner of the faceted layout exactly, and
    a smooth closed mesh needs about one vertex per two faces plus its seams."""
    import pygltflib

    from stages.assets.formats import export_mesh, read_atlas
    from stages.geometry.meshio import load_ply
    from stages.geometry.normalization import Similarity

    mesh = load_ply(trained / "mesh.ply")
    atlas = read_atlas(trained / "bake" / "atlas.npz")
    tf = Similarity.from_json(json.loads((trained / "transform.json").read_text()))
    faceted = export_mesh(mesh, atlas, tf, weld=False)
    welded = export_mesh(mesh, atlas, tf)
    assert len(faceted.positions) == 3 * len(mesh.faces)
    assert len(welded.positions) < 0.75 * len(mesh.faces)  # the candle: 13,440 faces, 6,722 positions
    assert len({tuple(r) for r in np.concatenate([welded.positions, welded.normals, welded.uv, welded.tangents], 1)}) == len(
        welded.positions
    )
    g = pygltflib.GLTF2().load(str(trained / "export" / "model.glb"))
    blob = g.binary_blob()
    prim = g.meshes[0].primitives[0]

    def read(index, dtype, width):
        acc = g.accessors[index]
        view = g.bufferViews[acc.bufferView]
        data = np.frombuffer(blob, dtype, acc.count * width, view.byteOffset + (acc.byteOffset or 0))
        return data.reshape(acc.count, width) if width > 1 else data

    idx_acc = g.accessors[prim.indices]
    idx = read(prim.indices, np.uint16 if idx_acc.componentType == pygltflib.UNSIGNED_SHORT else np.uint32, 1).astype(np.int64)
    assert g.accessors[prim.attributes.POSITION].count == len(welded.positions)
    for attr, ref, width in (("POSITION", faceted.positions, 3), ("NORMAL", faceted.normals, 3), ("TEXCOORD_0", faceted.uv, 2)):
        np.testing.assert_array_equal(read(getattr(prim.attributes, attr), np.float32, width)[idx], ref)
    np.testing.assert_array_equal(read(prim.attributes.TANGENT, np.float32, 4)[idx], faceted.tangents)
    size = json.loads((trained / "export" / "meta.json").read_text())["stats"]["file_bytes"]
    assert size["model.glb"] == (trained / "export" / "model.glb").stat().st_size


def test_khronos_gltf_validator(trained):
    node = shutil.which("node")
    validator = REPO / "node_modules" / "gltf-validator"
    require_tool(
        node is not None and validator.is_dir(),
        "Node.js or node_modules/gltf-validator missing (scripts/setup.sh runs npm ci when npm exists)",
    )
    out = subprocess.run(
        [node, str(REPO / "scripts" / "validate_gltf.mjs"), str(trained / "export" / "model.glb")],
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    report_ = json.loads(out.stdout)
    assert report_["issues"]["numErrors"] == 0, report_["issues"]["messages"]
    assert report_["issues"]["numWarnings"] == 0, report_["issues"]["messages"]
    # the export ran the same validator and recorded its counts
    recorded = json.loads((trained / "export" / "meta.json").read_text())["stats"]["validation"]["model.glb"]
    assert recorded["ran"] and recorded["validator"] == f"Khronos glTF-Validator {report_['validatorVersion']}"
    assert (recorded["errors"], recorded["warnings"]) == (0, 0)


def test_darker_environment_darkens_relit_render(trained, tmp_path):
    from stages.render.envmap import procedural_envmap

    bright = procedural_envmap("overcast", 32)
    write_hdr(tmp_path / "bright.hdr", bright)
    write_hdr(tmp_path / "dark.hdr", bright * 0.2)
    s = dict(lobes=8, fit_iterations=60, width=32, roughness_scales=(0.5, 2.0), specular_scales=(0.0, 1.0))
    a = relight.run(
        trained / "opt" / "field.pt",
        trained / "eval.npz",
        tmp_path / "a",
        RelightSettings(envmap=str(tmp_path / "bright.hdr"), **s),
    )
    b = relight.run(
        trained / "opt" / "field.pt",
        trained / "eval.npz",
        tmp_path / "b",
        RelightSettings(envmap=str(tmp_path / "dark.hdr"), **s),
    )
    assert b["mean_relit"] < 0.8 * a["mean_relit"]
    from PIL import Image

    grid = Image.open(tmp_path / "a" / "material_edit.png")
    # rows: roughness scales, columns: specular scales (2 x 2 tiles of 32), labelled around them
    assert grid.size[0] > 2 * 32 and grid.size[1] > 2 * 32
    # more specular (column 2) is brighter than none (column 1) in the same row
    assert a["mean_material_edit"][1] > a["mean_material_edit"][0]


def test_summary_and_pack(trained, tmp_path):
    results, cell = results_with_cell(trained, tmp_path)
    rows = report.run(results, [("candle", "wax", "base")], results / "report")
    assert len(rows) == 1 and rows[0]["weights"] == "test-only random" and rows[0]["test_only_weights"]
    import pandas as pd

    frame = pd.read_csv(results / "report" / "summary.csv")
    assert len(frame) == 1 and frame.loc[0, "bake_psnr_db"] >= 35
    assert (results / "report" / "overview.png").is_file()
    pack.run(results, [("candle", "wax", "base")], results / "pack.zip", results / "index.csv")
    with zipfile.ZipFile(results / "pack.zip") as z:
        names = z.namelist()
    for f in ("model.usdz", "model.usda", "model.glb", "textures/normal.png", "light.exr", "preview.png"):
        assert f"candle/wax/base/{f}" in names
    assert "index.csv" in names and "README.txt" in names
    index = pd.read_csv(results / "index.csv")
    assert index.loc[0, "faces"] == 13440 and index.loc[0, "texture_size"] == 256
    assert bool(index.loc[0, "test_only"]) and index.loc[0, "origin"].startswith("TEST ONLY")
    with zipfile.ZipFile(results / "pack.zip") as z:
        readme = z.read("README.txt").decode()
    assert "WARNING: TEST ONLY. 1 of 1 assets" in readme and "candle/wax/base: TEST ONLY" in readme


def test_pack_skips_links_and_ships_provenance_without_host_or_command(trained, tmp_path, caplog):
    """A results folder may hold symbolic links (to a private key, to a whole home folder): the
    pack ships none of them. Its meta.json keep settings, versions and origin, and leave out
    the host name, the platform, the command line and the user's folders."""
    results, cell = results_with_cell(trained, tmp_path)
    secret = tmp_path / "secret.txt"
    secret.write_text("PRIVATE KEY")
    (tmp_path / "home").mkdir()
    (tmp_path / "home" / "notes.txt").write_text("private notes")
    (cell / "export" / "textures" / "leak.png").symlink_to(secret)
    (cell / "export" / "home").symlink_to(tmp_path / "home", target_is_directory=True)
    pack.run(results, [("candle", "wax", "base")], results / "pack.zip", results / "index.csv")
    with zipfile.ZipFile(results / "pack.zip") as z:
        names = z.namelist()
        blob = b"".join(z.read(n) for n in names)
        metas = b"".join(z.read(n) for n in names if n.endswith((".json", ".csv", ".txt")))
        shipped = json.loads(z.read("candle/wax/base/meta.json"))
    assert not any("leak" in n or "home/" in n for n in names), names
    assert b"PRIVATE KEY" not in blob and b"private notes" not in blob
    assert sum("a symbolic link" in r.getMessage() for r in caplog.records) == 2
    original = json.loads((cell / "export" / "meta.json").read_text())
    assert original["host"]["hostname"] and original["argv"]  # recorded on this machine...
    assert "host" not in shipped and "argv" not in shipped  # ...and not shipped
    assert original["host"]["hostname"].encode() not in metas and b"argv" not in metas
    assert shipped["settings"] == original["settings"] and shipped["origin"] == original["origin"]
    assert shipped["versions"] == original["versions"]
    for key in ("inputs", "outputs"):
        for value in shipped[key].values():
            path = value["path"] if isinstance(value, dict) else value
            assert "/" not in path, (key, path)
    assert str(tmp_path).encode() not in metas
    # an export folder that is itself a link is refused, naming it
    from stages.core.errors import StageInputError

    shutil.move(cell / "export", tmp_path / "elsewhere")
    (cell / "export").symlink_to(tmp_path / "elsewhere", target_is_directory=True)
    with pytest.raises(StageInputError, match="is reached through a symbolic link"):
        pack.run(results, [("candle", "wax", "base")], results / "pack2.zip", results / "index2.csv")
    assert not (results / "pack2.zip").exists()


@pytest.mark.parametrize("single_file", [False, True])
def test_html_report_without_model_viewer_shows_previews(trained, tmp_path, caplog, single_file):
    """Without Node.js's packages the report is still written, as a folder or as one file:
    static previews, a warning in the log and a notice on the pages; the test-only banner
    comes first."""
    from stages import html_report
    from stages.config.sections import ReportSettings

    results, cell = results_with_cell(trained, tmp_path)
    report.run(results, [("candle", "wax", "base")], results / "report")
    out = html_report.run(
        results, results / "report", [("candle", "wax", "base")], ReportSettings(single_file=single_file), tmp_path / "absent.js"
    )
    index = (results / "report" / "index.html").read_text()
    pages = [index] if single_file else [index, (results / "report/cells/candle/wax/base/index.html").read_text()]
    assert out["viewers"] == 0
    for text in pages:
        assert "<model-viewer" not in text and "id='no-viewer'" in text
        assert text.index("TEST ONLY: 1 of 1 cells") < text.index("<h2")
    assert "class='preview viewer-img'" in pages[-1]
    assert ("data:image/png;base64," in index) == single_file
    assert (results / "report" / "cells").exists() != single_file
    assert any(r.levelname == "WARNING" and "static previews" in r.getMessage() for r in caplog.records)


def test_outputs_of_mixed_runs_are_refused(trained, tmp_path):
    """The report checks that every output of a cell repeats its optimisation's origin."""
    from stages.core.errors import StageInputError

    results, cell = results_with_cell(trained, tmp_path, normalize_meta=False)
    meta = json.loads((cell / "bake" / "meta.json").read_text())
    meta["origin"] = {**meta["origin"], "test_only": False, "label": "CLIP-guided (ViT-B-32/openai)"}
    (cell / "bake" / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(StageInputError, match="mixed"):
        summary.check_origins(cell)


def reference_ssim(a: np.ndarray, b: np.ndarray) -> float:
    """SSIM with scipy's Gaussian filter (truncate so the window is 11 wide), valid region."""
    from scipy.ndimage import gaussian_filter

    c1, c2 = 0.01**2, 0.03**2
    vals = []
    for ch in range(a.shape[0]):
        x, y = a[ch].astype(np.float64), b[ch].astype(np.float64)

        def f(t):
            return gaussian_filter(t, 1.5, truncate=5 / 1.5, mode="constant")[5:-5, 5:-5]

        mx, my = f(x), f(y)
        sxx, syy, sxy = f(x * x) - mx**2, f(y * y) - my**2, f(x * y) - mx * my
        vals.append(((2 * mx * my + c1) * (2 * sxy + c2) / ((mx**2 + my**2 + c1) * (sxx + syy + c2))).mean())
    return float(np.mean(vals))


def test_ssim_and_psnr_against_reference():
    from stages.imaging.quality import psnr, ssim

    rng = np.random.default_rng(0)
    a = rng.random((3, 48, 48))
    b = np.clip(a + rng.normal(0, 0.05, a.shape), 0, 1)
    ta, tb = torch.from_numpy(a)[None], torch.from_numpy(b)[None]
    assert ssim(ta, ta) == pytest.approx(1.0, abs=1e-12)
    assert ssim(ta, tb) == pytest.approx(reference_ssim(a, b), abs=1e-9)
    assert psnr(ta, tb) == pytest.approx(10 * np.log10(1 / np.mean((a - b) ** 2)), rel=1e-9)


def test_metrics_mark_weights_and_rank_prompts(trained, tmp_path):
    from stages import metrics
    from stages.config.sections import RaycacheSettings

    s = RaycacheSettings(
        views=1,
        resolution=16,
        eval_resolution=16,
        metrics_azimuths=4,
        metrics_elevations_deg=(0.0,),
        metrics_resolution=64,
    )
    raycache_run(
        trained / "mesh.ply",
        tmp_path / "t.npz",
        tmp_path / "e.npz",
        tmp_path / "m.json",
        s,
        tmp_path / "metrics.npz",
    )
    out = metrics.run(
        trained / "opt" / "field.pt",
        tmp_path / "metrics.npz",
        "a candle made of wax",
        ["a candle made of wax", "a candle made of gold", "a candle made of ice"],
        tmp_path / "met",
        MetricsSettings(clip_tiny_test=True),
    )
    ev = out["evaluation"]
    assert ev["test_only"] is True and "TEST ONLY" in ev["weights"]
    assert ev["candidates"] == 3 and ev["views"] == 4 and 0 <= ev["r_precision"] <= 1
    assert out["guidance"]["test_only"] is True
    assert out["protocol"]["fov_deg"] == 45.0 and out["protocol"]["radius"] == 2.5
    saved = json.loads((tmp_path / "met" / "metrics.json").read_text())
    assert saved["evaluation"]["clip_score"] == pytest.approx(ev["clip_score"])


def test_pareto_front_and_knee():
    from stages.results.compare import knee_point, pareto_front

    pts = [(1.0, 20.0), (2.0, 30.0), (3.0, 25.0), (4.0, 33.0), (8.0, 34.0), (16.0, 34.5), (5.0, 10.0)]
    front = pareto_front(pts)
    assert front == [0, 1, 3, 4, 5]  # (3, 25) and (5, 10) are dominated
    # normalised distance to the chord from (1 s, 20 dB) to (16 s, 34.5 dB) peaks at (4 s, 33 dB)
    assert knee_point(pts, front) == 3


def test_report_tables_never_mix_test_only_and_real():
    import pandas as pd

    from stages.results.site import group_rows

    frame = pd.DataFrame(
        {
            "test_only_weights": [True, False, False],
            "eval_test_only": [True, False, None],
            "guidance": ["CLIP", "CLIP", "image-guided (procedural targets)"],
        }
    )
    groups = dict(group_rows(frame))
    assert len(groups) == 3
    for title, sub in groups.items():
        assert len(sub) == 1
        assert sub["test_only_weights"].iloc[0] == title.startswith("TEST ONLY")


def test_report_fidelity_lines_per_cell():
    """Each cell's recovery and round-trip figures as the report writes them; a metal's albedo has
    no scale (its truth is black) and says only the error as is."""
    import pandas as pd

    from stages.results.site import fidelity_lines

    wood = pd.DataFrame(
        {
            "target_psnr_db": [22.05],
            "target_ssim": [0.741],
            "target_renderer": ["mitsuba"],
            "target_albedo_rmse": [0.283],
            "target_albedo_rmse_scaled": [0.269],
            "target_roughness_mae": [0.26],
            "roundtrip_glb_psnr_db": [28.26],
            "roundtrip_usdz_psnr_db": [22.61],
            "roundtrip_glb_diffuse_psnr_db": [36.99],
            "roundtrip_problems": [2],
        }
    )
    text = " ".join(fidelity_lines(wood))
    assert "recovery on mitsuba targets" in text and "22.05 dB, SSIM 0.741" in text
    assert "albedo RMSE 0.283 (0.269 after its scale), roughness MAE 0.260" in text
    assert "GLB 28.26 dB, USDZ 22.61 dB; GLB diffuse alone 36.99 dB; 2 import problem(s)" in text
    metal = wood.assign(target_albedo_rmse=[0.112], target_albedo_rmse_scaled=[None])
    assert "albedo RMSE 0.112, roughness" in " ".join(fidelity_lines(metal))
    assert fidelity_lines(pd.DataFrame({"target_psnr_db": [None]})) == []
    kept = pd.DataFrame({"uv_layout": ["kept"], "uv_why": ["usable: 13 islands; one material"]})
    assert fidelity_lines(kept) == ["UV layout: the input's own (usable: 13 islands; one material)"]
    atlas = pd.DataFrame({"uv_layout": ["atlas"], "uv_why": ["auto: the input has no texture coordinates"]})
    assert fidelity_lines(atlas) == ["UV layout: a new atlas (auto: the input has no texture coordinates)"]
    lod = pd.DataFrame(
        {
            "lod_faces": [[20352, 10176, 407]],
            "lod_glb_bytes": [[2670000, 1400000, 310000]],
            "lod_fidelity_psnr_db": [[48.90, 41.20, 30.05]],
        }
    )
    expected = "lod0 20,352 faces, 2.67 MB GLB, 48.90 dB; lod1 10,176 faces, 1.40 MB GLB, 41.20 dB; lod2 407 faces"
    assert expected in " ".join(fidelity_lines(lod))


@pytest.mark.parametrize("single_file", [False, True])
def test_html_report_opens_in_chromium(trained, tmp_path, single_file):
    """A small report of a trained cell, as a folder and as one file, loads in headless Chromium
    from disk with no console errors, and its 3D viewer draws the model (screenshot not blank).
    The synthetic 150-cell report is tested in tests/results/test_site.py."""
    from stages import html_report
    from stages.config.sections import ReportSettings

    require_tool(
        (REPO / "node_modules" / "@google" / "model-viewer").is_dir(),
        "node_modules missing (scripts/setup.sh runs npm ci when npm exists)",
    )
    results, cell = results_with_cell(trained, tmp_path)
    report.run(results, [("candle", "wax", "base")], results / "report")
    out = html_report.run(results, results / "report", [("candle", "wax", "base")], ReportSettings(single_file=single_file))
    assert out["viewers"] == 1
    index = results / "report" / "index.html"
    page = index if single_file else results / "report" / "cells" / "candle" / "wax" / "base" / "index.html"
    text = page.read_text()
    refs = page_references(text)
    assert refs and not any(r.startswith(("http:", "https:", "//", "/", "file:")) for r in refs)  # nothing from elsewhere
    if single_file:
        assert "<script src" not in text and "data:model/gltf-binary;base64," in text
        # everything inline but the downloads, which link the cell's own export files in the results
        offered = [r for r in refs if not r.startswith(("data:", "#"))]
        assert offered and all((index.parent / r).resolve().is_file() for r in offered), offered
    result = browser_check("single" if single_file else "cell", page, tmp_path / "shot.png")
    assert result["errors"] == [] and result["viewers"] == result["loaded"] == 1
    assert result["environment"].endswith("light.hdr") or "#light.hdr" in result["environment"]
    assert_not_blank(tmp_path / "shot.png")


def test_image_guided_metrics_psnr_ssim(trained, tmp_path):
    from stages import metrics

    s = OptimizeSettings(
        iterations=2, guidance="image", target_renderer="sg", image_size=32, width=16, crops=0, light_lobes=4, eval_width=32
    )
    optimize.run(trained / "train.npz", trained / "eval.npz", "", tmp_path / "opt", s, "cpu")
    rs = RaycacheSettings(
        views=1, resolution=16, eval_resolution=16, metrics_azimuths=3, metrics_elevations_deg=(0.0,), metrics_resolution=48
    )
    raycache_run(trained / "mesh.ply", tmp_path / "t.npz", tmp_path / "e.npz", tmp_path / "m.json", rs, tmp_path / "metrics.npz")
    out = metrics.run(
        tmp_path / "opt" / "field.pt", tmp_path / "metrics.npz", "x", ["x"], tmp_path / "met", MetricsSettings(clip=False)
    )
    it = out["image_target"]
    assert it["weights"].startswith("image targets") and 5 < it["psnr_db"] < 60 and 0 < it["ssim"] <= 1
    assert "evaluation" not in out and "guidance" not in out
    assert (tmp_path / "met" / "targets.png").is_file()


def test_decimation_shortfall_reaches_summary_and_report(trained, tmp_path):
    """A decimation that stopped short of its target is a column of the summary and a banner of
    the report, with the reason the stage recorded."""
    import pandas as pd

    from stages import html_report

    results, cell = results_with_cell(trained, tmp_path)
    (results / "candle" / "decimate").mkdir(parents=True)
    reason = "1000 separate triangles: no edge can collapse without deleting a component"
    dec = {"faces_after": 1000, "target_faces": 500, "target_reached": False, "target_shortfall_reason": reason}
    (results / "candle" / "decimate" / "meta.json").write_text(json.dumps({"stats": dec, "timings_s": {"total": 0.1}}))
    report.run(results, [("candle", "wax", "base")], results / "report")
    row = pd.read_csv(results / "report" / "summary.csv").iloc[0]
    assert not row["decimation_target_reached"] and row["decimation_shortfall"] == reason
    html_report.run(results, results / "report", [("candle", "wax", "base")], model_viewer=tmp_path / "absent.js")
    for page in (results / "report" / "index.html", results / "report" / "cells" / "candle" / "wax" / "base" / "index.html"):
        assert "DECIMATION SHORT OF TARGET: mesh candle has 1000 faces for a target of 500" in page.read_text()
