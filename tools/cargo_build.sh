#!/usr/bin/env bash
# The one cargo command that builds the Rust I/O crate (daemon/io-rs). CMake's build
# runs it; tools/test.sh runs it too, early, beside the rest of set-up, so that the
# crate's cold build (minutes) is under way before the C++ build starts. Both calls
# are the same command on the same target dir, so the second finds the crate built
# (or waits for cargo's lock on the target dir and then finds it built).
# With --test it runs the crate's Rust unit tests instead (a ctest test), with the
# same profile, so that the dependencies built for the library are reused.
#   tools/cargo_build.sh CARGO TARGET_DIR [--test]
set -euo pipefail
[ "$#" -eq 2 ] || { [ "$#" -eq 3 ] && [ "$3" = --test ]; } ||
  { echo "usage: $0 CARGO TARGET_DIR [--test]" >&2; exit 2; }
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
CARGO="$1"
export CARGO_TARGET_DIR="$2"
# cargo runs rustc from its own directory (rustup's or Debian's rustc-web).
PATH="$(dirname "$CARGO"):$PATH"
export PATH
if [ "$#" -eq 3 ]; then
  exec "$CARGO" test --release --locked --lib -j"${KEYFRAMED_JOBS:-2}" --quiet \
    --manifest-path "$ROOT/daemon/io-rs/Cargo.toml"
fi
exec "$CARGO" build --release --locked -j"${KEYFRAMED_JOBS:-2}" --quiet \
  --manifest-path "$ROOT/daemon/io-rs/Cargo.toml"
