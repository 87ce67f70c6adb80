#!/usr/bin/env bash
# Idempotent set-up on Debian 12 (as root, or with sudo): apt packages, Rust crates,
# Python venv. Safe to run again; does nothing that is already done.
#   tools/setup.sh [--system]   (--system: apt packages and Rust crates only)
set -euo pipefail
case "${1:-}" in
  "" | --system) ;;
  *) echo "usage: tools/setup.sh [--system]" >&2; exit 2 ;;
esac
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${KEYFRAMED_VENV:-$ROOT/.venv}"
STAMP_DIR="$ROOT/build/.setup"
mkdir -p "$STAMP_DIR"

APT_PACKAGES=(
  build-essential cmake ninja-build pkg-config git
  python3 python3-dev python3-venv
  libopencv-dev opencv-doc libavcodec-dev
  libcamera-dev libv4l-dev libexiv2-dev libturbojpeg0-dev libsystemd-dev
  libtomlplusplus-dev libzstd-dev libgtest-dev libbenchmark-dev
  libimage-exiftool-perl clang-format
  clang-14 libclang-rt-14-dev
  protobuf-compiler libprotobuf-dev
)

# tests/harness/test_zenoh_security.py: a throw-away CA and server certificate.
APT_PACKAGES+=(openssl)
# tests/harness/test_systemd.py: systemd-analyze verify/security on the unit;
# tests/harness/test_flight_record.py: strace counts the record's fsyncs.
APT_PACKAGES+=(systemd strace)
# tests/harness/test_package.py: CPack's DEB generator needs file(1) and
# dpkg-shlibdeps (dpkg-dev) for the package's Depends (a fresh Debian 12 lacks file).
APT_PACKAGES+=(file dpkg-dev)
# tests/harness/test_ground.py: COLMAP's own feature_importer and matches_importer
# read the ground station's SIFT export and pairs list (Debian's COLMAP 3.8, CPU).
APT_PACKAGES+=(colmap)

# tests/harness/test_v4l2_vivid.py: the kernel's vivid camera driver under qemu
# (an x86-64 guest; on other architectures, e.g. a Pi, that test skips).
# tests/harness/test_systemd_vm.py: the installed service under systemd in such a VM
# (udev gives the camera node to group video). tests/harness/test_arm64.py: the core
# and its tests cross-built for a Pi (arm64), run under qemu-aarch64.
if [ "$(dpkg --print-architecture)" = amd64 ]; then
  APT_PACKAGES+=(qemu-system-x86 linux-image-amd64 busybox-static cpio udev)
  APT_PACKAGES+=(g++-aarch64-linux-gnu qemu-user)
fi

# Rust 1.88+ for daemon/io-rs: rustup's toolchain when there is one, else Debian 12's
# rustc-web/cargo-web (1.96 from bookworm-security; Debian's plain rustc is 1.63).
export PATH="$HOME/.cargo/bin:/root/.cargo/bin:$PATH"
rust_ok() {
  command -v cargo > /dev/null && command -v rustc > /dev/null || return 1
  local v
  v="$(rustc --version | awk '{print $2}')"
  [ "$(printf '%s\n1.88.0\n' "$v" | sort -V | head -1)" = "1.88.0" ]
}
if ! rust_ok; then APT_PACKAGES+=(rustc-web cargo-web); fi

SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi

missing_apt() {
  local p out=()
  for p in "${APT_PACKAGES[@]}"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || out+=("$p")
  done
  echo "${out[@]:-}"
}

MISSING="$(missing_apt)"
if [ -n "$MISSING" ]; then
  echo "setup: installing apt packages: $MISSING"
  export DEBIAN_FRONTEND=noninteractive
  APT_LOCK=(-o DPkg::Lock::Timeout=600)
  # A stale or partial package index (a mirror mid-sync) fails the update; the
  # install below then fails too, and the next attempt refreshes it again.
  # libsystemd-dev can upgrade systemd and leave dpkg half-configured (exit 100):
  # repair and retry rather than fail.
  for attempt in 1 2 3; do
    $SUDO apt-get update -qq "${APT_LOCK[@]}" || echo "setup: apt-get update failed (attempt $attempt)" >&2
    if $SUDO apt-get install -y -qq "${APT_LOCK[@]}" --no-install-recommends $MISSING; then break; fi
    echo "setup: apt-get install failed (attempt $attempt), repairing" >&2
    $SUDO dpkg --configure -a --force-confdef --force-confold || true
    $SUDO apt-get -f install -y -qq "${APT_LOCK[@]}" || true
    [ "$attempt" = 3 ] && { echo "setup: apt-get install failed" >&2; exit 1; }
  done
fi

# Rust crates of daemon/io-rs (zenoh, mcap), fetched once per Cargo.lock so that the
# build itself needs no network.
LOCK="$ROOT/daemon/io-rs/Cargo.lock"
if ! rust_ok; then
  echo "setup: no cargo with rustc 1.88 or newer: install rustup, or enable bookworm-security" \
       "for apt's rustc-web/cargo-web (found: $(rustc --version 2>/dev/null || echo none))." \
       "To build without MCAP and Zenoh, configure with -DKEYFRAMED_WITH_IO=OFF." >&2
  exit 1
elif ! cmp -s "$LOCK" "$STAMP_DIR/io-rs-Cargo.lock"; then
  echo "setup: fetching Rust crates (cargo fetch --locked)"
  (cd "$ROOT/daemon/io-rs" && cargo fetch --locked -q)
  cp "$LOCK" "$STAMP_DIR/io-rs-Cargo.lock"
fi

# --system: apt packages and Rust crates only (tools/test.sh starts the crate's build
# then, beside the rest of set-up).
if [ "${1:-}" = --system ]; then exit 0; fi

# tests/harness/test_libcamera_virtual.py: newer libcamera releases than Debian 12's
# 0.0.3, unpacked under build/debian (nothing installed): trixie's 0.4 with its
# runtime, kernel and 9p modules (run under qemu on its virtual camera), sid's newest
# headers (compiled against). Not fatal: without them that test skips, saying why.
if [ "$(dpkg --print-architecture)" = amd64 ]; then
  python3 "$ROOT/tools/fetch_debian.py" --suite trixie --dest "$ROOT/build/debian/trixie" \
    --kernel amd64 --modules 9p,9pnet_virtio libcamera0.4 libcamera-dev libc6 libstdc++6 \
    libgcc-s1 ||
    echo "setup: warning: no libcamera 0.4 from trixie; the libcamera VM test will skip" >&2
  python3 "$ROOT/tools/fetch_debian.py" --suite sid --dest "$ROOT/build/debian/sid" \
    --no-deps libcamera-dev ||
    echo "setup: warning: no libcamera headers from sid; that compile check will skip" >&2
  # tests/harness/test_arm64.py: Debian 12's arm64 OpenCV (the modules the core and
  # its tests use, and what those load), unpacked under build/debian (95 MB).
  python3 "$ROOT/tools/fetch_debian.py" --suite bookworm --arch arm64 \
    --dest "$ROOT/build/debian/bookworm-arm64" --no-deps \
    libopencv-{core,imgproc,features2d,flann,calib3d,video}-dev \
    libopencv-{core,imgproc,features2d,flann,calib3d,video,dnn}406 libprotobuf32 \
    libtbb12 libtbbmalloc2 libtbbbind-2-5 libhwloc15 libxml2 libicu72 liblzma5 libudev1 \
    libglx0 libglvnd0 libx11-6 libxcb1 libxau6 libxdmcp6 libbsd0 libmd0 liblapack3 \
    libblas3 libgfortran5 zlib1g ||
    echo "setup: warning: no arm64 OpenCV from bookworm; the arm64 test will skip" >&2
fi

PY="${PYTHON:-python3}"
if [ ! -x "$VENV/bin/python" ]; then
  echo "setup: creating venv $VENV"
  "$PY" -m venv "$VENV"
fi
# The stamp lives in the venv, so a removed or recreated venv is filled again.
REQ="$ROOT/tools/requirements.txt"
if ! cmp -s "$REQ" "$VENV/.keyframed-requirements.txt"; then
  echo "setup: installing Python packages"
  "$VENV/bin/python" -m pip install -q --upgrade pip
  "$VENV/bin/python" -m pip install -q -r "$REQ"
  cp "$REQ" "$VENV/.keyframed-requirements.txt"
fi
