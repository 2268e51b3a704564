"""Layer ``assets``: texture baking of a trained field (xatlas charts, atlas rasterisation,
tangent frames, fidelity renders of the baked textures) and the asset file formats (USD, glTF)
with their validators. Above ``imaging``; beside ``training``."""
