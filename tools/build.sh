#!/usr/bin/env bash
# Builds the C++ tree (release, warnings as errors) and the Python package into
# the venv. Incremental: build dirs are reused.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
JOBS="${KEYFRAMED_JOBS:-2}"
export CMAKE_BUILD_PARALLEL_LEVEL="$JOBS"

# With libcamera 0.4 unpacked by tools/setup.sh, a second daemon linked against it
# (keyframed-libcamera-alt) for tests/harness/test_libcamera_virtual.py.
ALT=""
if [ -f build/debian/trixie/complete ]; then ALT="$ROOT/build/debian/trixie/root"; fi
if [ ! -f build/release/build.ninja ] ||
   ! grep -qx "KEYFRAMED_LIBCAMERA_ALT_ROOT:PATH=$ALT" build/release/CMakeCache.txt; then
  cmake -S . -B build/release -G Ninja -DCMAKE_BUILD_TYPE=Release -DKEYFRAMED_WERROR=ON \
    -DKEYFRAMED_LIBCAMERA_ALT_ROOT="$ALT"
fi
ninja -C build/release -j"$JOBS"

# The Python extension (same CMake, built by scikit-build-core; build dir cached).
STAMP=build/.setup/python-installed
if [ ! -f "$STAMP" ] || ! .venv/bin/python -c "import keyframed._core" 2>/dev/null \
   || [ -n "$(find daemon bindings CMakeLists.txt pyproject.toml -newer "$STAMP" | head -1)" ]; then
  .venv/bin/python -m pip install -q --no-build-isolation --no-deps .
  mkdir -p build/.setup && touch "$STAMP"
fi
