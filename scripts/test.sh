#!/usr/bin/env bash
# Set up (if needed) and run the default test suite. Extra arguments go to pytest (e.g. -m slow).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
# The official nuscenes-devkit in a throwaway venv (not a project dependency), so the test that
# `occdata synth` output loads in the devkit runs for real.
if [ -z "${OCCDATA_DEVKIT_PYTHON:-}" ]; then
    OCCDATA_DEVKIT_PYTHON=$(bash scripts/devkit_env.sh)
    export OCCDATA_DEVKIT_PYTHON
fi
# One pytest worker per CPU (pytest-xdist); a file's tests stay on one worker (--dist loadfile), so each
# module fixture (a built tree, a Dask cluster) is made once. OCCDATA_TEST_WORKERS=0 runs in one process.
exec .venv/bin/python -m pytest -n "${OCCDATA_TEST_WORKERS:-$(nproc)}" --dist loadfile "$@"
