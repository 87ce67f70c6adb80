#!/usr/bin/env bash
# The main job on the built-in sample: set up, build, generate a short synthetic
# survey flight (first run only), then fly it: the daemon (`keyframed run`) plays the
# flight's video as its camera, a fake autopilot streams the flight's MAVLink
# telemetry to it over UDP, and a ground station (keyframed-ground) receives the
# keyframes over Zenoh into a COLMAP/ODM dataset. Reports where everything went and
# how the keyframes compare with the flight's ground truth.
#   tools/demo.sh [nadir|orbit]
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
# The test suite runs this script on the tree it has just set up and built.
if [ "${KEYFRAMED_DEMO_SKIP_SETUP:-0}" != 1 ]; then
  tools/setup.sh
  tools/build.sh
fi

FLIGHT="${1:-nadir}"
SAMPLE="data/sample/$FLIGHT"
DEMO="data/demo/$FLIGHT"
# Made on first use, and again whenever the generator changes.
SYNTH_VERSION="$(sha256sum bindings/python/keyframed/synth.py | cut -c1-12)"
if [ ! -f "$SAMPLE/meta.json" ] || [ "$(cat "$SAMPLE/.synth-version" 2>/dev/null)" != "$SYNTH_VERSION" ]; then
  echo "==> generating the sample flight '$FLIGHT' into $SAMPLE"
  rm -rf "$SAMPLE"
  .venv/bin/python -m keyframed.synth --flight "$FLIGHT" --out "$SAMPLE"
  echo "$SYNTH_VERSION" > "$SAMPLE/.synth-version"
fi
rm -rf "$DEMO"
mkdir -p "$DEMO/etc/conf.d"
free_port() { .venv/bin/python -c "import socket,sys; s=socket.socket(socket.AF_INET, getattr(socket, sys.argv[1])); s.bind(('127.0.0.1', 0)); print(s.getsockname()[1])" "$1"; }
ZPORT="$(free_port SOCK_STREAM)"
MPORT="$(free_port SOCK_DGRAM)"
cat > "$DEMO/etc/zenoh.json5" <<EOF
{ mode: "peer", listen: { endpoints: ["tcp/127.0.0.1:$ZPORT"] }, scouting: { multicast: { enabled: false } } }
EOF
# The daemon's configuration: config/keyframed.toml's defaults, with this sample
# as the camera (docs/configuration.md explains every key).
cat > "$DEMO/etc/keyframed.toml" <<EOF
[camera]
source = "file"
path = "$ROOT/$SAMPLE/video.avi"
realtime = true

[telemetry]
url = "udpout:127.0.0.1:$MPORT"
start_wait_ms = 0

[tagging]
calibration = "$ROOT/$SAMPLE/calibration.yaml"

[output]
state_dir = "$ROOT/$DEMO/state"

[zenoh]
config = "$ROOT/$DEMO/etc/zenoh.json5"
vehicle = "demo-$FLIGHT"
EOF

cleanup() { kill "${GROUND_PID:-}" "${AP_PID:-}" 2>/dev/null || true; }
trap cleanup EXIT
echo "==> ground station: keyframed-ground --out $DEMO/dataset"
.venv/bin/keyframed-ground --out "$DEMO/dataset" --connect "tcp/127.0.0.1:$ZPORT" \
  --until-done --quiet > "$DEMO/ground.json" &
GROUND_PID=$!
# The video stands in for a camera that films as the vehicle flies: the daemon starts
# its camera as its MAVLink link opens (start_wait_ms = 0), and the autopilot's replay
# starts when it first hears the daemon, at the tlog's moment of the video's first
# frame, with the second before it as history, so that each frame is where the tlog
# says the vehicle was.
EPOCH="$(.venv/bin/python -c 'import json, sys; print(json.load(open(sys.argv[1]))["epoch_unix_s"])' "$SAMPLE/meta.json")"
echo "==> fake autopilot: replaying $SAMPLE/flight.tlog on udp 127.0.0.1:$MPORT"
rm -f "$DEMO/autopilot.ready"
.venv/bin/python tests/harness/fake_autopilot.py "$SAMPLE/flight.tlog" \
  --listen "$MPORT" --from-unix "$EPOCH" --ready-file "$DEMO/autopilot.ready" &
AP_PID=$!
for _ in $(seq 300); do [ -e "$DEMO/autopilot.ready" ] && break; sleep 0.1; done
SECS="$(.venv/bin/python -c 'import json, sys; print(round(json.load(open(sys.argv[1]))["seconds"]))' "$SAMPLE/meta.json")"
echo "==> keyframed run --config-dir $DEMO/etc   (the daemon; the flight takes ${SECS} s in real time)"
build/release/daemon/keyframed run --config-dir "$DEMO/etc"
wait "$AP_PID" || true
wait "$GROUND_PID" || true
trap - EXIT

OUT="$DEMO/state/latest"
echo
echo "==> against the flight's ground truth"
.venv/bin/python -m keyframed.evaluate "$SAMPLE" "$OUT"
.venv/bin/python - "$OUT" "$DEMO/ground.json" <<'EOF'
import json, sys
s = json.load(open(f"{sys.argv[1]}/summary.json"))
t = s["telemetry"] or {}
print(f"{s['frames_read']} frames at {s['frames_per_second']:.1f} fps, {s['frames_dropped']} dropped; "
      f"{s['rejected_blur']} rejected as blurred, {s['rejected_overlap']} as redundant; "
      f"{s['written']} keyframes, {t.get('geotagged', 0)} geotagged (clock: {t.get('clock')}); "
      f"CPU {s['cpu_percent']:.0f} % of one core, peak RSS {s['max_rss_mb']:.0f} MB")
for line in open(sys.argv[2]):
    g = json.loads(line)
    print(f"ground station: {g['keyframes']} keyframes of vehicle {g['vehicle']}, "
          f"{g['fetched_by_query']} fetched by query, {g['pairs']} image pairs")
EOF
FD="$(cd "$OUT" && pwd -P)"
echo
echo "keyframes:      $FD/keyframes/*.jpg (geotagged; index in keyframes.csv)"
echo "decisions:      $FD/decisions.csv"
echo "flight record:  $FD/flight.mcap (open in Foxglove)"
echo "summary:        $FD/summary.json"
echo "COLMAP/ODM:     $ROOT/$DEMO/dataset/demo-$FLIGHT/ (images/, cameras.txt, pairs.txt, geo.txt, cameras.json)"
