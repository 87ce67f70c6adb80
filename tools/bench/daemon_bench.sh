#!/usr/bin/env bash
# The live daemon's cost on 1080p30 in real time: `keyframed run` with the file
# source paced at the video's own rate (as a camera), MCAP recording on. Prints the
# summary's frame rate, drops, CPU (total, and without the video decoding a camera
# would do in hardware) and peak RSS.
#   tools/bench/daemon_bench.sh [SECONDS] [--full] [--format YUV420|NV12] [--allocs]
#                               [--rss] [--flight nadir|orbit] [--size WxH]
#                               [--set KEY=VALUE]... [--wrap 'COMMAND']
#   (default 12 s of the nadir survey, which ends at ~37 s; --flight orbit goes on for
#   any length; --size: other than 1920x1080; --set as `keyframed run --set`, e.g.
#   output.preview_format=h264)
# --allocs: heap allocations per frame by thread, counted from 3 s to 1 s before the
# end (tools/bench/alloc_preload.cpp, preloaded; it slows allocation a little).
# Without --full: no telemetry or Zenoh peers (the selection, recording and preview
# cost alone). With --full: the daemon as shipped, telemetry and Zenoh on, a fake
# autopilot replaying the flight's tlog over UDP and a ground station (keyframed-ground)
# receiving the keyframes over loopback; their own CPU is not counted.
# --rss: the daemon's resident memory (VmRSS) sampled five times a second: its growth
# after the first tenth of the run (at least 1 s), as a straight line fitted in MB a minute
# and the range, for a soak (a whole flight's length) rather than a peak.
# --wrap: the daemon runs under COMMAND, split at spaces: 'env MALLOC_ARENA_MAX=1', or
# 'heaptrack -o /tmp/kf' for the heap by allocation site (heaptrack_print; --rss then
# samples heaptrack's own shell, not the daemon: env execs, heaptrack does not).
# --format: the file source delivers frames as a camera would (converted from the
# decoded BGR on the capture thread, counted with the decoding), so that the
# daemon's own work is what it does behind a YUV camera; default: BGR as decoded.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
cd "$ROOT"
SECS=12
FULL=0
FORMAT=auto
ALLOCS=0
RSS=0
FLIGHT=nadir
SIZE=1920x1080
EXTRA=()
WRAP=()
while [ "$#" -gt 0 ]; do
  case "$1" in
    --full) FULL=1 ;;
    --format) FORMAT="$2"; shift ;;
    --allocs) ALLOCS=1 ;;
    --rss) RSS=1 ;;
    --flight) FLIGHT="$2"; shift ;;
    --size) SIZE="$2"; shift ;;
    --set) EXTRA+=(--set "$2"); shift ;;
    --wrap) read -r -a WRAP <<< "$2"; shift ;;
    *) SECS="$1" ;;
  esac
  shift
done
if [[ ! "$SIZE" =~ ^([0-9]+)x([0-9]+)$ ]]; then
  echo "daemon_bench.sh: --size wants WIDTHxHEIGHT, not '$SIZE'" >&2
  exit 2
fi
WIDTH="${BASH_REMATCH[1]}"
HEIGHT="${BASH_REMATCH[2]}"
SAMPLE="data/sample/${FLIGHT}${HEIGHT}-${SECS}s"
[ "$WIDTH" = $((HEIGHT * 16 / 9)) ] || SAMPLE="data/sample/${FLIGHT}${WIDTH}x${HEIGHT}-${SECS}s"
if [ ! -f "$SAMPLE/meta.json" ]; then
  .venv/bin/python -m keyframed.synth --flight "$FLIGHT" --out "$SAMPLE" --width "$WIDTH" --height "$HEIGHT" \
    --seconds "$SECS" >/dev/null
fi
STATE="$(mktemp -d)"
cleanup() { kill "${DAEMON_PID:-}" "${GROUND_PID:-}" "${AP_PID:-}" 2>/dev/null || true; rm -rf "$STATE"; }
trap cleanup EXIT
mkdir -p "$STATE/etc"
ARGS=(--set camera.source=file --set "camera.path=$ROOT/$SAMPLE/video.avi"
      --set "output.state_dir=$STATE" --set "camera.pixel_format=$FORMAT")
if [ "$FULL" = 1 ]; then
  free_port() { .venv/bin/python -c "import socket,sys; s=socket.socket(socket.AF_INET, getattr(socket, sys.argv[1])); s.bind(('127.0.0.1', 0)); print(s.getsockname()[1])" "$1"; }
  ZPORT="$(free_port SOCK_STREAM)"
  MPORT="$(free_port SOCK_DGRAM)"
  # The vehicle dials the station, as docs/deploy.md has it, once the station listens:
  # a station that came up after the short flight's first keyframe could not fetch it
  # from a daemon that has already stopped.
  echo "{ mode: \"peer\", connect: { endpoints: [\"tcp/127.0.0.1:$ZPORT\"] }, scouting: { multicast: { enabled: false } } }" \
    > "$STATE/etc/zenoh.json5"
  ARGS+=(--set "telemetry.url=udpin:127.0.0.1:$MPORT" --set "zenoh.config=$STATE/etc/zenoh.json5"
         --set zenoh.vehicle=bench --set "tagging.calibration=$ROOT/$SAMPLE/calibration.yaml")
  .venv/bin/python -m keyframed.ground --out "$STATE/dataset" --listen "tcp/127.0.0.1:$ZPORT" \
    --until-done --quiet > "$STATE/ground.json" &
  GROUND_PID=$!
  for _ in $(seq 300); do
    (exec 3<>"/dev/tcp/127.0.0.1/$ZPORT") 2>/dev/null && break
    sleep 0.1
  done
  .venv/bin/python tests/harness/fake_autopilot.py "$SAMPLE/flight.tlog" \
    --target "127.0.0.1:$MPORT" --start-delay 0.5 &
  AP_PID=$!
else
  ARGS+=(--set telemetry.url= --set zenoh.enabled=false)
fi
PRELOAD=()
if [ "$ALLOCS" = 1 ] && [ "$SECS" -lt 6 ]; then
  echo "daemon_bench.sh: --allocs counts from 3 s to 1 s before the end: fly 6 s or more" >&2
  exit 2
fi
if [ "$ALLOCS" = 1 ]; then
  PRELOAD=(env "LD_PRELOAD=$ROOT/build/release/tools/bench/libkeyframed-alloc-count.so"
           KEYFRAMED_ALLOC_FROM_S=3 "KEYFRAMED_ALLOC_TO_S=$((SECS - 1))"
           "KEYFRAMED_ALLOC_REPORT=$STATE/allocs.txt")
fi
"${PRELOAD[@]}" "${WRAP[@]}" build/release/daemon/keyframed run --config-dir "$STATE/etc" "${ARGS[@]}" "${EXTRA[@]}" \
  2>/dev/null &
DAEMON_PID=$!
if [ "$RSS" = 1 ]; then
  # the time and VmRSS in kB, until the daemon has gone
  while rss=$(awk '/^VmRSS:/ { print $2 }' "/proc/$DAEMON_PID/status" 2>/dev/null) && [ -n "$rss" ]; do
    echo "$EPOCHREALTIME $rss" >> "$STATE/rss.txt"
    sleep 0.2
  done
fi
wait "$DAEMON_PID"
DAEMON_PID=  # gone: nothing for cleanup to stop
if [ "$FULL" = 1 ]; then wait "$GROUND_PID" || true; fi
.venv/bin/python - "$STATE/latest/summary.json" "$FULL" "$STATE/ground.json" "$FORMAT" \
  "$STATE/allocs.txt" "$SECS" "$STATE/rss.txt" <<'PY'
import json, os, sys
s = json.load(open(sys.argv[1]))
full = sys.argv[2] == "1"
what = "telemetry, tagging, MCAP, Zenoh to a ground station" if full else "MCAP, no peers"
print(f"keyframed run, {s['width']}x{s['height']} file source in real time, {s['seconds']:.1f} s ({what}), frames as {'BGR (as decoded)' if sys.argv[4] == 'auto' else sys.argv[4]}")
for k in ("frames_per_second", "frames_read", "frames_dropped", "kept", "analysis_ms_mean",
          "cpu_percent", "cpu_percent_without_decode", "max_rss_mb"):
    print(f"  {k:28s} {s[k]}")
if full:
    t = s.get("telemetry") or {}
    print(f"  {'geotagged':28s} {t.get('geotagged')}")
    for line in open(sys.argv[3]):
        g = json.loads(line)
        print(f"  {'ground station received':28s} {g['keyframes']}")
if os.path.exists(sys.argv[5]):
    frames = s["frames_per_second"] * (int(sys.argv[6]) - 1 - 3)
    print(f"  heap allocations per frame, {frames:.0f} frames from 3 s to {int(sys.argv[6]) - 1} s, by thread:")
    for line in open(sys.argv[5]):
        name, count = line.rsplit(None, 1)
        print(f"    {name:26s} {int(count) / frames:8.2f}")
if os.path.exists(sys.argv[7]):
    samples = [tuple(map(float, line.split())) for line in open(sys.argv[7]) if line.strip()]
    samples = [(t - samples[0][0], kb) for t, kb in samples]
    settle = max(1.0, 0.1 * samples[-1][0]) if samples else 0.0
    late = [(t, kb / 1024) for t, kb in samples if t >= settle]
    if len(late) >= 3:
        n = len(late)
        mt = sum(t for t, _ in late) / n
        mr = sum(r for _, r in late) / n
        slope = sum((t - mt) * (r - mr) for t, r in late) / sum((t - mt) ** 2 for t, _ in late)
        rs = [r for _, r in late]
        print(f"  VmRSS from {settle:.0f} s to {late[-1][0]:.0f} s ({n} samples): {rs[0]:.1f} MB then, "
              f"{rs[-1]:.1f} MB at the end, {min(rs):.1f}-{max(rs):.1f} MB, "
              f"growth {slope * 60:+.3f} MB a minute (least squares)")
    else:
        print("  VmRSS: the run was too short to sample after it settled")
PY
