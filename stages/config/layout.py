"""File names the stages write and the rules declare: the contract between the two, importable
without torch (the workflow builds its outputs from it)."""

from __future__ import annotations

#: the images the optimize stage renders from every evaluation view (``renders/<kind>.png``)
RENDER_KINDS = ("rgb", "diffuse", "specular", "roughness", "normal", "normal_original")

#: the optimize stage's outputs (besides ``meta.json``), relative to its folder
OPTIMIZE_FILES = {
    "field": "field.pt",
    "loss_csv": "loss.csv",
    "loss_png": "loss.png",
    "light": "light.npz",
    **{f"render_{k}": f"renders/{k}.png" for k in (*RENDER_KINDS, "light")},
}

#: the baked texture maps (``textures/<name>.png`` in the bake and export folders)
TEXTURES = ("basecolor", "metallic_roughness", "specular", "normal")
TEXTURE_FILES = {k: f"textures/{k}.png" for k in TEXTURES}

#: the lod stage's outputs (the combined asset, the figure and the metadata), relative to its folder
LOD_FILES = {
    "usda": "model_lods.usda",
    "usdz": "model_lods.usdz",
    "glb": "model_lods.glb",
    "figure": "levels.png",
    "meta": "meta.json",
}
