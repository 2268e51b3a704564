"""Layer ``model``: positional encodings, the SVBRDF and normal networks, the light's components
(``lights``: one module per kind, the SG lobes and their SG fits of environment maps), the
stylisation field and its forward pass, the field file and procedural targets. Imports
``render``, ``geometry``-free; below ``imaging``."""
