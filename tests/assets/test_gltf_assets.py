"""A field trained with glTF's BRDF (``optimize.brdf: gltf``): its networks predict base colour,
metallic and roughness; the bake writes them as they are (metallic in the blue channel), and the
exporters map them without conversion (glTF metallic-roughness without extensions, USD's metallic
workflow), validated; the baked asset renders like the field (fidelity)."""

import json

import numpy as np
import pytest
import torch
from PIL import Image

from stages import bake, export, optimize
from stages.config.sections import BakeSettings, ExportSettings, OptimizeSettings
from stages.core.errors import ConfigError
from stages.model.field import MaterialEdit, StyleField
from stages.render.brdf import GLTF


def test_gltf_field_predicts_base_metallic_and_roughness():
    f = StyleField(OptimizeSettings(width=16, light_lobes=4, brdf="gltf").field_settings())
    pts = torch.rand(50, 3) * 2 - 1
    nrm = torch.nn.functional.normalize(torch.randn(50, 3), dim=-1)
    out = f(pts, nrm, nrm)
    m = out.material
    assert m.brdf is GLTF and m.base.shape == (50, 3) and m.metallic.shape == (50, 1)
    # the TANGO equivalents the figures and material errors read
    torch.testing.assert_close(m.albedo, m.base * (1 - m.metallic))
    torch.testing.assert_close(m.specular, 0.04 * (1 - m.metallic) + m.base * m.metallic)
    assert torch.isfinite(out.shading.rgb).all()
    edited = MaterialEdit(2.0, 0.0).apply(m, 0.01)
    assert float(edited.metallic.detach().abs().max()) == 0.0 and edited.brdf is GLTF


def test_gltf_needs_a_specular_model_of_its_own():
    with pytest.raises(ConfigError, match="isotropic"):
        OptimizeSettings(brdf="gltf", specular_lobe="isotropic")
    with pytest.raises(ConfigError, match="specular: true"):
        OptimizeSettings(brdf="gltf", specular=False)
    with pytest.raises(ConfigError, match="brdf must be one of"):
        OptimizeSettings(brdf="disney")


@pytest.mark.slow
def test_gltf_cell_bakes_and_exports_what_was_trained(trained_cell, tmp_path):
    """Two steps of a glTF field on the trained cell's caches, baked and exported: the metallic
    channel carries the field's metallic, the GLB has no KHR_materials_specular, the USD is in the
    metallic workflow, both validate, and the bake's fidelity is as high as TANGO's."""
    d = trained_cell
    s = OptimizeSettings(
        iterations=2, clip_tiny_test=True, image_size=64, width=16, crops=1, light_lobes=8, eval_width=32, brdf="gltf"
    )
    optimize.run(d / "train.npz", d / "eval.npz", "a candle made of gold", tmp_path / "opt", s, "cpu")
    stats = bake.run(
        d / "mesh.ply",
        tmp_path / "opt" / "field.pt",
        d / "eval.npz",
        tmp_path / "bake",
        BakeSettings(texture_size=256, eval_width=48),
    )
    meta = json.loads((tmp_path / "bake" / "meta.json").read_text())
    assert meta["stats"]["brdf"] == "gltf"
    tango = json.loads((d / "bake" / "meta.json").read_text())["stats"]
    assert stats["bake_psnr_db"] > min(35.0, tango["bake_psnr_db"] - 3.0), (stats["bake_psnr_db"], tango["bake_psnr_db"])
    mr = np.asarray(Image.open(tmp_path / "bake" / "textures" / "metallic_roughness.png"))
    assert mr[..., 2].max() > 0  # a trained metallic, not TANGO's 0
    export.run(
        d / "mesh.ply",
        d / "transform.json",
        tmp_path / "bake",
        tmp_path / "bake" / "preview.png",
        tmp_path / "export",
        ExportSettings(),
    )
    em = json.loads((tmp_path / "export" / "meta.json").read_text())["stats"]
    assert em["brdf"] == "gltf" and em["usd_validation_errors"] == 0
    glb = (tmp_path / "export" / "model.glb").read_bytes()
    assert b"KHR_materials_specular" not in glb and b"metallicRoughnessTexture" in glb
    usda = (tmp_path / "export" / "model.usda").read_text()
    assert "int inputs:useSpecularWorkflow = 0" in usda and "inputs:metallic.connect" in usda
    assert "specularColor" not in usda
