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
# The release tree builds the Python extension too, and scikit-build-core packages it
# from the same build directory with the same settings: the sources are compiled
# once. (A plain `pip install .` builds in build/python with pyproject.toml's.) The
# prefix is given to both: scikit-build-core would otherwise set its wheel's.
DEFINES=(-DCMAKE_INSTALL_PREFIX=/usr -DKEYFRAMED_WERROR=ON -DKEYFRAMED_BUILD_TESTS=ON -DKEYFRAMED_BUILD_BENCHMARKS=ON
         -DKEYFRAMED_BUILD_DAEMON=ON -DKEYFRAMED_WITH_IO=ON -DKEYFRAMED_BUILD_PYTHON=ON
         "-DKEYFRAMED_LIBCAMERA_ALT_ROOT=$ALT")
if [ ! -f build/release/build.ninja ] ||
   ! grep -qx "KEYFRAMED_LIBCAMERA_ALT_ROOT:PATH=$ALT" build/release/CMakeCache.txt ||
   ! grep -qx "KEYFRAMED_BUILD_PYTHON:BOOL=ON" build/release/CMakeCache.txt; then
  cmake -S . -B build/release -G Ninja -DCMAKE_BUILD_TYPE=Release \
    -DPython_EXECUTABLE="$ROOT/.venv/bin/python" "${DEFINES[@]}"
fi
# One job more than cores: the cargo build of the Rust crate is one of ninja's jobs but
# runs its own $JOBS; through its long serial stretches C++ keeps both cores busy.
ninja -C build/release -j"$((JOBS + 1))"

STAMP=build/.setup/python-installed
if [ ! -f "$STAMP" ] || ! .venv/bin/python -c "import keyframed._core" 2>/dev/null \
   || [ -n "$(find daemon bindings CMakeLists.txt pyproject.toml -newer "$STAMP" | head -1)" ]; then
  SKB=(-C build-dir=build/release)
  for d in "${DEFINES[@]}"; do SKB+=(-C "cmake.define.${d#-D}"); done
  .venv/bin/python -m pip install -q --no-build-isolation --no-deps "${SKB[@]}" .
  mkdir -p build/.setup && touch "$STAMP"
fi
