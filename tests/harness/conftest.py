"""Shared fixtures: the built binary, and small videos made from real photos."""

from __future__ import annotations

import contextlib
import fcntl
import os
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
PHOTOS = Path("/usr/share/doc/opencv-doc/examples/data")


def keyframed_bin() -> Path:
    path = Path(os.environ.get("KEYFRAMED_BIN", ROOT / "build/release/daemon/keyframed"))
    if not path.exists():
        pytest.fail(f"keyframed binary not found at {path}: run tools/build.sh")
    return path


@pytest.fixture(scope="session")
def kf_bin() -> Path:
    return keyframed_bin()


def sanitized_bin() -> Path | None:
    """The AddressSanitizer + UBSan build of keyframed, when tools/test.sh made one."""
    path = os.environ.get("KEYFRAMED_ASAN_BIN")
    return Path(path) if path and Path(path).exists() else None


@pytest.fixture(scope="session", params=["release", "asan"])
def any_bin(request: pytest.FixtureRequest) -> Path:
    """Bad-input tests run against both builds: under the sanitizers too, no crash."""
    if request.param == "release":
        return keyframed_bin()
    path = sanitized_bin()
    if path is None:
        pytest.skip("no sanitizer build (KEYFRAMED_ASAN_BIN unset): tools/test.sh builds one")
    return path


def build_dir() -> Path:
    build = keyframed_bin().resolve().parent.parent  # BUILD/daemon/keyframed
    if not (build / "CPackConfig.cmake").exists():
        pytest.skip(f"{build} has no CPackConfig.cmake")
    return build


def cached(name: str) -> str:
    """A variable from the build's CMakeCache.txt."""
    for line in (build_dir() / "CMakeCache.txt").read_text().splitlines():
        if line.startswith(name + ":"):
            return line.split("=", 1)[1]
    raise KeyError(name)


def require_usr_prefix() -> None:
    prefix = cached("CMAKE_INSTALL_PREFIX")
    if prefix != "/usr":
        pytest.skip(
            f"build configured with prefix {prefix} (a cache from before the /usr default):"
            " reconfigure with -DCMAKE_INSTALL_PREFIX=/usr to build the .deb"
        )


@pytest.fixture(scope="session")
def deb(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The Debian package built by cpack from the tested build tree (about 5 s)."""
    if shutil.which("dpkg-deb") is None:
        pytest.skip("dpkg-deb not installed")
    require_usr_prefix()
    out = tmp_path_factory.mktemp("pkg")
    p = subprocess.run(
        ["cpack", "-G", "DEB", "-B", str(out)],
        cwd=build_dir(),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert p.returncode == 0, p.stdout + p.stderr
    debs = list(out.glob("keyframed_*_*.deb"))
    assert len(debs) == 1, list(out.iterdir())
    return debs[0]


@contextlib.contextmanager
def host_package_lock() -> Iterator[None]:
    """Held while a test installs the package on this machine (test_package.py) and
    while a VM sees this machine's dpkg state through virtio-9p (test_systemd_vm.py):
    pytest-xdist would otherwise run the two files at once."""
    with open(Path(tempfile.gettempdir()) / "keyframed-tests-dpkg.lock", "w") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        yield


def photo_strip() -> np.ndarray:
    parts = []
    for name in ("aero1.jpg", "aero3.jpg", "building.jpg", "baboon.jpg"):
        img = cv2.imread(str(PHOTOS / name))
        assert img is not None, f"missing {PHOTOS / name} (Debian package opencv-doc)"
        h, w = img.shape[:2]
        parts.append(cv2.resize(img, (w * 480 // h, 480), interpolation=cv2.INTER_AREA))
    return np.hstack(parts)


def write_pan_video(
    path: Path, frames: int = 90, step: float = 6.0, size=(480, 270), fourcc: str = "MJPG"
) -> Path:
    """A camera panning along real photos at `step` px per frame, MJPG (or `fourcc`) at
    30 fps."""
    strip = photo_strip()
    w, h = size
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*fourcc), 30.0, (w, h))
    assert vw.isOpened()
    for i in range(frames):
        m = np.array([[1, 0, -(50 + i * step)], [0, 1, -100]], np.float32)
        vw.write(cv2.warpAffine(strip, m, (w, h), borderMode=cv2.BORDER_REFLECT))
    vw.release()
    return path


@pytest.fixture(scope="session")
def pan_video(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_pan_video(tmp_path_factory.mktemp("pan") / "pan.avi")


def pytest_configure(config: pytest.Config) -> None:
    # The controller (or a run without xdist) starts the flight-quality table afresh;
    # pytest-xdist workers (they have workerinput) only add rows to it.
    if not hasattr(config, "workerinput"):
        for row in (ROOT / "build" / "reports" / "flight_quality").glob("*.json"):
            row.unlink()


def pytest_terminal_summary(terminalreporter) -> None:  # noqa: ANN001 - pytest hook
    try:
        from test_flights import write_report
    except ImportError:
        return
    text = write_report()
    if text:
        terminalreporter.write_sep("-", "selection quality against ground truth")
        terminalreporter.write(text)
