"""The bake's ambient occlusion map (issue 32): glTF's occlusion, the cosine-weighted visible share
of the hemisphere, against closed forms written here; its interpolation between traced samples
against tracing at the texels themselves; when the bake writes it; and its wiring in the GLB and
the USD (validated, and in Blender)."""

import json
import math
from types import SimpleNamespace

import numpy as np
import pygltflib
import pytest
from conftest import floor_and_ball, require_blender
from PIL import Image

from stages import bake, export
from stages.assets.baking import occlusion_decision
from stages.config.sections import BakeSettings, ExportSettings
from stages.core.errors import ConfigError
from stages.geometry.meshio import TriMesh
from stages.geometry.tracing import EmbreeTracer
from stages.geometry.visibility import (
    OcclusionSamples,
    ambient_occlusion,
    blocked_share,
    fibonacci_directions,
    sample_surface,
    surface_offset,
    trace_visibility,
)


def _well(radius: float, depth: float) -> TriMesh:
    """A floor with a round well of ``radius`` and ``depth`` cut into it: a tube open at the top,
    closed by a disc at its bottom (z = -depth), the floor's ring around it at z = 0."""
    n = 256
    a = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    ring = np.stack([radius * np.cos(a), radius * np.sin(a)], 1)
    top = np.column_stack([ring, np.zeros(n)])
    bottom = np.column_stack([ring, np.full(n, -depth)])
    outer = np.column_stack([30.0 * np.cos(a), 30.0 * np.sin(a), np.zeros(n)])
    centre = np.array([[0.0, 0.0, -depth]])
    v = np.concatenate([top, bottom, outer, centre])
    i = np.arange(n)
    j = (i + 1) % n
    wall = np.concatenate([np.stack([i, j, n + j], 1), np.stack([i, n + j, n + i], 1)])
    floor = np.concatenate([np.stack([i, 2 * n + i, 2 * n + j], 1), np.stack([i, 2 * n + j, j], 1)])
    disc = np.stack([np.full(n, 3 * n), n + j, n + i], 1)
    return TriMesh(v, np.concatenate([wall, floor, disc]).astype(np.int64))


def _occlusion_at(mesh: TriMesh, points, normals, directions) -> np.ndarray:
    bits = trace_visibility(EmbreeTracer(mesh), points, normals, directions, surface_offset(mesh.vertices))
    return ambient_occlusion(bits, normals, directions)


@pytest.mark.parametrize("height,radius", [(2.0, 1.0), (1.5, 1.0)])
def test_occlusion_under_a_ball_is_the_cosine_weighted_share(height, radius):
    """Under a ball of radius r at height H the blocked cone has half-angle b = asin(r / H); its
    cosine-weighted share of the hemisphere is (1/pi) int_0^b cos t sin t dt 2 pi = sin^2 b, so the
    occlusion is 1 - (r / H)^2. The uniform share (1 - cos b blocked) is not it."""
    mesh = floor_and_ball(height, radius)
    dirs = fibonacci_directions(4096)
    pts = np.array([[0.0, 0.0, 0.0], [15.0, 15.0, 0.0]])
    nrm = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    ao = _occlusion_at(mesh, pts, nrm, dirs)
    expected = 1.0 - (radius / height) ** 2
    assert ao[0] == pytest.approx(expected, abs=0.01)
    assert ao[1] == pytest.approx(1.0, abs=1e-3)  # far away: nothing blocks
    # mutation: the uniform (solid-angle) share differs by far more than the tolerance
    bits = trace_visibility(EmbreeTracer(mesh), pts, nrm, dirs, surface_offset(mesh.vertices))
    uniform = 1.0 - blocked_share(bits, nrm, dirs)
    assert abs(uniform[0] - expected) > 0.05
    assert uniform[0] == pytest.approx(math.sqrt(1.0 - (radius / height) ** 2), abs=0.01)


def test_occlusion_at_the_bottom_of_a_well():
    """At the centre of a well's bottom only the cone of half-angle a = atan(R / D) escapes: the
    occlusion is sin^2 a; and exactly 1 on the open floor far from it."""
    mesh = _well(1.0, 2.0)
    dirs = fibonacci_directions(4096)
    pts = np.array([[0.0, 0.0, -2.0], [20.0, 0.0, 0.0]])
    nrm = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    ao = _occlusion_at(mesh, pts, nrm, dirs)
    assert ao[0] == pytest.approx(math.sin(math.atan(0.5)) ** 2, abs=0.01)
    assert ao[1] == 1.0


def test_interpolated_occlusion_against_tracing_at_the_points():
    """The samples' interpolation, read at fresh points, against the occlusion traced at those
    points (more open side): close on average and at the dark contact; the far wall of a thin
    part does not bleed in (a floor's underside stays open under the ball's dark contact)."""
    mesh = floor_and_ball(1.02, 1.0)  # the ball nearly touches the floor: a dark contact ring
    dirs = fibonacci_directions(512)
    samples = OcclusionSamples(mesh, EmbreeTracer(mesh), dirs, 65536, seed=1)
    assert samples.summary()["samples"] == 65536 and samples.summary()["p05"] < samples.summary()["median"]
    # query points near the ball's contact, on the floor's top and the ball
    pts, face = sample_surface(mesh, 200_000, seed=7)
    near = np.linalg.norm(pts[:, :2], axis=1) < 2.0
    pts, face = pts[near][:2000], face[near][:2000]
    normals = mesh.face_normals[face]
    traced = np.maximum(_occlusion_at(mesh, pts, normals, dirs), _occlusion_at(mesh, pts, -normals, dirs))
    got = samples.at(pts, normals)
    assert np.abs(got - traced).mean() < 0.03, np.abs(got - traced).mean()
    assert traced.min() < 0.5 and got.min() < 0.6  # the contact's darkness survives the blend
    # the floor's underside (0.1 below the top) directly under the contact: open, not the top's dark
    under = np.array([[0.05, 0.0, -0.1]])
    assert samples.at(under, np.array([[0.0, 0.0, -1.0]]))[0] > 0.95


def test_occlusion_decision_and_settings():
    with_vis = SimpleNamespace(visibility_directions=256)
    without = SimpleNamespace(visibility_directions=0)
    shadowed, unshadowed = SimpleNamespace(shadows=True), SimpleNamespace(shadows=False)
    assert occlusion_decision("auto", shadowed, with_vis) == {
        "baked": True,
        "why": "auto: the field was trained with shadows",
        "directions": 256,
    }
    assert not occlusion_decision("auto", unshadowed, with_vis)["baked"]
    assert not occlusion_decision("auto", shadowed, without)["baked"]
    assert occlusion_decision("on", unshadowed, without) == {"baked": True, "why": "bake.occlusion: on", "directions": 512}
    assert not occlusion_decision("off", shadowed, with_vis)["baked"]
    assert BakeSettings(occlusion=True).occlusion == "on"  # YAML 1.1's bare on
    with pytest.raises(ConfigError, match="bake.occlusion must be one of"):
        BakeSettings(occlusion="always")
    with pytest.raises(ConfigError, match="occlusion_samples"):
        BakeSettings(occlusion_samples=10)


def _bake_and_export(cell, out, occlusion: str) -> tuple[dict, dict]:
    bake.run(
        cell / "mesh.ply",
        cell / "opt" / "field.pt",
        cell / "eval.npz",
        out / "bake",
        BakeSettings(texture_size=256, eval_width=32, occlusion=occlusion, occlusion_samples=4096),
    )
    bake_dir = out / "bake"
    export.run(cell / "mesh.ply", cell / "transform.json", bake_dir, bake_dir / "preview.png", out / "export", ExportSettings())
    read = [json.loads((out / f / "meta.json").read_text())["stats"] for f in ("bake", "export")]
    return read[0], read[1]


@pytest.mark.slow
def test_bake_writes_occlusion_and_the_assets_read_it(trained_cell, tmp_path):
    """``off`` writes none (red channel 1, no material reads it); ``auto`` wrote it for the trained
    cell (the candle's cache holds visibility, its field cast shadows); ``on`` writes it into the
    red channel, the GLB's occlusionTexture and the USD's occlusion read that channel, and both
    pass their validators (the export raises on any error)."""
    own = json.loads((trained_cell / "bake" / "meta.json").read_text())["stats"]["occlusion"]
    assert own["baked"] is True and own["why"] == "auto: the field was trained with shadows"
    baked, exported = _bake_and_export(trained_cell, tmp_path / "off", "off")
    assert baked["occlusion"]["baked"] is False and baked["occlusion"]["why"] == "bake.occlusion: off"
    assert exported["occlusion"] is False
    mr = np.asarray(Image.open(tmp_path / "off" / "bake" / "textures" / "metallic_roughness.png"))
    assert (mr[..., 0] == 255).all()
    assert b"occlusionTexture" not in (tmp_path / "off" / "export" / "model.glb").read_bytes()
    assert "inputs:occlusion" not in (tmp_path / "off" / "export" / "model.usda").read_text()

    baked, exported = _bake_and_export(trained_cell, tmp_path / "on", "on")
    assert baked["occlusion"]["baked"] is True and baked["occlusion"]["samples"] == 4096
    assert exported["occlusion"] is True
    mr = np.asarray(Image.open(tmp_path / "on" / "bake" / "textures" / "metallic_roughness.png"))
    assert mr[..., 0].min() < 230  # the candle's base and wick darken
    material = pygltflib.GLTF2().load(str(tmp_path / "on" / "export" / "model.glb")).materials[0]
    assert material.occlusionTexture.index == material.pbrMetallicRoughness.metallicRoughnessTexture.index
    usda = (tmp_path / "on" / "export" / "model.usda").read_text()
    assert "inputs:occlusion.connect = </Asset/Looks/TangoMaterial/RoughnessTexture.outputs:r>" in usda
    assert exported["usd_validation_errors"] == 0
    if exported["validation"]["model.glb"].get("ran"):
        assert exported["gltf_validation_errors"] == 0


@pytest.mark.slow
def test_blender_reads_the_glb_occlusion(trained_cell, tmp_path):
    """Blender's glTF importer wires the occlusion (its red channel) into its "glTF Material
    Output" group, and the import check finds it there; on an export without one (``off``) the
    same check reports it missing. The USDZ imports intact (Blender's USD importer does not read it)."""
    from stages.assets.formats import export_mesh, read_atlas
    from stages.geometry.meshio import load_ply
    from stages.geometry.normalization import Similarity
    from stages.reference import blender

    require_blender()
    _bake_and_export(trained_cell, tmp_path / "on", "on")
    cell = trained_cell
    tf = Similarity.from_json(json.loads((cell / "transform.json").read_text()))
    geom = export_mesh(load_ply(cell / "mesh.ply"), read_atlas(tmp_path / "on" / "bake" / "atlas.npz"), tf)
    glb = blender.run_job({"asset": str(tmp_path / "on" / "export" / "model.glb")}, tmp_path / "glb")
    checks = blender.check_import(glb, geom, 1.0, occlusion=True)
    assert checks["problems"] == []
    assert checks["wiring"]["group:Occlusion"]["output"] == "Red"
    usdz = blender.run_job({"asset": str(tmp_path / "on" / "export" / "model.usdz")}, tmp_path / "usdz")
    assert blender.check_import(usdz, geom, 1.0)["problems"] == []
    # an export without an occlusion map: the check says so
    _bake_and_export(cell, tmp_path / "off", "off")
    plain = blender.run_job({"asset": str(tmp_path / "off" / "export" / "model.glb")}, tmp_path / "plain")
    plain_geom = export_mesh(load_ply(cell / "mesh.ply"), read_atlas(tmp_path / "off" / "bake" / "atlas.npz"), tf)
    assert any("group:Occlusion" in p for p in blender.check_import(plain, plain_geom, 1.0, occlusion=True)["problems"])
