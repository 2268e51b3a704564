"""Layer ``model``: positional encodings, the SVBRDF and normal networks, the SG light module, the
stylisation field and its forward pass, the field file, procedural targets, and SG fits of
environment maps. Imports ``render``, ``geometry``-free; below ``imaging``."""
