#!/usr/bin/env bash
# The whole test suite on a fresh Debian 12 machine (as root): set-up, builds,
# C++ unit tests (release and AddressSanitizer+UBSan), style checks, Python and
# end-to-end tests. Exit status is non-zero when anything fails.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
JOBS="${KEYFRAMED_JOBS:-2}"
START=$SECONDS
# Each step prints the minutes and seconds since the suite started.
step() { printf '\n==> [%dm%02ds] %s\n' $(((SECONDS - START) / 60)) $(((SECONDS - START) % 60)) "$*"; }

step "set-up (apt packages, Rust crates; the crate's build starts; Python venv)"
tools/setup.sh --system
# The Rust crate's cold build is the release build's critical path (minutes, with long
# stretches where cargo compiles one crate): it starts now, beside the rest of set-up
# and then the C++ build, whose cargo step (the same command, tools/cargo_build.sh)
# waits for it and finds the crate built. Its failure shows there again.
mkdir -p build
CARGO="$(PATH="$HOME/.cargo/bin:/root/.cargo/bin:$PATH" command -v cargo)"
tools/cargo_build.sh "$CARGO" "$ROOT/build/release/io-rs" > build/cargo-early.log 2>&1 &
CARGO_PID=$!
# A failed step ends the suite, and the background builds with it (ninja stops its
# compilers when it is terminated; cargo its rustc's).
BACKGROUND=("$CARGO_PID")
trap 'kill "${BACKGROUND[@]}" 2>/dev/null || true' EXIT
tools/setup.sh
# Tools the tests need and setup.sh installs: without one, its tests would only skip,
# so a missing one fails the suite here.
for tool in exiftool systemd-analyze strace openssl; do
  command -v "$tool" > /dev/null || { echo "missing $tool (tools/setup.sh installs it)" >&2; exit 1; }
done

# The sanitizer build's objects compile beside the release build, at the lowest
# priority: the release build's critical path is cargo's cold build of the Rust crate
# (minutes, one or two crates at a time at its end), and these fill the idle core
# without slowing it. Objects only: the links need the Rust crate, which the release
# build makes (the trees share its cargo target dir).
asan_configure() {
  if [ ! -f build/asan/build.ninja ]; then
    # A unity build (eight sources compiled as one): a quarter less CPU than one
    # compile per file, which the release tree still does (each file compiles alone).
    cmake -S . -B build/asan -G Ninja -DCMAKE_BUILD_TYPE=Debug -DKEYFRAMED_SANITIZE=ON \
      -DKEYFRAMED_BUILD_BENCHMARKS=OFF -DKEYFRAMED_WERROR=ON -DCMAKE_UNITY_BUILD=ON \
      -DKEYFRAMED_CARGO_TARGET_DIR="$ROOT/build/release/io-rs"
  fi
}
ASAN_TARGETS=(tests/keyframed_unit daemon/keyframed tests/fuzz/fuzz_mavlink_standalone)
(
  asan_configure
  listing="$(ninja -C build/asan -t inputs "${ASAN_TARGETS[@]}")"
  mapfile -t objects < <(grep -E '\.(o|gch)$' <<< "$listing")
  # None listed would make ninja build everything, cargo included: an error instead.
  [ "${#objects[@]}" -gt 0 ] || { echo "no objects listed for the sanitizer build" >&2; exit 1; }
  exec nice -n 19 ninja -C build/asan -j"$JOBS" "${objects[@]}"
) > build/asan-objects.log 2>&1 &
ASAN_OBJECTS_PID=$!
BACKGROUND+=("$ASAN_OBJECTS_PID")

step "build (release, warnings as errors) and Python package; sanitizer objects beside it"
tools/build.sh

# The sample flights the Python tests use, made now at the lowest priority in the CPU
# the C++ tests leave idle (about 2.5 minutes of CPU) rather than by the first tests
# that need them while the others wait (tests/harness/flights.py).
nice -n 19 .venv/bin/python tests/harness/flights.py > build/flights.log 2>&1 &
FLIGHTS_PID=$!
BACKGROUND+=("$FLIGHTS_PID")

step "C++ unit tests (release)"
rm -f build/release/tests/skipped-tests/*.txt
ctest --test-dir build/release --output-on-failure --no-tests=error -j"$JOBS"
# Tests that skipped, in suites that passed as well as in skipped ones
# (cmake/run_gtest_suite.sh): named, with the reason, not counted as passed.
if compgen -G 'build/release/tests/skipped-tests/*.txt' > /dev/null; then
  echo "unit tests skipped (test: reason):"
  sed 's/^/  /' build/release/tests/skipped-tests/*.txt
fi
# On amd64 (CI, and where setup.sh installs every tool) only the camera hardware test
# may skip: any other skip (exiftool, /dev/full, a pseudo-terminal, the sample photos)
# means a missing set-up step. KEYFRAMED_ALLOW_SKIPS=1 allows them anywhere.
strict_skips() {
  [ "$(dpkg --print-architecture)" = amd64 ] && [ "${KEYFRAMED_ALLOW_SKIPS:-0}" != 1 ]
}
unexpected_skips() {  # FILE...: "Suite.Test: reason" lines
  local bad
  bad="$(cat "$@" 2> /dev/null | grep -v '^LibcameraHardware\.' || true)"
  if [ -n "$bad" ] && strict_skips; then
    printf 'skipped on amd64: %s\n' "$bad" >&2
    echo "C++ unit tests skipped where all should run (KEYFRAMED_ALLOW_SKIPS=1 allows it)" >&2
    return 0
  fi
  return 1
}
if unexpected_skips build/release/tests/skipped-tests/*.txt; then exit 1; fi

step "C++ unit tests (AddressSanitizer + UBSan)"
if ! wait "$ASAN_OBJECTS_PID"; then
  cat build/asan-objects.log
  echo "the sanitizer build's objects failed to compile (above)" >&2
  exit 1
fi
ninja -C build/asan -j"$JOBS" "${ASAN_TARGETS[@]}"
export ASAN_OPTIONS=detect_leaks=1:abort_on_error=1 UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1
# A gtest binary with no tests passes; this one must have them.
asan_tests=$(build/asan/tests/keyframed_unit --gtest_list_tests | grep -c '^  ' || true)
if [ "$asan_tests" -eq 0 ]; then
  echo "the AddressSanitizer build has no unit tests: treating as failure" >&2
  exit 1
fi
echo "$asan_tests unit tests under AddressSanitizer + UBSan"
# In two shards a core (each test runs in one of them): many tests wait on threads,
# sockets and timers, and two shards left a core idle half the time. Beside them, the
# parser's deterministic mutations under the sanitizers (the release build's ctest
# runs 200,000 without them; libFuzzer, next, runs coverage-guided under them).
# 56 s -> 35 s on 2 idle cores.
SHARDS=$((2 * JOBS))
shard_pids=()
rm -f build/asan/unit-shard-*.json
for ((i = 0; i < SHARDS; i++)); do
  GTEST_TOTAL_SHARDS="$SHARDS" GTEST_SHARD_INDEX="$i" build/asan/tests/keyframed_unit \
    --gtest_brief=1 --gtest_output="json:build/asan/unit-shard-$i.json" \
    > "build/asan/unit-shard-$i.log" 2>&1 &
  shard_pids+=($!)
done
build/asan/tests/fuzz/fuzz_mavlink_standalone --iterations 25000 > build/asan/fuzz.log 2>&1 &
fuzz_pid=$!
asan_rc=0
for ((i = 0; i < SHARDS; i++)); do
  wait "${shard_pids[$i]}" || asan_rc=1
  cat "build/asan/unit-shard-$i.log"
done
fuzz_rc=0
wait "$fuzz_pid" || fuzz_rc=1
cat build/asan/fuzz.log
[ "$asan_rc" -eq 0 ] || { echo "unit tests failed under AddressSanitizer + UBSan" >&2; exit 1; }
# (--gtest_brief prints no skips: the shards' JSON reports name them.)
.venv/bin/python - build/asan/unit-shard-*.json > build/asan/skipped.txt <<'PY'
import json
import sys

for path in sys.argv[1:]:
    for suite in json.load(open(path))["testsuites"]:
        for test in suite["testsuite"]:
            if test.get("result") == "SKIPPED":
                print(f"{suite['name']}.{test['name']}: (under the sanitizers)")
PY
if unexpected_skips build/asan/skipped.txt; then exit 1; fi
[ "$fuzz_rc" -eq 0 ] || { echo "fuzz_mavlink_standalone failed under the sanitizers" >&2; exit 1; }
unset ASAN_OPTIONS UBSAN_OPTIONS

step "fuzz the MAVLink parser (libFuzzer, 15 s in $JOBS processes)"
tools/fuzz.sh 15

step "style and types (clang-format, ruff, mypy)"
git ls-files -co --exclude-standard -- '*.cpp' '*.h' '*.inc' | xargs clang-format --dry-run --Werror
.venv/bin/ruff check .
.venv/bin/ruff format --check .
# The package and the test harness, as [tool.mypy] in pyproject.toml lists them.
.venv/bin/mypy

if ! wait "$FLIGHTS_PID"; then
  cat build/flights.log
  echo "making the sample flights failed (above)" >&2
  exit 1
fi

# One process (pytest-xdist) more than cores, one test file each at a time: most tests
# replay a flight in real time and leave CPU idle (with 2 cores: 6.9 min instead of
# 9.2). KEYFRAMED_TEST_WORKERS=0 runs them in one.
WORKERS="${KEYFRAMED_TEST_WORKERS:-$((JOBS + 1))}"
XDIST=()
if [ "$WORKERS" -gt 0 ]; then XDIST=(-n "$WORKERS" --dist loadfile); fi
step "Python and end-to-end tests (pytest, ${WORKERS} workers)"
set +e
KEYFRAMED_BIN="$ROOT/build/release/daemon/keyframed" \
KEYFRAMED_ASAN_BIN="$ROOT/build/asan/daemon/keyframed" \
  .venv/bin/python -m pytest -q -rs "${XDIST[@]}" --junitxml=build/pytest.xml "$@"
rc=$?
set -e
if [ "$rc" -eq 5 ]; then
  echo "pytest collected no tests: treating as failure (the suite must have tests)" >&2
  exit 1
fi
# On amd64 (CI, and where setup.sh installs qemu and every tool) nothing may skip: a
# skip there means a missing set-up step, not missing hardware. Elsewhere (a Pi: no
# qemu guest) skips are expected; KEYFRAMED_ALLOW_SKIPS=1 allows them anywhere.
if [ "$rc" -eq 0 ] && [ "$(dpkg --print-architecture)" = amd64 ] &&
  [ "${KEYFRAMED_ALLOW_SKIPS:-0}" != 1 ] && [ "$#" -eq 0 ]; then
  .venv/bin/python - build/pytest.xml <<'PY' || rc=1
import sys
import xml.etree.ElementTree as ET

skipped = [
    f"{case.get('classname')}::{case.get('name')}: {s.get('message')}"
    for case in ET.parse(sys.argv[1]).iter("testcase")
    for s in case.findall("skipped")
]
for line in skipped:
    print("skipped on amd64:", line, file=sys.stderr)
if skipped:
    print(f"{len(skipped)} tests skipped where all should run (KEYFRAMED_ALLOW_SKIPS=1 allows it)",
          file=sys.stderr)
sys.exit(1 if skipped else 0)
PY
fi
step "done (exit status $rc)"
exit "$rc"
