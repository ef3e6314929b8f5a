#!/usr/bin/env bash
# A throwaway venv with the official nuscenes-devkit, lyft_dataset_sdk and truckscenes-devkit (NOT project
# dependencies; truckscenes-devkit reads its .pcd files with pypcd4, which needs pydantic), the independent
# truths of the tests that check our reading and projection against them. Prints the venv's python path.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv-devkit/bin/python ] || ! .venv-devkit/bin/python -c "import nuscenes, lyft_dataset_sdk, truckscenes" >/dev/null 2>&1; then
    log=$(mktemp)
    # The devkit pins numpy<2 and a few extras it never imports for loading and projection; its
    # NuScenes class and map_pointcloud_to_image work with these.
    if ! { "$PY" -m venv .venv-devkit \
           && .venv-devkit/bin/pip install -q --no-deps nuscenes-devkit lyft_dataset_sdk \
           && .venv-devkit/bin/pip install -q --no-deps truckscenes-devkit pypcd4 python-neo-lzf \
           && .venv-devkit/bin/pip install -q numpy pyquaternion pillow matplotlib opencv-python-headless tqdm \
                scipy shapely scikit-learn cachetools descartes pydantic; } >"$log" 2>&1; then
        cat "$log" >&2
        echo "devkit venv set-up failed" >&2
        exit 1
    fi
    rm -f "$log"
fi
echo "$PWD/.venv-devkit/bin/python"
