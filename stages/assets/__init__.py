"""Layer ``assets``: texture baking of a trained field (xatlas charts, atlas rasterisation,
tangent frames, fidelity renders of the baked textures) and the export formats (``formats/``:
one module per format, glTF and USD, each writer with its validator, found by name). Above
``imaging``; beside ``training``."""
