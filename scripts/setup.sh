#!/usr/bin/env bash
# Create (or refresh) the project's virtual environment in .venv.
#
# - Keeps a torch that is already installed in .venv (GPU users install their CUDA build first,
#   see README); otherwise installs torch==2.13.0: without an NVIDIA driver from PyTorch's CPU
#   wheel index, with one from the default index (scripts/torch_index.py decides and says which;
#   TANGO_TORCH_INDEX names another index, or "default"; an index that cannot be reached falls back
#   to the default one with a warning), and then pins whatever torch is present for every later
#   install so no dependency can swap it for a multi-GB CUDA build.
# - Points Snakemake's cache at .cache/ inside the project (in .venv/bin/activate).
# - Idempotent and quick when nothing changed (a stamp file records the last successful set-up).
set -euo pipefail
cd "$(dirname "$0")/.."
root=$(pwd)
py=${PYTHON:-python3}
extras=${1:-test,reference,blender}
# Blender as a module (bpy) pins numpy < 2, so it lives in its own environment, .venv-blender,
# which the Blender judge (stages/reference/blender.py) runs as a separate process
bpy_version=${BPY_VERSION:-5.0.1}
pip_extras=$(echo "$extras" | tr ',' '\n' | grep -v '^blender$' | paste -sd, -)

if [ ! -x .venv/bin/python ]; then
    "$py" -m venv .venv
fi
stamp=.venv/.setup-stamp-$extras
# (up to date unless a file it installs from changed, or npm appeared since node_modules was skipped)
if [ -f "$stamp" ] && [ "$stamp" -nt pyproject.toml ] && [ "$stamp" -nt scripts/setup.sh ] \
    && [ "$stamp" -nt package-lock.json ] && { [ -d node_modules ] || ! command -v npm >/dev/null 2>&1; }; then
    echo "setup: .venv is up to date ($stamp)"
    exit 0
fi

export PIP_DISABLE_PIP_VERSION_CHECK=1
if ! .venv/bin/python -c "import torch" >/dev/null 2>&1; then
    index_args=$("$py" scripts/torch_index.py)
    echo "setup: installing torch==${TORCH_VERSION:-2.13.0}"
    # shellcheck disable=SC2086 # the index arguments are words
    .venv/bin/pip install --quiet "torch==${TORCH_VERSION:-2.13.0}" $index_args
fi
torch_version=$(.venv/bin/python -c "import torch; print(torch.__version__.split('+')[0])" 2>/dev/null)
echo "torch==$torch_version" > .venv/constraints.txt
echo "setup: installing the project (extras: $extras) with torch pinned to $torch_version"
PIP_CONSTRAINT="$root/.venv/constraints.txt" .venv/bin/pip install --quiet -e ".[$pip_extras]"

if [[ ",$extras," == *",blender,"* ]]; then
    bpy_python=${BLENDER_PYTHON:-$(command -v python3.11 || command -v "$py" || true)}
    if [ -z "$bpy_python" ] || ! "$bpy_python" -c "import sys; sys.exit(sys.version_info[:2] != (3, 11))" 2>/dev/null; then
        echo "setup: bpy $bpy_version needs Python 3.11 ($bpy_python not found): the Blender round trip and its"
        echo "       tests are unavailable (install python3.11, or set TANGO_BLENDER to a blender executable)"
    else
        [ -x .venv-blender/bin/python ] || "$bpy_python" -m venv .venv-blender
        if ! .venv-blender/bin/python -c "import bpy, sys; sys.exit(bpy.app.version_string != '$bpy_version')" >/dev/null 2>&1; then
            echo "setup: installing Blender as a module (bpy==$bpy_version, about 370 MB) into .venv-blender"
            .venv-blender/bin/pip install --quiet "bpy==$bpy_version"
        fi
    fi
fi

# Snakemake (and other tools honouring XDG) cache inside the project, not in $HOME.
if ! grep -q "tango-stylize cache" .venv/bin/activate; then
    cat >> .venv/bin/activate <<ACT
# tango-stylize cache: keep Snakemake's source cache inside the project
export XDG_CACHE_HOME="$root/.cache"
ACT
fi
# Node.js tools (model-viewer for the report's 3D viewers; the Khronos glTF-Validator, run by the
# export and the tests; playwright-core for the browser test), when npm is available
if command -v npm >/dev/null 2>&1; then
    echo "setup: installing Node.js test tools (npm ci)"
    npm ci --no-audit --no-fund --silent
else
    echo "setup: npm not found: the HTML report will show static previews instead of 3D viewers, and the"
    echo "       glTF-validator and browser tests will skip (install Node.js and npm, then rerun this script)"
fi
touch "$stamp"
echo "setup: done; activate with 'source .venv/bin/activate'"
