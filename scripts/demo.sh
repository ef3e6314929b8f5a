#!/usr/bin/env bash
# Set up, then run the main job on the embedded default: a small synthetic nuScenes-format world.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export PATH="$PWD/.venv/bin:$PATH"
OUT=${DEMO_DIR:-demo}
rm -rf "$OUT" && mkdir -p "$OUT"
occdata synth --out "$OUT/world" --scenes 2 --samples 6 --seed 0 --width 800 --height 450
occdata scan --root "$OUT/world"
occdata build --root "$OUT/world" --gts "$OUT/world/gts" --out "$OUT/data.zarr" --workers 2
occdata verify --store "$OUT/data.zarr"
occdata info --store "$OUT/data.zarr"
occdata visibility --store "$OUT/data.zarr" --recompute
occdata check-projection --store "$OUT/data.zarr" --index 0 --out "$OUT/check_projection.png"
fastocc show-batch --store "$OUT/data.zarr" --index 3 --train --out "$OUT/batch.png"
fastocc bench --preset nano --head all --repeats 2
# A few minutes of CPU training (nano, 64x176, 3 epochs of the 6 training samples), then score and draw it.
fastocc train --store "$OUT/data.zarr" --config scripts/demo_train.toml --out "$OUT/run"
fastocc eval --checkpoint "$OUT/run/last.pt" --store "$OUT/data.zarr" --split val
fastocc predict --checkpoint "$OUT/run/last.pt" --store "$OUT/data.zarr" --split val --out "$OUT/pred" --png 2
echo "demo done: store $OUT/data.zarr; run $OUT/run; pictures $OUT/check_projection.png, $OUT/batch.png, $OUT/pred/pictures"
