"""Where the repository's set-up puts the tools the stages call beside Python: the npm packages of
``package.json`` (``npm ci``, run by ``scripts/setup.sh`` where npm exists) under ``node_modules``.
Paths only, so a stage that needs one imports nothing heavy with it (the report stage, its viewer,
imports no torch)."""

from __future__ import annotations

from pathlib import Path

#: the repository's root (the checkout the stages run from)
REPO_ROOT = Path(__file__).resolve().parents[2]
#: the Khronos glTF-Validator as ``npm ci`` installs it (``scripts/validate_gltf.mjs`` runs it)
GLTF_VALIDATOR = REPO_ROOT / "node_modules" / "gltf-validator"
#: the report's 3D viewer (model-viewer) as ``npm ci`` installs it
MODEL_VIEWER = REPO_ROOT / "node_modules" / "@google" / "model-viewer" / "dist" / "model-viewer-umd.min.js"
