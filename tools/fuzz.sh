#!/usr/bin/env bash
# Coverage-guided fuzzing (clang's libFuzzer + AddressSanitizer, UBSan) of everything
# that reads bytes from the autopilot's side. One target, tests/fuzz/fuzz_mavlink.cpp,
# feeds each input, cut into pieces of 1-64 bytes as a link delivers them, to:
#   - the MAVLink 1/2 parser and the telemetry decoder behind it (every byte counted
#     once; pose queries safe on whatever history results);
#   - TelemetryService, the camera component, on a link that plays the input and now
#     and then refuses a write: COMMAND_LONG (REQUEST_MESSAGE for CAMERA_INFORMATION,
#     CAMERA_IMAGE_CAPTURED re-requests by index and range), TIMESYNC requests and
#     answers, queued capture reports; each write must be one well-formed frame
#     (MAVLink 1 or 2), and every capture is sent, pending or counted dropped;
#   - the tlog reader (the input as a file): records inside the file, packets that
#     start with a MAVLink start byte.
# The seed corpus is generated (well-formed frames of every message the decoder reads,
# the camera commands, a byte stream and a tlog); crashes land in build/fuzz/artifacts/.
# The same target also runs without libFuzzer in every test build, on the seeds and
# deterministic mutations of them (fuzz_mavlink_standalone, a ctest).
#   tools/fuzz.sh [SECONDS]   (default 60; wall time, in KEYFRAMED_JOBS processes,
#                              libFuzzer's fork mode, 2 by default)
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
SECONDS_TO_RUN="${1:-60}"
JOBS="${KEYFRAMED_JOBS:-2}"
CXX_FUZZ="$(command -v clang++-14 || command -v clang++ || true)"
CC_FUZZ="$(command -v clang-14 || command -v clang || true)"
if [ -z "$CXX_FUZZ" ] || [ -z "$CC_FUZZ" ]; then
  echo "fuzz: clang not found (tools/setup.sh installs clang-14)" >&2
  exit 1
fi
if [ ! -f build/fuzz/build.ninja ]; then
  cmake -S . -B build/fuzz -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo \
    -DCMAKE_C_COMPILER="$CC_FUZZ" -DCMAKE_CXX_COMPILER="$CXX_FUZZ" -DKEYFRAMED_FUZZ=ON \
    -DKEYFRAMED_BUILD_DAEMON=OFF -DKEYFRAMED_BUILD_TESTS=OFF -DKEYFRAMED_BUILD_BENCHMARKS=OFF \
    -DKEYFRAMED_WITH_IO=OFF -DKEYFRAMED_WITH_LIBCAMERA=OFF \
    -DKEYFRAMED_PYTHON="$ROOT/.venv/bin/python" >/dev/null
fi
ninja -C build/fuzz -j"$JOBS" fuzz_mavlink fuzz_mavlink_standalone
mkdir -p build/fuzz/corpus build/fuzz/artifacts
build/fuzz/tests/fuzz/fuzz_mavlink_standalone --write-seeds build/fuzz/seeds
ASAN_OPTIONS=detect_leaks=1 UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1 \
  build/fuzz/tests/fuzz/fuzz_mavlink -fork="$JOBS" -max_total_time="$SECONDS_TO_RUN" -max_len=4096 \
  -print_final_stats=1 -artifact_prefix=build/fuzz/artifacts/ \
  build/fuzz/corpus build/fuzz/seeds
