#!/usr/bin/env bash
# The GPU checks in one command, for a machine with a CUDA device and the project's Python
# dependencies: the paper step's levers side by side (python -m benchmarks.training.gpu: a short main run, its
# profile, then each lever at 100 iterations) and the GPU tests (pytest -m gpu tests/gpu, the
# end-to-end workflows left out: they need Mitsuba and Blender), each under its own time limit so
# that one slow part cannot cost the other's figures. Logs and a summary go to OUT.
#
#   bash benchmarks/gpu_checks.sh [OUT] [LEVERS]
#
# OUT defaults to gpu-checks/; LEVERS (benchmarks.training.gpu's names, comma-separated) to the baseline, then
# the levers not yet timed to the end on a GPU, then those that were (the compiled renderer, TF32):
# "float32,one graph,cuda graphs,compiled renderer,tf32" (on an H200 the CUDA graphs lever's compilation
# and 100 steps outlasted 250 s, so it comes after the one graph).
# GPU_LEVERS_S (330) and GPU_TESTS_S (250) are the two parts' limits in seconds (together within a
# 10-minute command); the levers run in order, so a limit cuts the last ones off.
set -uo pipefail
cd "$(dirname "$0")/.."
out=${1:-gpu-checks}
levers=${2:-float32,one graph,cuda graphs,compiled renderer,tf32}
mkdir -p "$out"
python -c "import torch" 2>/dev/null || {
    echo "gpu_checks: python cannot import torch: run it in the project's environment (source .venv/bin/activate)" >&2
    exit 2
}
python -c "import sys, torch; sys.exit(0 if torch.cuda.is_available() else 1)" || {
    echo "gpu_checks: torch sees no CUDA device; on a CPU use python -m benchmarks.training.optimize" >&2
    exit 2
}
{
    date -u +%Y-%m-%dT%H:%M:%SZ
    git rev-parse --short HEAD 2>/dev/null || echo "(not a git checkout)"
    python -c "import torch; print(torch.__version__, torch.cuda.get_device_name(), 'CUDA', torch.version.cuda)"
    nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>/dev/null || true
} >"$out/device.txt"
cat "$out/device.txt"

echo "== levers (limit ${GPU_LEVERS_S:-330} s): $levers"
timeout "${GPU_LEVERS_S:-330}" python -m benchmarks.training.gpu --iterations 200 --warmup 5 --profile-steps 10 \
    --levers "$levers" --lever-iterations 100 >"$out/levers.log" 2>&1
echo "levers exit $?" >>"$out/levers.log"
grep -E "^(# |iterations=|lever|float32|tf32|bf16|compiled|one graph|cuda graphs|levers exit)" "$out/levers.log"

echo "== GPU tests (limit ${GPU_TESTS_S:-250} s)"
timeout "${GPU_TESTS_S:-250}" python -m pytest -o addopts="" -q -m gpu tests/gpu -k "not workflow" \
    -p no:cacheprovider --durations=10 >"$out/tests.log" 2>&1
echo "tests exit $?" >>"$out/tests.log"
tail -25 "$out/tests.log"
