"""Shared fixtures: the built binary, and small videos made from real photos."""

from __future__ import annotations

import os
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
