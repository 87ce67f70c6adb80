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
# The flight's tlog geotags the keyframes; the video starts at the flight's epoch.
START="$(.venv/bin/python -c 'import json, sys; print(json.load(open(sys.argv[1]))["epoch_unix_s"])' "$SAMPLE/meta.json")"
echo "==> keyframed select $SAMPLE/video.avi --telemetry $SAMPLE/flight.tlog --video-start $START --calibration $SAMPLE/calibration.yaml --out $OUT"
build/release/daemon/keyframed select "$SAMPLE/video.avi" --telemetry "$SAMPLE/flight.tlog" \
  --video-start "$START" --calibration "$SAMPLE/calibration.yaml" --out "$OUT"
echo "==> against the flight's ground truth"
.venv/bin/python -m keyframed.evaluate "$SAMPLE" "$OUT"
echo
echo "keyframes: $ROOT/$OUT/*.jpg ($(ls "$OUT"/*.jpg | wc -l) files)"
echo "index:     $ROOT/$OUT/keyframes.csv (position, attitude and geotag note of each)"
echo "summary:   $ROOT/$OUT/summary.json"
FIRST="$(ls "$OUT"/*.jpg | head -1)"
echo
echo "==> tags of $FIRST (exiftool)"
exiftool -s -GPSLatitude -GPSLongitude -GPSAltitude -DateTimeOriginal -FocalLength \
  -FocalLengthIn35mmFormat -Yaw -Pitch -Roll "$FIRST" || true
