"""Layer ``config``: every stage's settings (:mod:`.sections`, the one home of defaults), the
presets, the file layout the rules declare, and the workflow config (validation against the
schema, per-mesh and per-cell resolution). Imports only :mod:`stages.core`; no torch, no numpy.

``python -m stages.config --configfile C --cell mesh/prompt/variant`` explains a cell's settings.
"""
