#!/usr/bin/env bash
# The live daemon's cost on 1080p30 in real time: `keyframed run` with the file
# source paced at the video's own rate (as a camera), MCAP recording on, no
# telemetry or Zenoh peers. Prints the summary's frame rate, drops, CPU (total, and
# without the video decoding a camera would do in hardware) and peak RSS.
#   tools/bench/daemon_bench.sh [SECONDS]   (default 12)
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
cd "$ROOT"
SECS="${1:-12}"
SAMPLE="data/sample/nadir1080-${SECS}s"
if [ ! -f "$SAMPLE/meta.json" ]; then
  .venv/bin/python -m keyframed.synth --flight nadir --out "$SAMPLE" --width 1920 --height 1080 \
    --seconds "$SECS" >/dev/null
fi
STATE="$(mktemp -d)"
trap 'rm -rf "$STATE"' EXIT
mkdir -p "$STATE/etc"
build/release/daemon/keyframed run --config-dir "$STATE/etc" --set camera.source=file \
  --set "camera.path=$ROOT/$SAMPLE/video.avi" --set "output.state_dir=$STATE" \
  --set telemetry.url= --set zenoh.enabled=false 2>/dev/null
.venv/bin/python - "$STATE/latest/summary.json" <<'PY'
import json, sys
s = json.load(open(sys.argv[1]))
print(f"keyframed run, {s['width']}x{s['height']} file source in real time, {s['seconds']:.1f} s")
for k in ("frames_per_second", "frames_read", "frames_dropped", "kept", "analysis_ms_mean",
          "cpu_percent", "cpu_percent_without_decode", "max_rss_mb"):
    print(f"  {k:28s} {s[k]}")
PY
