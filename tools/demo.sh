#!/usr/bin/env bash
# The main job on the built-in sample: set up, build, generate a short synthetic
# survey flight (first run only), pick its keyframes and report where they went
# and how they compare with the flight's ground truth.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
tools/setup.sh
tools/build.sh

FLIGHT="${1:-nadir}"
SAMPLE="data/sample/$FLIGHT"
OUT="data/keyframes/$FLIGHT"
if [ ! -f "$SAMPLE/meta.json" ]; then
  echo "==> generating the sample flight '$FLIGHT' into $SAMPLE (first run only)"
  .venv/bin/python -m keyframed.synth --flight "$FLIGHT" --out "$SAMPLE"
fi
rm -rf "$OUT"
echo "==> keyframed select $SAMPLE/video.avi --out $OUT"
build/release/daemon/keyframed select "$SAMPLE/video.avi" --out "$OUT"
echo "==> against the flight's ground truth"
.venv/bin/python -m keyframed.evaluate "$SAMPLE" "$OUT"
echo
echo "keyframes: $ROOT/$OUT/*.jpg ($(ls "$OUT"/*.jpg | wc -l) files)"
echo "summary:   $ROOT/$OUT/summary.json"
