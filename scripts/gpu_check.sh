#!/usr/bin/env bash
# The GPU path in a few minutes (benchmarks/gpu_check.py): latency eager/compiled x fp32/fp16/bf16, ONNX Runtime
# CUDA/TensorRT, 50 AMP training steps, a one-process NCCL step, loader rate against step rate.
#   bash scripts/gpu_check.sh --json gpu_check.json     # on a CUDA machine
#   bash scripts/gpu_check.sh --dry-run                 # anywhere: the same sections on tiny CPU shapes
set -euo pipefail
cd "$(dirname "$0")/.."
PY=python
if [ -x .venv/bin/python ]; then PY=.venv/bin/python; fi
exec "$PY" -m benchmarks.gpu_check "$@"
