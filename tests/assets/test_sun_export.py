"""The learned suns in the assets: left out of the environment image, carried as lights (glTF
``KHR_lights_punctual`` directional lights, USD ``DistantLight`` s) with the direction, colour,
irradiance and angular size the field learned, in the file's frame; each file passing its
validator. Blender's reading of them is tests/reference/test_blender_assets.py's."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from conftest import require_tool
from gltf_quad import buffers, glb_bytes
from PIL import Image

from stages.assets.baking import light_image
from stages.assets.formats import recorded_lights
from stages.assets.formats.base import facing_rotation
from stages.assets.formats.gltf import validate_glb
from stages.assets.ownformat import write_document_glb
from stages.geometry.sourcemesh import glb_chunks, read_source
from stages.model.checkpoint import load_field
from stages.render.envmap import equirect_directions
from stages.render.light import DistantLight


def turn(q, v) -> np.ndarray:
    """``v`` turned by the unit quaternion ``q = (x, y, z, w)``, written out:
    ``v + 2 w (u x v) + 2 u x (u x v)`` with ``u = (x, y, z)``."""
    u, w = np.asarray(q[:3], np.float64), float(q[3])
    v = np.asarray(v, np.float64)
    return v + 2.0 * w * np.cross(u, v) + 2.0 * np.cross(u, np.cross(u, v))


@pytest.mark.parametrize(
    "d", [(0.0, 0.0, 1.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0), (-0.48, 0.57, 0.66), (1e-9, 0.0, -1.0), (0.3, -0.9, 0.1)]
)
def test_a_light_node_turned_to_shine_away_from_its_direction(d):
    d = np.asarray(d) / np.linalg.norm(d)
    q = facing_rotation(d)
    assert abs(np.linalg.norm(q) - 1.0) < 1e-12
    assert np.allclose(turn(q, [0.0, 0.0, -1.0]), -d, atol=1e-9)  # it shines along -direction


def test_a_distant_lights_record_reads_back_and_turns():
    light = DistantLight((0.0, 0.6, 0.8), (3.0, 2.0, 1.0), math.radians(1.5))
    back = DistantLight.from_record(json.loads(json.dumps(light.record())))
    assert np.allclose(back.direction, light.direction) and back.irradiance == light.irradiance
    assert back.radius == pytest.approx(light.radius)
    r = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    assert np.allclose(light.turned(r).direction, r @ np.array(light.direction))
    stats = {"distant_lights": [light.record()]}
    assert np.allclose(recorded_lights(stats, r)[0].direction, r @ np.array(light.direction))
    assert recorded_lights({}) == ()


@pytest.fixture(scope="module")
def sun(sun_cell):
    field, _ = load_field(sun_cell / "opt" / "field.pt", "cpu")
    (light,) = field.light().distant_lights()
    return field, light


def test_the_environment_image_leaves_the_sun_out(sun):
    field, light = sun
    full = field.light()
    assert [c.kind for c in full.components] == ["sg", "sun"]
    assert [c.kind for c in full.environment().components] == ["sg"]
    image, distant = light_image(field, 256)
    assert distant == [light]
    with torch.no_grad():
        dirs = equirect_directions(128, 256).reshape(-1, 3)
        sky = full.environment().radiance(dirs).reshape(128, 256, -1).numpy()
        everything = full.radiance(dirs).reshape(128, 256, -1).numpy()
    assert np.allclose(image, sky, rtol=1e-5, atol=1e-6)
    assert everything.max() > 10.0 * image.max()  # the disc is in the light, not in the image


def test_the_assets_carry_the_learned_sun(sun, sun_cell):
    _, light = sun
    bake = json.loads((sun_cell / "bake" / "meta.json").read_text())["stats"]
    export = json.loads((sun_cell / "export" / "meta.json").read_text())["stats"]
    assert bake["distant_lights"] == [light.record()]
    (shipped,) = export["distant_lights"]  # the traced mesh, exported: the normalised frame's directions
    assert np.allclose(shipped["direction"], light.direction, atol=1e-6) and shipped["irradiance"] == list(light.irradiance)
    e = np.asarray(light.irradiance)
    # glTF: a directional light, intensity in lux (683 lm/W), its node turned to shine along -d
    raw, _ = glb_chunks((sun_cell / "export" / "model.glb").read_bytes())
    doc = json.loads(raw)
    assert "KHR_lights_punctual" in doc["extensionsUsed"]
    (gl,) = doc["extensions"]["KHR_lights_punctual"]["lights"]
    assert gl["type"] == "directional"
    assert gl["intensity"] == pytest.approx(683.0 * e.max())
    assert np.allclose(gl["color"], e / e.max())
    assert gl["extras"]["radius_deg"] == pytest.approx(math.degrees(light.radius))
    (node,) = [n for n in doc["nodes"] if "KHR_lights_punctual" in n.get("extensions", {})]
    assert doc["nodes"].index(node) in doc["scenes"][doc["scene"]]["nodes"]
    assert np.allclose(turn(node["rotation"], [0.0, 0.0, -1.0]), -np.asarray(light.direction), atol=1e-6)
    # USD: a DistantLight of the disc's diameter, normalised (intensity = illuminance), shining along -d
    from pxr import Gf, Usd, UsdGeom, UsdLux

    stage = Usd.Stage.Open(str(sun_cell / "export" / "model.usda"))
    (prim,) = [p for p in stage.Traverse() if p.IsA(UsdLux.DistantLight)]
    usd = UsdLux.DistantLight(prim)
    assert usd.GetAngleAttr().Get() == pytest.approx(2.0 * math.degrees(light.radius), rel=1e-6)
    assert usd.GetNormalizeAttr().Get() is True
    assert usd.GetIntensityAttr().Get() == pytest.approx(e.max(), rel=1e-6)
    assert np.allclose(np.asarray(usd.GetColorAttr().Get()), e / e.max(), atol=1e-6)
    m = UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(Usd.TimeCode.Default())
    shine = m.TransformDir(Gf.Vec3d(0.0, 0.0, -1.0))
    assert np.allclose(np.asarray(shine) / np.linalg.norm(shine), -np.asarray(light.direction), atol=1e-6)
    # each file passed its validator (the export stops otherwise); the glTF one must have run in CI
    reports = export["validation"]
    assert all(reports[f"model.{s}"]["errors"] == 0 for s in ("usda", "usdz"))
    require_tool(reports["model.glb"].get("ran", False), "the Khronos glTF-Validator did not run (npm ci installs it)")
    assert reports["model.glb"]["errors"] == 0


def test_a_kept_documents_own_lights_stay_and_the_sun_follows_them(tmp_path):
    """A glTF input with a light of its own: the sun is appended after it, on a node of its own in
    the default scene, the document's own light and node untouched; the validator passes."""
    doc = {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0, 1]}],
        "nodes": [
            {"mesh": 0, "name": "quad"},
            {"name": "lamp", "translation": [0, 2, 0], "extensions": {"KHR_lights_punctual": {"light": 0}}},
        ],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2}]}],
        "extensions": {"KHR_lights_punctual": {"lights": [{"type": "point", "intensity": 5.0}]}},
        "extensionsUsed": ["KHR_lights_punctual"],
        **buffers(),
    }
    (tmp_path / "in").mkdir()
    src = tmp_path / "in" / "asset.glb"
    src.write_bytes(glb_bytes(doc))
    textures = tmp_path / "textures"
    textures.mkdir()
    for key in ("basecolor", "metallic_roughness", "normal", "specular"):
        Image.fromarray(np.full((8, 8, 3), 128, np.uint8)).save(textures / f"{key}.png")
    light = DistantLight((0.0, 0.6, 0.8), (3.0, 2.0, 1.0), math.radians(1.5))
    out = tmp_path / "model.glb"
    notes = write_document_glb(out, read_source(src), textures, {"run": "test"}, "gltf", False, (), (light,))
    assert any("KHR_lights_punctual" in n for n in notes)
    got = json.loads(glb_chunks(out.read_bytes())[0])
    lights = got["extensions"]["KHR_lights_punctual"]["lights"]
    assert [x["type"] for x in lights] == ["point", "directional"] and lights[0]["intensity"] == 5.0
    assert got["nodes"][1]["extensions"]["KHR_lights_punctual"]["light"] == 0
    assert got["nodes"][2]["extensions"]["KHR_lights_punctual"]["light"] == 1
    assert got["scenes"][0]["nodes"] == [0, 1, 2]
    report = validate_glb(out)
    require_tool(report.get("ran", False), "the Khronos glTF-Validator did not run (npm ci installs it)")
    assert report["errors"] == 0, report["messages"]
