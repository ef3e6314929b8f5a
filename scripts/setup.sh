#!/usr/bin/env bash
# Create .venv and install the project with its dependencies. Idempotent.
# Without an NVIDIA GPU it installs the CPU build of torch 2.13.0 (an unpinned torch would pull
# several GB of CUDA packages).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
    "$PY" -m venv .venv
fi
VPY=.venv/bin/python
"$VPY" -m pip install -q --upgrade pip >/dev/null 2>&1 || true
if ! "$VPY" -c "import torch" >/dev/null 2>&1; then
    if command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi >/dev/null 2>&1; then
        "$VPY" -m pip install -q "torch==2.13.0"
    else
        # A local CPU wheel is preferred; the CPU index is the fallback elsewhere.
        "$VPY" -m pip install -q "torch==2.13.0" 2>/dev/null \
            || "$VPY" -m pip install -q "torch==2.13.0" --index-url https://download.pytorch.org/whl/cpu
    fi
fi
"$VPY" -m pip install -q -e ".[dev]"
echo "set-up done: $("$VPY" -c 'import torch, numba, zarr; print("torch", torch.__version__, "| numba", numba.__version__, "| zarr", zarr.__version__)')"
