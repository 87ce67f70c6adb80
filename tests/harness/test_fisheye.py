"""Selection through a fisheye lens, on a flight rendered through one.

A nadir camera with OpenCV's fisheye model (120 degrees across the image) flies a
straight line over the synthetic flights' ground texture. With the lens's
calibration, `keyframed select` measures overlap through the lens: consecutive
keyframes share the target's share of the image, as the geometry says. Without it
the homography is fitted to the pixels the lens draws, and the figures for that are
reported beside.
"""

from __future__ import annotations

import csv
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest
from keyframed import synth

WIDTH, HEIGHT, FPS = 480, 270, 30.0
K = np.array([[220.0, 0.0, 239.5], [0.0, 221.0, 134.5], [0.0, 0.0, 1.0]])
D = np.array([0.032, -0.0081, 0.0017, -0.0003])
HEIGHT_M, SPEED_MS, SECONDS = 15.0, 8.0, 16.0
TEXEL_M = 0.05  # the ground texture's; 0.07 m a pixel at the image centre


def _rays(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Normalised image-plane coordinates (x/z, y/z) of pixels (u, v)."""
    pts = np.stack([u.ravel(), v.ravel()], 1).astype(np.float64).reshape(-1, 1, 2)
    return cv2.fisheye.undistortPoints(pts, K, D).reshape(-1, 2)


def _east(i: int) -> float:
    return -64.0 + SPEED_MS * i / FPS


def _seen(rays: np.ndarray, i: int, j: int) -> float:
    """The share of frame i's sampled pixels that frame j shows (nadir, image x east,
    image y south, flat ground HEIGHT_M below)."""
    east = _east(i) + HEIGHT_M * rays[:, 0]
    north = -HEIGHT_M * rays[:, 1]
    xj = (east - _east(j)) / HEIGHT_M
    yj = -north / HEIGHT_M
    pts = np.stack([xj, yj], 1).reshape(-1, 1, 2)
    px = cv2.fisheye.distortPoints(pts, K, D).reshape(-1, 2)
    inside = (px[:, 0] >= -0.5) & (px[:, 1] >= -0.5)
    inside &= (px[:, 0] < WIDTH - 0.5) & (px[:, 1] < HEIGHT - 0.5)
    return float(inside.mean())


@pytest.fixture(scope="module")
def fisheye_flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("fisheye")
    tex = cv2.cvtColor(synth.ground_mosaic(), cv2.COLOR_BGRA2GRAY)
    u, v = np.meshgrid(np.arange(WIDTH), np.arange(HEIGHT))
    rays = _rays(u, v)
    n = int(SECONDS * FPS)
    writer = cv2.VideoWriter(
        str(out / "video.avi"), cv2.VideoWriter.fourcc(*"MJPG"), FPS, (WIDTH, HEIGHT)
    )
    assert writer.isOpened()
    rng = np.random.default_rng(5)
    for i in range(n):
        east = _east(i) + HEIGHT_M * rays[:, 0]
        north = -HEIGHT_M * rays[:, 1]
        col = ((east + 125.0) / TEXEL_M - 0.5).reshape(HEIGHT, WIDTH).astype(np.float32)
        row = ((125.0 - north) / TEXEL_M - 0.5).reshape(HEIGHT, WIDTH).astype(np.float32)
        img = cv2.remap(tex, col, row, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT101)
        noise = rng.normal(0.0, 2.0, img.shape)
        img = np.clip(img + noise, 0, 255).astype(np.uint8)
        writer.write(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    writer.release()
    fs = cv2.FileStorage(str(out / "fisheye.yaml"), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", WIDTH)
    fs.write("image_height", HEIGHT)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", D.reshape(4, 1))
    fs.write("fisheye_model", 1)
    fs.release()
    return out


def _keyframes(kf_bin: Path, video: Path, out: Path, *args: str) -> list[int]:
    r = subprocess.run(
        ["nice", "-n", "10", str(kf_bin), "select", str(video), "--out", str(out), "--quiet"]
        + list(args),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    return _kept(out)


def _kept(out: Path) -> list[int]:
    """The kept frames' indices in OUT/decisions.csv."""
    with (out / "decisions.csv").open() as f:
        return [int(row["index"]) for row in csv.DictReader(f) if row["kept"] == "1"]


def test_overlap_is_measured_through_the_fisheye_lens(
    kf_bin: Path, fisheye_flight: Path, tmp_path: Path
) -> None:
    u, v = np.meshgrid(
        (np.arange(96) + 0.5) * WIDTH / 96 - 0.5, (np.arange(54) + 0.5) * HEIGHT / 54 - 0.5
    )
    rays = _rays(u, v)
    video = fisheye_flight / "video.avi"
    calib = fisheye_flight / "fisheye.yaml"
    with_lens = _keyframes(kf_bin, video, tmp_path / "lens", "--calibration", str(calib))
    without = _keyframes(kf_bin, video, tmp_path / "raw")
    assert len(with_lens) >= 5 and len(without) >= 2, (with_lens, without)
    pairs = [_seen(rays, a, b) for a, b in zip(with_lens, with_lens[1:], strict=False)]
    raw_pairs = [_seen(rays, a, b) for a, b in zip(without, without[1:], strict=False)]
    print(
        f"\nfisheye flight, target 0.70: through the lens {len(with_lens)} keyframes, "
        f"true overlaps {min(pairs):.3f}..{max(pairs):.3f}; without the calibration "
        f"{len(without)}, {min(raw_pairs):.3f}..{max(raw_pairs):.3f}"
    )
    print("through the lens", [round(p, 3) for p in pairs])
    print("without", [round(p, 3) for p in raw_pairs])
    # 128 m flown, about 20 m between keyframes (asserted above).
    # The last keyframe may close the flight early; the others are at the target.
    assert all(abs(p - 0.70) < 0.025 for p in pairs[:-1]), pairs
    assert all(0.60 <= p for p in pairs), pairs


def test_the_python_module_selects_through_the_lens_too(
    kf_bin: Path, fisheye_flight: Path, tmp_path: Path
) -> None:
    """keyframed.select_video with the calibration decides as `keyframed select
    --calibration` does, and differently from without it."""
    import keyframed

    video = fisheye_flight / "video.avi"
    calib = str(fisheye_flight / "fisheye.yaml")
    cli = _keyframes(kf_bin, video, tmp_path / "cli", "--calibration", calib)
    r = keyframed.select_video(str(video), str(tmp_path / "py"), calibration=calib)
    assert r["error"] == "" and r["kept"] == len(cli)
    assert _kept(tmp_path / "py") == cli
    assert b'Camera:ModelType="fisheye"' in (tmp_path / "py" / f"{cli[1]:06d}.jpg").read_bytes()
    raw = keyframed.select_video(str(video), str(tmp_path / "raw"))
    unlensed = _kept(tmp_path / "raw")
    assert unlensed != cli and raw["kept"] == len(unlensed)
    with pytest.raises(RuntimeError, match="nonexistent"):
        keyframed.select_video(str(video), str(tmp_path / "bad"), calibration="/nonexistent.yaml")
