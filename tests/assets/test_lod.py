"""Levels of detail: the high-to-low projection against analytic spheres, the level bake carrying the
fine surface's normal and material, and the lod stage's files (USD variant set, glTF MSFT_lod)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch
from conftest import icosphere, require_tool, run_lod

from stages.assets.baking import bake_level, decode_textures, project_to_surface
from stages.assets.formats.gltf import validate_glb
from stages.config.sections import BakeSettings, LodSettings
from stages.core.errors import ConfigError, StageInputError
from stages.geometry.atlas import rasterize_atlas
from stages.geometry.meshio import TriMesh, load_ply
from stages.geometry.normals import NormalSpec
from stages.model.lights import LightModule
from stages.model.lights.sg import SGLightModule
from stages.model.networks import Material


def _scaled(mesh: TriMesh, s: float) -> TriMesh:
    return TriMesh(mesh.vertices * s, mesh.faces)


def _points_on(mesh: TriMesh, rng, per_face: int = 4):
    f = np.repeat(np.arange(len(mesh.faces)), per_face)
    b = rng.dirichlet([1.0, 1.0, 1.0], len(f))
    p = (b[:, :, None] * mesh.vertices[mesh.faces[f]]).sum(1)
    return p, mesh.face_normals[f]


def _angle_deg(a, b):
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip((a * b).sum(1), -1, 1)))


@pytest.mark.parametrize("scale, sign", [(0.97, 1.0), (1.12, -1.0)])
def test_projection_reaches_the_fine_sphere_along_the_coarse_normal(scale, sign):
    """A coarse icosphere inside (wholly outside: its inradius is 0.934) the fine one: every ray forwards (backwards) along the
    coarse normal meets the fine sphere; the hit lies on it (radius 1 up to the fine mesh's sag,
    about 2.4e-4) and on the ray (written out: no component across the normal)."""
    fine = icosphere(5)
    coarse = _scaled(icosphere(1), scale)
    p, n = _points_on(coarse, np.random.default_rng(0))
    proj = project_to_surface(fine, p, n, 0.2, NormalSpec("flat"))
    assert proj.found.all()
    r = np.linalg.norm(proj.points, axis=1)
    assert np.abs(r - 1.0).max() < 1e-3
    d = proj.points - p
    assert np.linalg.norm(np.cross(d, n), axis=1).max() < 1e-5
    assert (np.sign(proj.offset) == sign).all()
    np.testing.assert_allclose(np.abs(proj.offset), np.linalg.norm(d, axis=1), atol=1e-5)
    # the fine mesh's normal at the hit: its face's, turned to the coarse normal's side
    assert ((proj.normals * n).sum(1) > 0).all()
    assert _angle_deg(proj.normals, proj.points).max() < 3.0


def test_projection_keeps_the_coarse_point_beyond_the_search_distance():
    fine = icosphere(4)
    coarse = _scaled(icosphere(1), 0.8)  # 0.2 inside: out of reach of a 0.1 search
    p, n = _points_on(coarse, np.random.default_rng(1), 1)
    proj = project_to_surface(fine, p, n, 0.1, NormalSpec("flat"))
    assert not proj.found.any() and np.isnan(proj.offset).all()
    np.testing.assert_array_equal(proj.points, p)
    np.testing.assert_array_equal(proj.normals, n)


def test_projection_prefers_the_nearer_side():
    """A thin shell: the fine surface both 0.01 outside and 0.05 inside the coarse point; the
    nearer (outside) one is taken, and with only the inner sphere in reach, the inner one."""
    outer, inner = icosphere(4), _scaled(icosphere(4), 0.94)
    both = TriMesh(
        np.concatenate([outer.vertices, inner.vertices]), np.concatenate([outer.faces, inner.faces + len(outer.vertices)])
    )
    p = np.array([[0.0, 0.99, 0.0]])
    n = np.array([[0.0, 1.0, 0.0]])
    near = project_to_surface(both, p, n, 0.2, NormalSpec("flat"))
    assert near.offset[0] == pytest.approx(0.01, abs=1e-3)
    p_in = np.array([[0.0, 0.96, 0.0]])  # 0.02 above the inner sphere, 0.04 below the outer
    assert project_to_surface(both, p_in, n, 0.2, NormalSpec("flat")).offset[0] == pytest.approx(-0.02, abs=1e-3)


def test_projection_skips_the_far_wall_of_a_thin_part():
    """A hollow shell (outer sphere facing out, inner sphere at 0.98 facing in, as a thick-walled
    vase's inner wall does): from a coarse point inside the wall, the inner sphere is nearer
    backwards but faces away; the outer one, forwards, is this texel's surface. A fine mesh wound
    the other way round everywhere still projects (onto the nearest hit, flagged opposite)."""
    outer, inner = icosphere(4), _scaled(icosphere(4), 0.98)
    shell = TriMesh(
        np.concatenate([outer.vertices, inner.vertices]),
        np.concatenate([outer.faces, inner.faces[:, ::-1] + len(outer.vertices)]),
    )
    p, n = np.array([[0.0, 0.985, 0.0]]), np.array([[0.0, 1.0, 0.0]])
    proj = project_to_surface(shell, p, n, 0.1, NormalSpec("flat"))
    assert proj.offset[0] == pytest.approx(0.015, abs=1e-3) and not proj.opposite[0]
    inverted = TriMesh(outer.vertices, outer.faces[:, ::-1])
    flipped = project_to_surface(inverted, np.array([[0.0, 0.97, 0.0]]), n, 0.1, NormalSpec("flat"))
    assert flipped.found[0] and flipped.opposite[0] and flipped.offset[0] == pytest.approx(0.03, abs=1e-3)
    assert flipped.normals[0] @ n[0] > 0.99  # turned to the coarse normal's side


class _PositionField(torch.nn.Module):
    """Albedo a smooth function of position, the normal as given (no normal network)."""

    def __init__(self, normals: str = "smooth"):
        super().__init__()
        self.light = LightModule([SGLightModule(4)])
        self.normals = NormalSpec(normals)

    @staticmethod
    def albedo(p):
        return torch.stack([0.5 + 0.4 * torch.sin(4 * p[:, 0]), 0.5 + 0.4 * p[:, 1], 0.3 + 0.2 * torch.cos(3 * p[:, 2])], -1)

    def surface(self, p, n, view=None):
        return Material(self.albedo(p), torch.full_like(p, 0.2), torch.full_like(p[:, :1], 0.4)), n


@pytest.mark.parametrize("normals", ["smooth", "flat"])
def test_level_bake_carries_the_fine_normal_and_material(normals):
    """An ellipsoid (semi-axes 1, 0.7, 0.5) at 80 faces as the level of the same ellipsoid at
    20,480: decoded through the level's frame (MikkTSpace's T, B = w (N x T), N interpolated,
    written out here), the normal map gives the ellipsoid's analytic normal (the gradient
    (x/a^2, y/b^2, z/c^2)) at the projected point, which the level's own shading normal (smooth
    or flat) misses by degrees; the albedo is the field's at the fine point, not at the coarse one."""
    axes = np.array([1.0, 0.7, 0.5])
    fine, coarse = icosphere(5), icosphere(1)
    fine, coarse = TriMesh(fine.vertices * axes, fine.faces), TriMesh(coarse.vertices * axes, coarse.faces)
    res = bake_level(fine, coarse, _PositionField(normals), 256, BakeSettings(dilation=1, light_width=32), 0.2)
    face, bary = rasterize_atlas(res.texels.atlas.uv, 256)
    filled = face >= 0
    f, b = face[filled], bary[filled].astype(np.float64)
    c = np.stack([1 - b[:, 0] - b[:, 1], b[:, 0], b[:, 1]], 1)[..., None]
    fr = res.frames
    t = (c * fr.tangents[f]).sum(1)
    n = (c * fr.normals[f]).sum(1)
    bt = fr.handedness[f][:, None] * np.cross(n, t)
    ts = decode_textures(res.textures)["normal"][filled]
    world = ts[:, :1] * t + ts[:, 1:2] * bt + ts[:, 2:3] * n
    p_low = (c * coarse.vertices[coarse.faces[f]]).sum(1)
    found = res.projection.found
    assert found.mean() > 0.999 and not res.projection.opposite.any()
    p_high = res.projection.points
    analytic = p_high / axes**2
    err = _angle_deg(world, analytic)[found]
    own = _angle_deg(n, analytic)[found]  # what a bake without the fine surface would give
    # the fine mesh's own normals: smooth ones within 0.3 deg (p99) of the analytic, flat ones 1.5
    assert np.percentile(err, 99) < (0.6 if normals == "smooth" else 2.0)
    assert own.mean() > 3.0 and np.percentile(own, 99) > 5 * np.percentile(err, 99)
    got = decode_textures(res.textures)["albedo"][filled]
    at_high = _PositionField.albedo(torch.from_numpy(p_high)).numpy()
    at_low = _PositionField.albedo(torch.from_numpy(p_low)).numpy()
    quant = 0.5 / 255 / 0.4 + 1e-6  # half an 8-bit sRGB step, in linear units
    assert np.abs(got - at_high)[found].max() < quant
    assert np.abs(got - at_low)[found].max() > 5 * quant


# ------------------------------------------------------------------------------------- the stage
def test_lod_settings_refuse_bad_levels():
    for levels in ((0.5, 0.5), (0.1, 0.5), (1.0,), (0.0,), ()):
        with pytest.raises(ConfigError, match="levels"):
            LodSettings(levels=levels)
    assert LodSettings(levels=(0.5, 0.1)).screen_coverage() == [0.25, 0.05, 0.0]
    # texture width: the full bake's times sqrt(fraction) to the nearest power of two (the tie at
    # 1/2 going up at every full size), at least min_texture_size, never above the full
    sizes = [LodSettings().level_texture_size(1024, f) for f in (0.5, 0.1, 0.02)]
    assert sizes == [1024, 256, 128]  # 724, 324, 145 before rounding to powers of two
    assert [LodSettings().level_texture_size(full, 0.5) for full in (256, 512, 1024, 2048, 4096)] == [256, 512, 1024, 2048, 4096]
    assert LodSettings().level_texture_size(1024, 0.12) == 256  # 354.7: log2 8.47, nearer 256
    assert LodSettings().level_texture_size(1024, 0.13) == 512  # 369.2: log2 8.53, nearer 512
    assert (
        LodSettings().level_texture_size(256, 0.02) == 64 and LodSettings(min_texture_size=16).level_texture_size(256, 0.02) == 32
    )
    assert LodSettings(texture_size=300).level_texture_size(1024, 0.02) == 300


def test_lod_stage_files_and_figures(lod_cell):
    meta = json.loads((lod_cell / "lod" / "meta.json").read_text())
    rows = meta["stats"]["levels"]
    faces = len(load_ply(lod_cell / "mesh.ply").faces)
    assert [r["level"] for r in rows] == ["lod0", "lod1", "lod2"]
    assert rows[0]["faces"] == faces
    for r, frac in zip(rows[1:], (0.5, 0.1), strict=True):
        assert abs(r["faces"] - frac * faces) <= 0.01 * frac * faces + 1
        assert r["texels_on_traced_surface"] > 0.99
        assert r["file_bytes"]["model.glb"] < rows[0]["file_bytes"]["model.glb"]
        assert r["bake_seconds"] > 0 and r["decimate_seconds"] > 0
        level_meta = json.loads((lod_cell / "lod" / r["level"] / "meta.json").read_text())
        assert level_meta["origin"]["test_only"] is True  # the tiny random CLIP made it
        assert load_ply(lod_cell / "lod" / r["level"] / "mesh.ply").faces.shape[0] == r["faces"]
    for r in rows:
        assert np.isfinite(r["fidelity_psnr_db"]) and 0.9 < r["silhouette_iou"] <= 1.0
    # lod0 is the full bake read back: as faithful as the bake stage measured it
    bake_psnr = json.loads((lod_cell / "bake" / "meta.json").read_text())["stats"]["bake_psnr_db"]
    assert rows[0]["fidelity_psnr_db"] == pytest.approx(bake_psnr, abs=0.5)
    assert meta["origin"]["test_only"] is True
    for rel, r in meta["stats"]["validation"].items():
        assert r.get("errors", 0) == 0, rel
    assert (lod_cell / "lod" / "levels.png").is_file()


def test_lod_usd_variant_set_switches_meshes(lod_cell):
    from pxr import Usd, UsdGeom

    rows = json.loads((lod_cell / "lod" / "meta.json").read_text())["stats"]["levels"]
    for name in ("model_lods.usda", "model_lods.usdz"):
        stage = Usd.Stage.Open(str(lod_cell / "lod" / name))
        vset = stage.GetDefaultPrim().GetVariantSets().GetVariantSet("LOD")
        assert vset.GetVariantNames() == ["lod0", "lod1", "lod2"] and vset.GetVariantSelection() == "lod0"
        for r in rows:
            vset.SetVariantSelection(r["level"])
            mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Asset/Geometry/Mesh"))
            assert len(mesh.GetFaceVertexCountsAttr().Get()) == r["faces"]
            shader = stage.GetPrimAtPath("/Asset/Looks/TangoMaterial/NormalTexture")
            assert shader.GetAttribute("inputs:file").Get().path == f"{r['level']}/textures/normal.png"
        data = stage.GetRootLayer().customLayerData
        assert list(data["tango_stylize_lod"]["levels"]) == ["lod0", "lod1", "lod2"]


def test_lod_glb_lists_the_levels_with_msft_lod(lod_cell):
    import pygltflib

    rows = json.loads((lod_cell / "lod" / "meta.json").read_text())["stats"]["levels"]
    g = pygltflib.GLTF2().load(str(lod_cell / "lod" / "model_lods.glb"))
    assert g.scenes[0].nodes == [0] and "MSFT_lod" in g.extensionsUsed
    assert g.nodes[0].extensions["MSFT_lod"]["ids"] == [1, 2]
    assert g.nodes[0].extras["MSFT_screencoverage"] == [0.25, 0.05, 0.0]
    for k, r in enumerate(rows):
        prim = g.meshes[g.nodes[k].mesh].primitives[0]
        assert g.accessors[prim.indices].count == 3 * r["faces"]
        assert prim.material == k and g.materials[k].normalTexture.index == 4 * k + 2


def test_lod_validators_ran(lod_cell):
    """The Khronos validator accepts the MSFT_lod file (it reports the extension and the coarse
    nodes as infos only); usd-core's validators pass the variant set."""
    validation = json.loads((lod_cell / "lod" / "meta.json").read_text())["stats"]["validation"]
    require_tool(validation["model_lods.glb"]["ran"], "the Khronos glTF-Validator needs Node.js and npm ci")
    glb = validate_glb(lod_cell / "lod" / "model_lods.glb")
    assert glb["errors"] == 0 and glb["warnings"] == 0 and glb["infos"] >= 1
    assert validation["model_lods.usdz"]["validators"] > 0 and validation["model_lods.usdz"]["errors"] == 0


def test_lod_rerun_with_fewer_levels_leaves_no_stale_level(lod_cell, tmp_path):
    """A rerun with fewer levels removes the level folders it no longer makes (the pack would
    otherwise ship them)."""
    d = lod_cell
    out = tmp_path / "lod"
    shutil.copytree(d / "lod", out)
    run_lod(d, out, LodSettings(levels=(0.3,)))
    assert (out / "lod1" / "meta.json").is_file() and not (out / "lod2").exists()
    assert [r["level"] for r in json.loads((out / "meta.json").read_text())["stats"]["levels"]] == ["lod0", "lod1"]


def test_lod_stage_refuses_levels_below_min_faces(trained_cell, tmp_path):
    with pytest.raises(StageInputError, match="min_faces"):
        run_lod(trained_cell, tmp_path / "lod", LodSettings(levels=(0.5, 1e-4)), BakeSettings(texture_size=64))
    assert not (tmp_path / "lod" / "meta.json").exists()


def test_the_stage_reads_its_four_sections_from_one_settings_json():
    from stages.lod import parse_settings

    s = parse_settings('{"lod": {"levels": [0.25]}, "decimate": {"weld": false}}')
    assert s["lod"].levels == (0.25,) and s["decimate"].weld is False
    assert s["bake"] == BakeSettings() and s["export"].units == "original"
    with pytest.raises(ConfigError, match="sections lod, bake, export, decimate"):
        parse_settings('{"lods": {}}')
    with pytest.raises(ConfigError, match=r"lod\.levels"):
        parse_settings('{"lod": {"levels": [1.5]}}')
