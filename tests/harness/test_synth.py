"""Tests of the synthetic flight generator (keyframed.synth) and its ground truth."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from keyframed import synth

W, H = 480, 270
NADIR_S = 12.0
ORBIT_S = 6.0


@pytest.fixture(scope="session")
def nadir(tmp_path_factory: pytest.TempPathFactory) -> synth.Flight:
    d = tmp_path_factory.mktemp("nadir")
    info = synth.generate("nadir", d, width=W, height=H, seconds=NADIR_S, seed=0)
    assert info.frames == 360
    return synth.load_flight(d)


@pytest.fixture(scope="session")
def orbit(tmp_path_factory: pytest.TempPathFactory) -> synth.Flight:
    d = tmp_path_factory.mktemp("orbit")
    synth.generate("orbit", d, width=W, height=H, seconds=ORBIT_S, seed=0)
    return synth.load_flight(d)


def read_frames(video: Path, wanted: set[int]) -> dict[int, np.ndarray]:
    cap = cv2.VideoCapture(str(video))
    out: dict[int, np.ndarray] = {}
    i = 0
    try:
        while len(out) < len(wanted):
            ok, frame = cap.read()
            if not ok:
                break
            if i in wanted:
                out[i] = frame
            i += 1
    finally:
        cap.release()
    assert set(out) == wanted, f"missing frames {wanted - set(out)}"
    return out


def euler_to_r(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """ZYX aeronautical Euler angles (deg) -> R_ned_body, written out independently."""
    r, p, y = (math.radians(v) for v in (roll, pitch, yaw))
    rx = np.array([[1, 0, 0], [0, math.cos(r), -math.sin(r)], [0, math.sin(r), math.cos(r)]])
    ry = np.array([[math.cos(p), 0, math.sin(p)], [0, 1, 0], [-math.sin(p), 0, math.cos(p)]])
    rz = np.array([[math.cos(y), -math.sin(y), 0], [math.sin(y), math.cos(y), 0], [0, 0, 1]])
    return rz @ ry @ rx


def orb_overlap(a: np.ndarray, b: np.ndarray) -> float:
    """Image-based overlap of a in b: ORB + brute-force matching + RANSAC homography."""
    orb = cv2.ORB.create(nfeatures=3000)
    ga = cv2.cvtColor(a, cv2.COLOR_BGR2GRAY)
    gb = cv2.cvtColor(b, cv2.COLOR_BGR2GRAY)
    # No mask: OpenCV takes None, which its stubs leave out.
    ka, da = orb.detectAndCompute(ga, None)  # type: ignore[call-overload]
    kb, db = orb.detectAndCompute(gb, None)  # type: ignore[call-overload]
    matches = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(da, db)
    assert len(matches) > 100
    src = np.array([ka[m.queryIdx].pt for m in matches], np.float32)
    dst = np.array([kb[m.trainIdx].pt for m in matches], np.float32)
    h, inl = cv2.findHomography(src, dst, cv2.RANSAC, 2.0)
    assert h is not None and int(inl.sum()) > 60
    return synth.overlap_fraction(h, a.shape[1], a.shape[0])


# --------------------------------------------------------------------------- files


def test_outputs(nadir: synth.Flight) -> None:
    d = nadir.path
    for name in ("video.avi", "groundtruth.csv", "intrinsics.json", "flight.tlog", "meta.json"):
        assert (d / name).stat().st_size > 0, name
    assert len(nadir) == int(NADIR_S * 30)
    cap = cv2.VideoCapture(str(d / "video.avi"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == len(nadir)
    ok, first = cap.read()
    cap.release()
    assert ok and first.shape == (H, W, 3)
    header = (d / "groundtruth.csv").read_text().splitlines()[0].split(",")
    assert tuple(header) == synth.GT_COLUMNS
    intr = json.loads((d / "intrinsics.json").read_text())
    assert intr["width"] == W and intr["height"] == H
    assert intr["distortion"] == [0, 0, 0, 0, 0]
    assert intr["fx"] == pytest.approx(intr["fy"])
    assert intr["fx"] == pytest.approx((W / 2) / math.tan(math.radians(35.0)))
    assert intr["focal_length_mm"] == pytest.approx(intr["fx"] * intr["sensor_width_mm"] / W)
    assert intr["sensor_width_mm"] / intr["sensor_height_mm"] == pytest.approx(W / H)
    assert intr["mount_pitch_deg"] == -90.0
    meta = json.loads((d / "meta.json").read_text())
    assert meta["frames"] == len(nadir) and meta["flight"] == "nadir"
    assert meta["hover_frames"] == [[225, 344]]
    assert meta["epoch_unix_s"] == synth.EPOCH_UNIX_S
    assert nadir.t[1] - nadir.t[0] == pytest.approx(1 / 30)


def test_pose_conventions(nadir: synth.Flight, orbit: synth.Flight) -> None:
    """Camera-to-world = ENU<-NED * vehicle attitude * mount pitch (the documented chain)."""
    t_enu_ned = np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1]], float)
    r_body_cam0 = np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0]], float)
    for fl in (nadir, orbit):
        mount = math.radians(fl.intrinsics["mount_pitch_deg"])
        ry = np.array(
            [
                [math.cos(mount), 0, math.sin(mount)],
                [0, 1, 0],
                [-math.sin(mount), 0, math.cos(mount)],
            ]
        )
        for i in range(0, len(fl), 37):
            r = t_enu_ned @ euler_to_r(*fl.euler_deg[i]) @ ry @ r_body_cam0
            np.testing.assert_allclose(fl.rotations[i], r, atol=1e-6)
    # nadir camera looks straight down while hovering, image top towards the nose (north)
    hov = np.nonzero(nadir.hover)[0]
    z_axes = nadir.rotations[hov][:, :, 2]
    assert np.all(z_axes[:, 2] < -0.999)
    assert np.all(nadir.rotations[hov][:, 1, 1] < -0.999)  # image y (down) points south
    assert np.allclose(nadir.positions[hov, 2], 50.0, atol=0.1)
    # orbit: optical axis about 55 deg below the horizon (less the bank), vehicle 35 m up
    elev = np.degrees(np.arcsin(orbit.rotations[:, 2, 2]))
    assert np.median(elev) == pytest.approx(-55.0, abs=2.0)


# --------------------------------------------------------------------------- overlap


def test_overlap_identity(nadir: synth.Flight, orbit: synth.Flight) -> None:
    for fl in (nadir, orbit):
        for i in (0, 50, len(fl) - 1):
            assert fl.overlap(i, i) == pytest.approx(1.0, abs=1e-9)
            h = fl.homography(i, i)
            assert synth.overlap_fraction(h / h[2, 2], W, H) == pytest.approx(1.0, abs=1e-6)


def test_overlap_along_straight_leg(nadir: synth.Flight) -> None:
    ks = list(range(0, 90, 5))
    ov = [nadir.overlap(0, k) for k in ks]
    assert all(b <= a + 1e-3 for a, b in zip(ov, ov[1:], strict=False)), ov
    assert ov[1] > 0.9  # 5 frames at 8 m/s and 50 m: about 3.4 % of the footprint
    assert 0.3 < ov[-1] < 0.6
    consecutive = [nadir.overlap(i, i + 1) for i in range(0, 80)]
    assert min(consecutive) > 0.98


def test_overlap_hover(nadir: synth.Flight) -> None:
    hov = np.nonzero(nadir.hover)[0]
    assert len(hov) == 120
    for i in hov[::20]:
        for j in hov[::30]:
            assert nadir.overlap(int(i), int(j)) > 0.97


def test_overlap_orbit(orbit: synth.Flight) -> None:
    ov = [orbit.overlap(0, k) for k in range(0, len(orbit), 10)]
    assert all(0.0 <= v <= 1.0 for v in ov)
    assert ov[-1] < ov[1]
    assert all(b <= a + 1e-2 for a, b in zip(ov, ov[1:], strict=False)), ov


def test_overlap_fraction_helper() -> None:
    shift = np.array([[1.0, 0.0, 120.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    assert synth.overlap_fraction(shift, W, H) == pytest.approx(1 - 120 / W)
    half = np.diag([0.5, 0.5, 1.0])  # image i is twice as large as j's view: all of i inside
    assert synth.overlap_fraction(half, W, H) == pytest.approx(1.0)
    assert synth.overlap_fraction(np.linalg.inv(half), W, H) == pytest.approx(0.25, abs=1e-3)
    # a homography sending part of image i behind camera j
    behind = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0 / W, 0.0, 0.5]])
    v = synth.overlap_fraction(behind, W, H)
    assert 0.0 <= v < 0.5


@pytest.mark.parametrize(("flight", "target"), [("nadir", 0.7), ("orbit", 0.7)])
def test_overlap_matches_images(flight: str, target: float, request: pytest.FixtureRequest) -> None:
    """Ground-truth overlap agrees with ORB + RANSAC on the rendered frames."""
    fl: synth.Flight = request.getfixturevalue(flight)
    i = 0
    j = next(k for k in range(1, len(fl)) if fl.overlap(i, k) <= target)
    while fl.blurry[j]:
        j += 1
    gt = fl.overlap(i, j)
    assert target - 0.1 < gt <= target
    frames = read_frames(fl.path / "video.avi", {i, j})
    est = orb_overlap(frames[i], frames[j])
    assert est == pytest.approx(gt, abs=0.05), (i, j, gt, est)


# --------------------------------------------------------------------------- blur


def test_blur_labels(nadir: synth.Flight) -> None:
    expected = (nadir.blur_px > 2.0) | (nadir.defocus_sigma > 1.0)
    assert np.array_equal(nadir.blurry, expected)
    meta = json.loads((nadir.path / "meta.json").read_text())
    a, b = meta["defocus"][0]["frames"]
    assert b - a + 1 >= 15
    inside = [k for k in range(a, b + 1) if nadir.defocus_sigma[k] > 1.0]
    assert len(inside) >= 12 and all(nadir.blurry[k] for k in inside)
    outside = [k for k in range(a - 16, a - 5)] + [k for k in range(b + 6, b + 17)]
    assert not any(nadir.blurry[k] for k in outside)
    frames = read_frames(nadir.path / "video.avi", set(inside) | set(outside))

    def lapvar(img: np.ndarray) -> float:
        g = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        return float(cv2.Laplacian(g, cv2.CV_64F).var())

    blurred = np.median([lapvar(frames[k]) for k in inside])
    sharp = np.median([lapvar(frames[k]) for k in outside])
    assert blurred < 0.5 * sharp, (blurred, sharp)
    frac = float(nadir.blurry.mean())
    assert 0.02 < frac < 0.2


def test_motion_blur_from_sub_frames(tmp_path: Path) -> None:
    # The same second of flight at the default 1/500 s shutter and at 1/30 s: same
    # poses, so only the exposure differs. The long one smears ~16.7x further, is
    # labelled blurry throughout, and its frames show it: less Laplacian variance,
    # and less gradient energy along the direction of flight than across it
    # (motion blur is directional; defocus is not).
    short, long_ = tmp_path / "short", tmp_path / "long"
    synth.generate("nadir", short, width=960, height=540, seconds=1.0, seed=0)
    synth.generate("nadir", long_, width=960, height=540, seconds=1.0, seed=0, exposure_s=1 / 30)
    s, lg = synth.load_flight(short), synth.load_flight(long_)
    assert np.allclose(lg.blur_px / s.blur_px, (1 / 30) / synth.DEFAULT_EXPOSURE_S, rtol=0.01)
    assert not s.blurry.any() and lg.blurry.all() and (lg.blur_px > 2).all()
    assert not lg.defocus_sigma.any()

    def energies(video: Path) -> np.ndarray:
        frames = read_frames(video, set(range(0, 30, 5)))
        out = []
        for k in sorted(frames):
            g = cv2.cvtColor(frames[k], cv2.COLOR_BGR2GRAY).astype(np.float64)
            gx = float((cv2.Sobel(g, cv2.CV_64F, 1, 0) ** 2).mean())
            gy = float((cv2.Sobel(g, cv2.CV_64F, 0, 1) ** 2).mean())
            out.append((cv2.Laplacian(g, cv2.CV_64F).var(), gx, gy))
        return np.array(out)

    ratio = energies(long_ / "video.avi") / energies(short / "video.avi")
    assert (ratio[:, 0] < 0.7).all(), ratio
    assert (np.abs(ratio[:, 1] - ratio[:, 2]) > 0.1).all(), ratio


# --------------------------------------------------------------------------- determinism


def test_determinism(tmp_path: Path, nadir: synth.Flight) -> None:
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    synth.generate("nadir", a, width=W, height=H, seconds=1.0, seed=0)
    synth.generate("nadir", b, width=W, height=H, seconds=1.0, seed=0)
    synth.generate("nadir", c, width=W, height=H, seconds=1.0, seed=1)
    gt_a = (a / "groundtruth.csv").read_bytes()
    assert gt_a == (b / "groundtruth.csv").read_bytes()
    assert gt_a != (c / "groundtruth.csv").read_bytes()
    fa = read_frames(a / "video.avi", {0})[0]
    fb = read_frames(b / "video.avi", {0})[0]
    assert np.array_equal(fa, fb)
    # a shorter flight is a prefix of the longer one
    long_rows = (nadir.path / "groundtruth.csv").read_text().splitlines()
    assert gt_a.decode().splitlines() == long_rows[:31]
    assert np.array_equal(fa, read_frames(nadir.path / "video.avi", {0})[0])


# --------------------------------------------------------------------------- tlog


def test_tlog(nadir: synth.Flight) -> None:
    from pymavlink import mavutil

    path = nadir.path / "flight.tlog"
    raw = path.read_bytes()
    assert raw[8] == 0xFD  # MAVLink 2
    conn = mavutil.mavlink_connection(str(path))
    msgs: dict[str, list] = {}
    while True:
        m = conn.recv_match(blocking=False)
        if m is None:
            break
        if m.get_type() == "BAD_DATA":
            pytest.fail(f"bad data in tlog: {m}")
        assert m.get_srcSystem() == 1 and m.get_srcComponent() == 1
        msgs.setdefault(m.get_type(), []).append(m)
    conn.close()
    duration = NADIR_S + 3.0  # 2 s before frame 0, 1 s after the last frame
    rates = {
        "HEARTBEAT": 1,
        "SYSTEM_TIME": 1,
        "ATTITUDE": 50,
        "ATTITUDE_QUATERNION": 50,
        "GLOBAL_POSITION_INT": 10,
        "GPS_RAW_INT": 5,
    }
    for name, rate in rates.items():
        n = len(msgs.get(name, []))
        assert abs(n / duration - rate) <= max(0.05 * rate, 1.0 / duration + 1e-9), (name, n)
    # tlog timestamps are unix time, consistent with time_boot_ms and SYSTEM_TIME
    for m in msgs["ATTITUDE"][::25]:
        t = (m.time_boot_ms - synth.BOOT_MS_AT_FRAME0) / 1000.0
        assert m._timestamp == pytest.approx(synth.EPOCH_UNIX_S + t, abs=1e-3)
    st = msgs["SYSTEM_TIME"][3]
    assert st.time_unix_usec / 1e6 - (st.time_boot_ms - synth.BOOT_MS_AT_FRAME0) / 1e3 == (
        pytest.approx(synth.EPOCH_UNIX_S, abs=1e-3)
    )
    gps = msgs["GPS_RAW_INT"][0]
    assert gps.fix_type == 3 and gps.satellites_visible == 14
    # ATTITUDE_QUATERNION (body -> NED) agrees with ATTITUDE's Euler angles
    for a, q in list(zip(msgs["ATTITUDE"], msgs["ATTITUDE_QUATERNION"], strict=True))[::40]:
        assert a.time_boot_ms == q.time_boot_ms
        w, x, y, z = q.q1, q.q2, q.q3, q.q4
        rq = np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )
        re = euler_to_r(*(math.degrees(v) for v in (a.roll, a.pitch, a.yaw)))
        np.testing.assert_allclose(rq, re, atol=1e-5)

    gpi = msgs["GLOBAL_POSITION_INT"]
    tb = np.array([m.time_boot_ms for m in gpi], float)
    lat = np.array([m.lat for m in gpi], float) / 1e7
    lon = np.array([m.lon for m in gpi], float) / 1e7
    alt = np.array([m.alt for m in gpi], float) / 1e3
    att = msgs["ATTITUDE"]
    ta = np.array([m.time_boot_ms for m in att], float)
    for i in (0, 1, 100, 222, 305, len(nadir) - 1):
        t_ms = synth.BOOT_MS_AT_FRAME0 + nadir.t[i] * 1000.0
        assert abs(np.interp(t_ms, tb, lat) - nadir.geodetic[i, 0]) < 1e-6
        assert abs(np.interp(t_ms, tb, lon) - nadir.geodetic[i, 1]) < 1e-6
        assert abs(np.interp(t_ms, tb, alt) - nadir.geodetic[i, 2]) < 0.01
        if i % 3 == 0:  # frame times on the 50 Hz grid: attitude must match exactly
            m = att[int(np.searchsorted(ta, round(t_ms)))]
            assert m.time_boot_ms == round(t_ms)
            yaw = math.degrees(m.yaw) % 360.0
            assert math.degrees(m.roll) == pytest.approx(nadir.euler_deg[i, 0], abs=1e-4)
            assert math.degrees(m.pitch) == pytest.approx(nadir.euler_deg[i, 1], abs=1e-4)
            dy = (yaw - nadir.euler_deg[i, 2] + 180.0) % 360.0 - 180.0
            assert abs(dy) < 1e-4


# --------------------------------------------------------------------------- CLI


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ)
    pkg = str(Path(synth.__file__).resolve().parents[1])
    env["PYTHONPATH"] = pkg + os.pathsep + env.get("PYTHONPATH", "")
    return subprocess.run(
        [sys.executable, "-m", "keyframed.synth", *args],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )


@pytest.mark.parametrize(
    "args",
    [
        ["--flight", "spiral", "--out", "X"],
        ["--flight", "nadir"],
        ["--flight", "nadir", "--out", "X", "--width", "0"],
        ["--flight", "nadir", "--out", "X", "--width", "abc"],
        ["--flight", "orbit", "--out", "X", "--seconds", "-1"],
        ["--flight", "orbit", "--out", "X", "--fps", "0"],
        ["--flight", "nadir", "--out", "X", "--seconds", "400"],
    ],
)
def test_cli_bad_arguments(args: list[str], tmp_path: Path) -> None:
    args = [str(tmp_path / "out") if a == "X" else a for a in args]
    r = _cli(*args)
    assert r.returncode != 0
    assert r.stdout == ""
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "error" in lines[0], r.stderr


def test_cli_generates(tmp_path: Path) -> None:
    out = tmp_path / "cli"
    r = _cli("--flight", "orbit", "--out", str(out), "--width", "320", "--height", "180",
             "--seconds", "0.5")  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert len(r.stdout.strip().splitlines()) == 1 and "15 frames" in r.stdout
    assert len(synth.load_flight(out)) == 15


def test_a_video_too_large_for_the_avi_writer_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """OpenCV's AVI writer aborts the process when it closes a file past 4 GiB (after
    half an hour of rendering a 10-minute 1080p flight): the generator says so
    instead, from the first second's size when the whole would be well over, or
    once the file is, and the file it leaves closes and reads (no abort)."""
    # a second that fits, for the size of a frame of this flight
    fl = synth.generate("orbit", tmp_path / "fits", width=320, height=180, seconds=1.0)
    assert fl.frames == 30
    per_frame = (tmp_path / "fits" / "video.avi").stat().st_size / 30

    def frames_in(video: Path) -> int:
        cap = cv2.VideoCapture(str(video))
        try:
            assert cap.isOpened() and cap.read()[0]
            return int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        finally:
            cap.release()

    # 4 s (120 frames) against room for 48: the first second says so (at NTSC's 29.97
    # frames a second too, whose first second ends on no whole frame)
    monkeypatch.setattr(synth, "AVI_MAX_BYTES", int(48 * per_frame))
    with pytest.raises(ValueError, match="OpenCV's AVI writer can hold: fly fewer seconds"):
        synth.generate("orbit", tmp_path / "early", width=320, height=180, seconds=4.0, fps=29.97)
    assert 30 <= frames_in(tmp_path / "early" / "video.avi") < 48
    # room for 108: within the first second's guess, so found when the file outgrows it
    monkeypatch.setattr(synth, "AVI_MAX_BYTES", int(108 * per_frame))
    with pytest.raises(ValueError, match=r"about 0\.0 GB, more than"):
        synth.generate("orbit", tmp_path / "late", width=320, height=180, seconds=4.0)
    assert 90 <= frames_in(tmp_path / "late" / "video.avi") < 120
    # the CLI: one line, exit 2
    with pytest.raises(SystemExit) as exited:
        synth.main(["--flight", "orbit", "--out", str(tmp_path / "cli"), "--width", "320",
                    "--height", "180", "--seconds", "4"])  # fmt: skip
    assert exited.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "s fit at 320x180) or a smaller image" in err[-1], err
