"""Geotagged keyframes: telemetry from a tlog or a live (fake) autopilot, tags read back
with exiftool and compared with the synthetic flight's ground truth."""

from __future__ import annotations

import copy
import csv
import json
import math
import os
import shutil
import socket
import struct
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fake_autopilot import (
    FakeAutopilot,
    Message,
    Noise,
    TlogRecord,
    autopilot_fixture,
    read_tlog,
    with_noise,
    write_tlog,
)
from flights import flight
from keyframed import synth
from ports import free_port
from pymavlink.dialects.v20 import common as mav2

fake_autopilot = autopilot_fixture()

M_PER_DEG = 111_320.0
EXIFTOOL = shutil.which("exiftool")
needs_exiftool = pytest.mark.skipif(
    EXIFTOOL is None, reason="exiftool not installed (Debian libimage-exiftool-perl)"
)


@pytest.fixture(scope="module")
def short_nadir() -> Path:
    return flight("nadir", width=480, height=270, seconds=8.0)


def run_select(kf_bin: Path, fl: Path, out: Path, *extra: str, timeout: float = 120) -> Any:
    cmd = [str(kf_bin), "select", str(fl / "video.avi"), "--out", str(out), "--quiet", *extra]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)


def exif(files: list[Path]) -> dict[str, dict[str, Any]]:
    assert EXIFTOOL is not None
    res = subprocess.run(
        [EXIFTOOL, "-n", "-j", "-G1", "-a", *map(str, files)],
        capture_output=True,
        text=True,
        check=True,
    )
    return {Path(d["SourceFile"]).name: d for d in json.loads(res.stdout)}


def keyframes(out: Path) -> list[dict[str, str]]:
    with (out / "keyframes.csv").open() as fh:
        return list(csv.DictReader(fh))


def decisions(out: Path) -> dict[int, dict[str, str]]:
    with (out / "decisions.csv").open() as fh:
        return {int(r["index"]): r for r in csv.DictReader(fh)}


def pix4d_to_r_ned_cam(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """Pix4D's camera Yaw/Pitch/Roll (degrees) -> R_ned_cam: the Z-Y-X angles of a body
    carrying a nadir camera whose image top points at the body's nose."""
    y, p, r = (math.radians(v) for v in (yaw, pitch, roll))
    rz = np.array([[math.cos(y), -math.sin(y), 0], [math.sin(y), math.cos(y), 0], [0, 0, 1]])
    ry = np.array([[math.cos(p), 0, math.sin(p)], [0, 1, 0], [-math.sin(p), 0, math.cos(p)]])
    rx = np.array([[1, 0, 0], [0, math.cos(r), -math.sin(r)], [0, math.sin(r), math.cos(r)]])
    b = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    return rz @ ry @ rx @ b


def rotation_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    c = (np.trace(a.T @ b) - 1.0) / 2.0
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


class Truth:
    """The flight's exact pose at any flight time (seconds from frame 0)."""

    def __init__(self, fl: Path) -> None:
        meta = json.loads((fl / "meta.json").read_text())
        self.plan = synth._plan(meta["flight"], meta["seconds"], meta["seed"])
        self.epoch_us = meta["epoch_unix_s"] * 1_000_000

    def at(self, t: float) -> tuple[float, float, float, np.ndarray]:
        pos, r_wc, _ = self.plan.camera(np.array([t]))
        lat, lon, alt = synth.enu_to_geodetic(pos[:, 0], pos[:, 1], pos[:, 2])
        t_ned_enu = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
        return float(lat[0]), float(lon[0]), float(alt[0]), t_ned_enu @ r_wc[0]


def tag_errors(tags: dict[str, Any], truth: tuple[float, float, float, np.ndarray]) -> tuple:
    lat, lon, alt, r_ned_cam = truth
    d_n = (tags["Composite:GPSLatitude"] - lat) * M_PER_DEG
    d_e = (tags["Composite:GPSLongitude"] - lon) * M_PER_DEG * math.cos(math.radians(lat))
    sign = -1.0 if tags["GPS:GPSAltitudeRef"] == 1 else 1.0
    d_u = sign * tags["GPS:GPSAltitude"] - alt
    r = pix4d_to_r_ned_cam(
        tags["XMP-Camera:Yaw"], tags["XMP-Camera:Pitch"], tags["XMP-Camera:Roll"]
    )
    return math.hypot(d_n, d_e), abs(d_u), rotation_angle_deg(r, r_ned_cam)


def utc_us_of(tags: dict[str, Any]) -> float:
    from datetime import UTC, datetime

    dt = datetime.strptime(tags["ExifIFD:DateTimeOriginal"], "%Y:%m:%d %H:%M:%S")
    sub = str(tags["ExifIFD:SubSecTimeOriginal"])
    return dt.replace(tzinfo=UTC).timestamp() * 1e6 + int(sub) * 10 ** (6 - len(sub))


@needs_exiftool
def test_tlog_tags_match_ground_truth(kf_bin: Path, short_nadir: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    r = run_select(
        kf_bin,
        short_nadir,
        out,
        "--telemetry",
        str(short_nadir / "flight.tlog"),
        "--video-start",
        "2026-06-01T10:00:00Z",
        "--calibration",
        str(short_nadir / "intrinsics.json"),
    )
    assert r.returncode == 0, r.stderr
    kfs = keyframes(out)
    assert len(kfs) >= 5
    tags = exif([out / k["file"] for k in kfs])
    truth = Truth(short_nadir)
    intr = json.loads((short_nadir / "intrinsics.json").read_text())
    fps = intr["fps"]
    worst = [0.0, 0.0, 0.0]
    for k in kfs:
        t = tags[k["file"]]
        idx = int(k["index"])
        errs = tag_errors(t, truth.at(idx / fps))
        worst = [max(a, b) for a, b in zip(worst, errs, strict=True)]
        assert abs(utc_us_of(t) - (truth.epoch_us + idx / fps * 1e6)) <= 1000
        # intrinsics.json names no camera: no Make or Model is made up
        assert "IFD0:Make" not in t and "IFD0:Model" not in t, t
        assert t["ExifIFD:FocalLength"] == pytest.approx(intr["focal_length_mm"], abs=1e-3)
        assert t["ExifIFD:FocalLengthIn35mmFormat"] == round(intr["fx"] * 36 / intr["width"])
        assert t["XMP-Camera:PerspectiveFocalLength"] == pytest.approx(
            intr["focal_length_mm"], rel=1e-5
        )
        # a 3D fix: PDOP from the autopilot's HDOP 0.8 and VDOP 1.2
        assert t["GPS:GPSDOP"] == pytest.approx(math.hypot(0.8, 1.2), abs=1e-3)
        assert str(t["GPS:GPSSatellites"]) == "14"  # the flight's GPS_RAW_INT says 14
        assert t["XMP-Camera:GPSXYAccuracy"] == pytest.approx(0.8)
        assert decisions(out)[idx]["geotag"] == "ok"
    print(
        f"tlog tags vs truth, max: horizontal {worst[0]:.4f} m, vertical {worst[1]:.4f} m, "
        f"attitude {worst[2]:.4f} deg"
    )
    # Telemetry is quantised to 1e-7 degrees (1 cm) and 1 mm: 0.1 m and 0.2 degrees is
    # far above that and far below any interpolation or clock mistake.
    assert worst[0] < 0.1, f"horizontal error {worst[0]:.3f} m"
    assert worst[1] < 0.1, f"vertical error {worst[1]:.3f} m"
    assert worst[2] < 0.2, f"attitude error {worst[2]:.3f} deg"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["telemetry"]["geotagged"] == len(kfs)
    assert summary["telemetry"]["truncated"] is False


def tag_errors_with_tlog(
    kf_bin: Path, fl: Path, tlog: Path, out: Path, *extra: str, video_start: float | None = None
) -> np.ndarray:
    """`select` on the flight's video with `tlog` as telemetry: every keyframe tagged
    (at least five); their tag errors against the ground truth (horizontal m,
    vertical m, attitude deg), one row each."""
    r = run_select(
        kf_bin,
        fl,
        out,
        "--telemetry",
        str(tlog),
        "--video-start",
        str(synth.EPOCH_UNIX_S if video_start is None else video_start),
        "--calibration",
        str(fl / "intrinsics.json"),
        *extra,
    )
    assert r.returncode == 0, r.stderr
    kfs = keyframes(out)
    assert len(kfs) >= 5
    assert all(k["geotag"] == "ok" for k in kfs), kfs
    tags = exif([out / k["file"] for k in kfs])
    truth = Truth(fl)
    fps = json.loads((fl / "intrinsics.json").read_text())["fps"]
    return np.array([tag_errors(tags[k["file"]], truth.at(int(k["index"]) / fps)) for k in kfs])


@needs_exiftool
def test_noisy_tlog_errors_stay_at_the_noise_level(
    kf_bin: Path, short_nadir: Path, tmp_path: Path
) -> None:
    """The flight's tlog with the fake autopilot's noise on attitude and position: the
    tags are off by about the injected noise, no more (and, so the noise is known to be
    there, not much less)."""
    noise = Noise(attitude_deg=0.5, position_m=0.5, altitude_m=0.3)
    tlog = tmp_path / "noisy.tlog"
    write_tlog(tlog, with_noise(read_tlog(short_nadir / "flight.tlog"), noise, seed=4))
    out = tmp_path / "out"
    errs = tag_errors_with_tlog(kf_bin, short_nadir, tlog, out)
    assert_at_noise_level(errs, noise, "noisy tlog")


@needs_exiftool
def test_time_offset_corrects_a_late_camera(
    kf_bin: Path, short_nadir: Path, tmp_path: Path
) -> None:
    """A camera that stamps its frames 120 ms after the exposure (an end-of-frame
    timestamp and transfer): the geotags land that far along the track; with
    --time-offset -120 (camera.time_offset_ms) they are back on the truth, and
    keyframes.csv's time is the instant tagged."""
    late_s = 0.12
    tlog = short_nadir / "flight.tlog"
    start = synth.EPOCH_UNIX_S + late_s
    late = tag_errors_with_tlog(kf_bin, short_nadir, tlog, tmp_path / "late", video_start=start)
    fixed = tag_errors_with_tlog(
        kf_bin,
        short_nadir,
        tlog,
        tmp_path / "fixed",
        "--time-offset",
        str(-late_s * 1000),
        video_start=start,
    )
    print(
        f"late camera, median horizontal error: {np.median(late[:, 0]):.3f} m uncorrected, "
        f"{np.median(fixed[:, 0]):.4f} m with --time-offset"
    )
    # The survey flies at several m/s: 120 ms is tens of centimetres.
    assert np.median(late[:, 0]) > 0.3
    assert fixed[:, 0].max() < 0.1 and fixed[:, 1].max() < 0.1 and fixed[:, 2].max() < 0.2
    frame_ns = {int(k["index"]): int(k["time_ns"]) for k in keyframes(tmp_path / "late")}
    for k in keyframes(tmp_path / "fixed"):
        assert int(k["time_ns"]) == frame_ns[int(k["index"])] - 120_000_000


def with_a_long_tail(records: list[Any], tail_s: int, reboot_s: int) -> list[Any]:
    """A ground station's log of a day's flying rather than of one video: the flight's
    records, then the vehicle standing where the flight ended while the log goes on for
    ``tail_s`` seconds (the last second of telemetry again and again), then the
    autopilot rebooted (time_boot_ms from 1 s) for ``reboot_s`` seconds more."""
    end_us = records[-1].unix_us
    last = [r for r in records if r.unix_us > end_us - 1_000_000]
    first_boot_ms = min(r.msg.time_boot_ms for r in last if hasattr(r.msg, "time_boot_ms"))
    out = list(records)
    for k in range(1, tail_s + reboot_s + 1):
        d_us = k * 1_000_000
        for rec in last:
            msg = copy.deepcopy(rec.msg)
            if hasattr(msg, "time_boot_ms"):
                if k <= tail_s:
                    msg.time_boot_ms += k * 1000
                else:
                    msg.time_boot_ms += (k - tail_s) * 1000 - first_boot_ms
            if hasattr(msg, "time_unix_usec"):
                msg.time_unix_usec += d_us
            if msg.get_type() == "GPS_RAW_INT":
                msg.time_usec += d_us
            out.append(type(rec)(rec.unix_us + d_us, msg))
    return out


@needs_exiftool
def test_a_tlog_far_longer_than_the_video_tags_every_keyframe(
    kf_bin: Path, short_nadir: Path, tmp_path: Path
) -> None:
    """The tlog goes on for 2.5 minutes after the video (the pose history the daemon
    keeps in flight is 2 minutes) and the autopilot then reboots: the telemetry reaches
    the selection as the frames go, as it did in flight, so every keyframe is tagged
    with the pose of its own time, not from what is left at the end of the log."""
    records = read_tlog(short_nadir / "flight.tlog")
    long = with_a_long_tail(records, tail_s=150, reboot_s=20)
    tlog = tmp_path / "long.tlog"
    write_tlog(tlog, long)
    out = tmp_path / "out"
    errs = tag_errors_with_tlog(kf_bin, short_nadir, tlog, out)
    worst = errs.max(axis=0)
    assert worst[0] < 0.1 and worst[1] < 0.1 and worst[2] < 0.2, worst
    summary = json.loads((out / "summary.json").read_text())
    kfs = keyframes(out)
    # The whole log was read and counted, the reboot seen.
    assert summary["telemetry"]["messages"] == len(long), summary["telemetry"]
    assert summary["telemetry"]["geotagged"] == len(kfs)
    assert summary["telemetry"]["autopilot_reboots"] == 1, summary["telemetry"]


def assert_at_noise_level(errs: np.ndarray, noise: Noise, what: str) -> None:
    """Tag errors (horizontal m, vertical m, attitude deg per keyframe) of a flight
    with injected noise: at the noise level, no more, and not below it."""
    rms = np.sqrt(np.mean(errs**2, axis=0))
    print(
        f"{what} tags vs truth: RMS horizontal {rms[0]:.3f} m, vertical {rms[1]:.3f} m, "
        f"attitude {rms[2]:.3f} deg; max {errs[:, 0].max():.3f} m, {errs[:, 1].max():.3f} m, "
        f"{errs[:, 2].max():.3f} deg"
    )
    # A horizontal error is two axes of noise, a rotation angle three; interpolating
    # between two noisy samples averages them a little. At the noise level: no more than
    # 1.5 sigma RMS, no gross outlier, and at least a fifth of sigma (the noise did reach
    # the tags).
    sigma = np.array(
        [noise.position_m * math.sqrt(2), noise.altitude_m, noise.attitude_deg * math.sqrt(3)]
    )
    assert np.all(rms < 1.5 * sigma), rms
    assert np.all(rms > 0.2 * sigma), rms
    assert errs[:, 2].max() < 5 * noise.attitude_deg, errs


def rewrite_tlog(src: Path, dst: Path, edit: Any) -> None:
    """Copies a tlog, re-encoding each message after edit(t_unix_us, msg) -> msg."""
    mav = mav2.MAVLink(None, srcSystem=1, srcComponent=1)
    out = bytearray()
    for rec in read_tlog(src):
        msg = edit(rec.unix_us, rec.msg)
        if msg is None:  # dropped
            continue
        mav.seq = msg.get_seq()
        out += struct.pack(">Q", rec.unix_us) + msg.pack(mav)
    dst.write_bytes(bytes(out))


@needs_exiftool
def test_tlog_without_system_time_takes_utc_from_its_records(
    kf_bin: Path, short_nadir: Path, tmp_path: Path
) -> None:
    """No SYSTEM_TIME in the log: the capture time comes from the tlog's own record
    times (the recording station's clock), as docs/formats.md says."""
    tlog = tmp_path / "nosys.tlog"
    rewrite_tlog(
        short_nadir / "flight.tlog",
        tlog,
        lambda _t, m: None if m.get_type() == "SYSTEM_TIME" else m,
    )
    out = tmp_path / "out"
    r = run_select(
        kf_bin,
        short_nadir,
        out,
        "--telemetry",
        str(tlog),
        "--video-start",
        "2026-06-01T10:00:00Z",
        "--calibration",
        str(short_nadir / "intrinsics.json"),
    )
    assert r.returncode == 0, r.stderr
    kfs = keyframes(out)
    assert len(kfs) >= 5
    tags = exif([out / k["file"] for k in kfs])
    truth = Truth(short_nadir)
    fps = json.loads((short_nadir / "intrinsics.json").read_text())["fps"]
    for k in kfs:
        # the generator stamps the records with the flight's own UTC
        assert int(k["utc_us"]) == pytest.approx(
            truth.epoch_us + int(k["index"]) / fps * 1e6, abs=1000
        )
        assert abs(utc_us_of(tags[k["file"]]) - int(k["utc_us"])) <= 1000
        assert tags[k["file"]].get("GPS:GPSTimeStamp") is not None


@needs_exiftool
@pytest.mark.parametrize("station_ahead_s", [2.0, -3.5, 40.0])
def test_a_tlog_recorded_on_a_wrong_clock_is_placed_by_gps_time(
    kf_bin: Path, short_nadir: Path, tmp_path: Path, station_ahead_s: float
) -> None:
    """The ground station that recorded the tlog had its clock seconds off: its record
    times do not place the video (--video-start is UTC), the autopilot's GPS time in
    SYSTEM_TIME does. The tags match the ground truth as with a right clock, and the
    summary and a warning say how far off the station was."""
    tlog = tmp_path / "skewed.tlog"
    shift_us = round(station_ahead_s * 1e6)
    records = read_tlog(short_nadir / "flight.tlog")
    write_tlog(tlog, [TlogRecord(r.unix_us + shift_us, r.msg) for r in records])
    out = tmp_path / "out"
    errs = tag_errors_with_tlog(kf_bin, short_nadir, tlog, out)
    assert errs[:, 0].max() < 0.1 and errs[:, 1].max() < 0.1, errs
    assert errs[:, 2].max() < 0.2, errs
    tel = json.loads((out / "summary.json").read_text())["telemetry"]
    assert tel["clock"] == "system_time"
    # the generator's records carry no latency: the skew is the shift itself
    assert tel["record_clock_ahead_ms"] == pytest.approx(station_ahead_s * 1e3, abs=1.0)
    truth = Truth(short_nadir)
    fps = json.loads((short_nadir / "intrinsics.json").read_text())["fps"]
    for k in keyframes(out):
        assert int(k["utc_us"]) == pytest.approx(
            truth.epoch_us + int(k["index"]) / fps * 1e6, abs=1000
        )


@needs_exiftool
@pytest.mark.parametrize("shift_s", [-3.0, 30.0, 2 * 86400.0])
def test_one_record_time_out_of_line_costs_no_tag(
    kf_bin: Path, short_nadir: Path, tmp_path: Path, shift_s: float
) -> None:
    """One record's time off by seconds or days (a corrupt timestamp; the rest of the
    log on time) would hold every packet after it back, or pull the clock estimate
    away: it is taken as the record's before, said once, and every keyframe is tagged
    as with the clean log."""
    tlog = tmp_path / "one-off.tlog"
    records = read_tlog(short_nadir / "flight.tlog")
    records[100] = TlogRecord(records[100].unix_us + round(shift_s * 1e6), records[100].msg)
    write_tlog(tlog, records)
    out = tmp_path / "out"
    errs = tag_errors_with_tlog(kf_bin, short_nadir, tlog, out)
    assert errs[:, 0].max() < 0.1 and errs[:, 1].max() < 0.1, errs
    assert errs[:, 2].max() < 0.2, errs
    r = run_select(
        kf_bin,
        short_nadir,
        tmp_path / "again",
        *["--telemetry", str(tlog), "--video-start", str(synth.EPOCH_UNIX_S)],
    )
    assert r.stderr.count("1 record time(s) out of line") == 1, r.stderr


def test_a_tlog_naming_no_autopilot_says_to_give_one(
    kf_bin: Path, short_nadir: Path, tmp_path: Path
) -> None:
    """Without a HEARTBEAT no sender is known to fly the vehicle: nothing is followed,
    and the warning says so and what to give, not only "no telemetry"; with
    --autopilot the same log tags every keyframe."""
    tlog = tmp_path / "nohb.tlog"
    write_tlog(tlog, [r for r in read_tlog(short_nadir / "flight.tlog") if r.type != "HEARTBEAT"])
    start = ("--telemetry", str(tlog), "--video-start", str(synth.EPOCH_UNIX_S))
    r = run_select(kf_bin, short_nadir, tmp_path / "o", *start)
    assert r.returncode == 0, r.stderr
    assert "names no autopilot (no HEARTBEAT of one)" in r.stderr, r.stderr
    assert "--autopilot SYS[:COMP]" in r.stderr
    r = run_select(kf_bin, short_nadir, tmp_path / "o2", *start, "--autopilot", "1:1")
    assert r.returncode == 0, r.stderr
    kfs = keyframes(tmp_path / "o2")
    assert kfs and all(k["geotag"] == "ok" for k in kfs), [k["geotag"] for k in kfs]
    # An --autopilot the log does not have: said so, not "give --autopilot".
    r = run_select(kf_bin, short_nadir, tmp_path / "o3", *start, "--autopilot", "7")
    assert r.returncode == 0, r.stderr
    assert "the tlog has no autopilot 7 (--autopilot)" in r.stderr, r.stderr
    assert "give --autopilot" not in r.stderr, r.stderr


@needs_exiftool
def test_no_fix_means_no_gps_tags_and_the_decision_says_why(
    kf_bin: Path, short_nadir: Path, tmp_path: Path
) -> None:
    epoch_us = synth.EPOCH_UNIX_S * 1_000_000
    lost0, lost1 = epoch_us + 3_000_000, epoch_us + 5_500_000  # no fix from 3.0 s to 5.5 s

    def edit(t: int, msg: Any) -> Any:
        if msg.get_type() == "GPS_RAW_INT" and lost0 <= t < lost1:
            msg.fix_type = 1
        return msg

    tlog = tmp_path / "nofix.tlog"
    rewrite_tlog(short_nadir / "flight.tlog", tlog, edit)
    out = tmp_path / "out"
    r = run_select(
        kf_bin, short_nadir, out, "--telemetry", str(tlog), "--video-start", str(synth.EPOCH_UNIX_S)
    )
    assert r.returncode == 0, r.stderr
    assert "no --calibration" in r.stderr
    kfs = keyframes(out)
    tags = exif([out / k["file"] for k in kfs])
    dec = decisions(out)
    inside = outside = 0
    for k in kfs:
        idx = int(k["index"])
        t_us = epoch_us + idx / 30.0 * 1e6
        t = tags[k["file"]]
        # GPS_RAW_INT comes at 5 Hz: allow its 0.2 s period at each edge.
        if lost0 + 200_000 <= t_us < lost1:
            inside += 1
            assert not any(key.startswith("GPS:") for key in t), k["file"]
            assert "no GPS fix" in dec[idx]["geotag"]
            assert "XMP-Camera:Yaw" in t, "attitude does not need a fix"
        elif t_us < lost0 - 200_000 or t_us >= lost1 + 200_000:
            outside += 1
            assert "GPS:GPSLatitude" in t
            assert dec[idx]["geotag"] == "ok"
        # without calibration: no intrinsics are invented
        assert "XMP-Camera:PerspectiveFocalLength" not in t
        assert "ExifIFD:FocalLength" not in t
    assert inside >= 1 and outside >= 2, (inside, outside)


@needs_exiftool
def test_nan_and_zero_attitudes_are_counted_not_used(
    kf_bin: Path, short_nadir: Path, tmp_path: Path
) -> None:
    """An autopilot whose estimator hands out NaN angles and zero quaternions for a
    while (a reset, a bad IMU): those samples are counted, and keyframes then carry
    no attitude rather than "level, facing north"."""
    epoch_us = synth.EPOCH_UNIX_S * 1_000_000
    bad0, bad1 = epoch_us + 3_000_000, epoch_us + 5_500_000

    def edit(t: int, msg: Any) -> Any:
        if bad0 <= t < bad1:
            if msg.get_type() == "ATTITUDE":
                msg.roll = float("nan")
            elif msg.get_type() == "ATTITUDE_QUATERNION":
                msg.q1 = msg.q2 = msg.q3 = msg.q4 = 0.0
        return msg

    tlog = tmp_path / "badatt.tlog"
    rewrite_tlog(short_nadir / "flight.tlog", tlog, edit)
    out = tmp_path / "out"
    r = run_select(
        kf_bin, short_nadir, out, "--telemetry", str(tlog), "--video-start", str(synth.EPOCH_UNIX_S)
    )
    assert r.returncode == 0, r.stderr
    summary = json.loads((out / "summary.json").read_text())
    # both streams, 2.5 s of them, are refused (the tlog sends each at tens of Hz)
    assert summary["telemetry"]["bad_samples"] >= 100, summary["telemetry"]
    kfs = keyframes(out)
    tags = exif([out / k["file"] for k in kfs])
    dec = decisions(out)
    inside = outside = 0
    for k in kfs:
        idx = int(k["index"])
        t_us = epoch_us + idx / 30.0 * 1e6
        t = tags[k["file"]]
        if bad0 + 300_000 <= t_us < bad1 - 300_000:
            inside += 1
            assert "XMP-Camera:Yaw" not in t, k["file"]
            assert "attitude" in dec[idx]["geotag"], dec[idx]
            assert "GPS:GPSLatitude" in t, "the position does not need the attitude"
        elif t_us < bad0 - 300_000 or t_us >= bad1 + 300_000:
            outside += 1
            assert "XMP-Camera:Yaw" in t and dec[idx]["geotag"] == "ok", dec[idx]
    assert inside >= 1 and outside >= 2, (inside, outside)


def test_truncated_tlog_tags_what_it_covers(
    kf_bin: Path, short_nadir: Path, tmp_path: Path
) -> None:
    data = (short_nadir / "flight.tlog").read_bytes()
    cut = tmp_path / "cut.tlog"
    cut.write_bytes(data[: len(data) // 2 + 13])  # mid-packet, around 3 s into the video
    out = tmp_path / "out"
    r = run_select(
        kf_bin,
        short_nadir,
        out,
        "--telemetry",
        f"tlog:{cut}",
        "--video-start",
        "2026-06-01T10:00:00.000Z",
    )
    assert r.returncode == 0, r.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["telemetry"]["truncated"] is True
    kfs = keyframes(out)
    tagged = [k for k in kfs if k["geotag"] == "ok"]
    stale = [k for k in kfs if k["geotag"] != "ok"]
    assert tagged and stale
    assert max(int(k["index"]) for k in tagged) < min(int(k["index"]) for k in stale)
    assert all("stale" in k["geotag"] for k in stale)
    assert all(k["lat"] == "" for k in stale)


def test_garbage_inside_a_tlog_is_counted_and_skipped(
    kf_bin: Path, short_nadir: Path, tmp_path: Path
) -> None:
    """A tlog with a run of garbage between two records and one record whose packet
    was damaged: the garbage is counted as skipped bytes, the damaged packet as a
    rejected frame, and every keyframe is still tagged from the records around them."""
    data = bytearray((short_nadir / "flight.tlog").read_bytes())
    records = [r for r in read_tlog_offsets(bytes(data))]
    at = records[len(records) // 3]  # a record boundary about 2 s in
    garbage = bytes([0x55, 0xAA]) * 2500  # no STX byte, no plausible timestamp
    hit = records[2 * len(records) // 3]
    data[hit + 8 + 6] ^= 0xFF  # a byte inside the packet after the cut: its CRC fails
    bad = tmp_path / "garbage.tlog"
    bad.write_bytes(bytes(data[:at]) + garbage + bytes(data[at:]))
    out = tmp_path / "out"
    r = run_select(
        kf_bin,
        short_nadir,
        out,
        "--telemetry",
        f"tlog:{bad}",
        "--video-start",
        "2026-06-01T10:00:00.000Z",
    )
    assert r.returncode == 0, r.stderr
    telemetry = json.loads((out / "summary.json").read_text())["telemetry"]
    assert telemetry["skipped_bytes"] == len(garbage)
    assert telemetry["rejected_frames"] >= 1
    assert telemetry["truncated"] is False
    kfs = keyframes(out)
    assert kfs and all(k["geotag"] == "ok" for k in kfs), [k["geotag"] for k in kfs]


def read_tlog_offsets(data: bytes) -> list[int]:
    """Byte offsets of a well-formed tlog's records (8-byte time, then one packet)."""
    offsets, at = [], 0
    while at + 10 <= len(data):
        offsets.append(at)
        stx, length = data[at + 8], data[at + 9]
        if stx == 0xFE:
            size = 6 + length + 2
        else:
            size = 10 + length + 2 + (13 if data[at + 10] & 0x01 else 0)
        at += 8 + size
    assert at == len(data), "not a well-formed tlog"
    return offsets


def test_a_video_start_outside_the_tlog_is_an_error(
    kf_bin: Path, short_nadir: Path, tmp_path: Path
) -> None:
    """Local time given for UTC (here two hours off): the tlog does not cover the video,
    no keyframe can be tagged. The keyframes are written all the same, and the run
    fails naming both spans, rather than exit 0 with nothing geotagged."""
    out = tmp_path / "out"
    r = run_select(
        kf_bin,
        short_nadir,
        out,
        "--telemetry",
        str(short_nadir / "flight.tlog"),
        "--video-start",
        "2026-06-01T12:00:00",
    )
    assert r.returncode == 3, r.stderr
    assert "lies outside the tlog's telemetry" in r.stderr, r.stderr
    assert "(2026-06-01T12:00:00.000Z to" in r.stderr, r.stderr
    kfs = keyframes(out)
    assert kfs and all(k["geotag"] != "ok" for k in kfs)
    assert all((out / k["file"]).is_file() for k in kfs)
    summary = json.loads((out / "summary.json").read_text())
    assert "outside the tlog" in summary["error"]
    # The right start: the same command tags them.
    r = run_select(
        kf_bin,
        short_nadir,
        tmp_path / "right",
        "--telemetry",
        str(short_nadir / "flight.tlog"),
        "--video-start",
        "2026-06-01T10:00:00",
    )
    assert r.returncode == 0, r.stderr
    assert all(k["geotag"] == "ok" for k in keyframes(tmp_path / "right"))


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--telemetry", "tcp:1.2.3.4:5"], "unknown scheme"),
        (["--telemetry", "serial:/dev/ttyS0:1234"], "baud"),
        (["--video-start", "yesterday"], "UTC time"),
        (["--mount", "0,-90"], "ROLL,PITCH,YAW"),
        (["--autopilot", "300"], "SYS[:COMP]"),
    ],
)
def test_bad_telemetry_options(
    any_bin: Path, short_nadir: Path, tmp_path: Path, args: list[str], message: str
) -> None:
    r = run_select(any_bin, short_nadir, tmp_path / "o", *args)
    assert r.returncode == 2
    assert message in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda p: p.write_bytes(b""), "not a MAVLink tlog"),
        (lambda p: p.write_bytes(np.random.default_rng(1).bytes(50_000)), "not a MAVLink tlog"),
        (lambda p: None, "cannot open"),
        # no writer will come: refused, not waited for past any signal
        (lambda p: os.mkfifo(p), "is not a regular file"),
        (lambda p: p.mkdir(), "is not a regular file"),
    ],
)
def test_bad_tlog_files(
    any_bin: Path, short_nadir: Path, tmp_path: Path, make: Any, message: str
) -> None:
    tlog = tmp_path / "bad.tlog"
    make(tlog)
    r = run_select(
        any_bin, short_nadir, tmp_path / "o", "--telemetry", str(tlog), "--video-start", "0"
    )
    assert r.returncode == 3, r.stderr
    assert message in r.stderr


def test_bad_calibration_file(any_bin: Path, short_nadir: Path, tmp_path: Path) -> None:
    cal = tmp_path / "cal.yaml"
    cal.write_text("%YAML:1.0\ncamera_matrix: [1, 2\n")
    r = run_select(any_bin, short_nadir, tmp_path / "o", "--calibration", str(cal))
    assert r.returncode == 3
    assert "cal.yaml" in r.stderr


# ----------------------------------------------------------------------- live telemetry


def live_run(
    kf_bin: Path,
    fl: Path,
    tmp_path: Path,
    ap: FakeAutopilot,
    *extra: str,
    during: Any = None,
) -> tuple[Path, Any]:
    out = tmp_path / "live"
    ap.start()
    proc = subprocess.Popen(
        [
            str(kf_bin),
            "select",
            str(fl / "video.avi"),
            "--out",
            str(out),
            "--quiet",
            "--telemetry",
            f"udpout:127.0.0.1:{ap.port}",
            "--calibration",
            str(fl / "intrinsics.json"),
            *extra,
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    if during is not None:
        during(ap, proc)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 0, stderr
    return out, stderr


def check_live_tags(
    fl: Path, out: Path, ap: FakeAutopilot, utc_tolerance_us: float = 5_000, utc_first: bool = True
) -> list[tuple[float, float, float]]:
    """Errors of each keyframe's tags against the truth at the instant it was captured
    (its monotonic timestamp, mapped through the autopilot's replay clock).
    ``utc_first`` False: the first keyframe may come before SYSTEM_TIME (1 Hz) has, and
    then carries no capture time rather than a made-up one."""
    truth = Truth(fl)
    kfs = keyframes(out)
    assert len(kfs) >= 5
    tags = exif([out / k["file"] for k in kfs])
    errs = []
    for n, k in enumerate(kfs):
        assert k["geotag"] == "ok", (k["index"], k["geotag"], n, k)
        flight_t = (ap.unix_us_at_monotonic_ns(int(k["time_ns"])) - truth.epoch_us) / 1e6
        errs.append(tag_errors(tags[k["file"]], truth.at(flight_t)))
        if n == 0 and not utc_first and "ExifIFD:DateTimeOriginal" not in tags[k["file"]]:
            continue
        # UTC comes from SYSTEM_TIME through the same clock mapping
        utc_error_us = utc_us_of(tags[k["file"]]) - (truth.epoch_us + flight_t * 1e6)
        assert abs(utc_error_us) < utc_tolerance_us, (k, utc_error_us)
    e = np.array(errs)
    print(
        f"live tags vs truth, max: horizontal {e[:, 0].max():.3f} m, "
        f"vertical {e[:, 1].max():.3f} m, attitude {e[:, 2].max():.3f} deg"
    )
    return errs


def quat_to_matrix(q: Any) -> np.ndarray:
    w, x, y, z = (float(v) for v in q)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


# MAVLink's camera axes (x optical axis, y right, z image down) in OpenCV's (x right,
# y down, z optical axis): R_ned_mavcam = R_ned_cvcam @ MAV_IN_CV.
MAV_IN_CV = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])


CAPTURE_FIELDS = (
    "time_utc",
    "camera_id",
    "lat",
    "lon",
    "alt",
    "relative_alt",
    "q",
    "image_index",
    "capture_result",
    "file_url",
)


def check_captures(fl: Path, out: Path, ap: FakeAutopilot, resent: tuple[int, ...] = ()) -> None:
    """One CAMERA_IMAGE_CAPTURED per keyframe, with the keyframe's position, altitudes,
    UTC, and the camera attitude in MAVLink's camera frame (identity: looking north,
    level), checked against the flight's truth; a second one only for the image
    indices in ``resent`` (re-requested), the same as the first."""
    truth = Truth(fl)
    kfs = keyframes(out)
    caps: list[Message] = []
    again: list[Message] = []
    for c in ap.received("CAMERA_IMAGE_CAPTURED"):
        (again if any(o.image_index == c.image_index for o in caps) else caps).append(c)
    assert [c.image_index for c in caps] == list(range(len(kfs)))
    assert sorted(c.image_index for c in again) == sorted(resent)
    for c in again:
        first = caps[c.image_index]
        assert [getattr(c, f) for f in CAPTURE_FIELDS] == [
            getattr(first, f) for f in CAPTURE_FIELDS
        ]
        # the frame time on the autopilot's clock, through the clock mapping of now
        assert abs(c.time_boot_ms - first.time_boot_ms) <= 5
    pitch_down = quat_to_matrix((math.cos(math.pi / 4), 0.0, -math.sin(math.pi / 4), 0.0))
    for c, k in zip(caps, kfs, strict=True):
        # (the CSV's 9 decimals can end in 5: a tie that C++ and Python round apart)
        assert abs(c.lat - float(k["lat"]) * 1e7) <= 0.5 + 1e-6
        assert abs(c.lon - float(k["lon"]) * 1e7) <= 0.5 + 1e-6
        assert abs(c.alt - float(k["alt_amsl"]) * 1e3) <= 1.0
        assert abs(c.relative_alt - float(k["alt_rel"]) * 1e3) <= 1.0
        assert c.time_utc == int(k["utc_us"])
        assert c.file_url.endswith(k["file"])
        assert c.capture_result == 1
        assert c.camera_id == 0
        r_mav = quat_to_matrix(c.q)
        flight_t = (ap.unix_us_at_monotonic_ns(int(k["time_ns"])) - truth.epoch_us) / 1e6
        r_truth = truth.at(flight_t)[3] @ MAV_IN_CV
        assert rotation_angle_deg(r_mav, r_truth) < 0.2, (k["file"], c.q)
        # A nadir camera: its optical axis (MAVLink x) points down, and the attitude is
        # the 90 degree pitch-down rotation turned by the heading (north: exactly it),
        # up to the vehicle's tilt (under 20 degrees while it speeds up and brakes).
        assert r_mav[2, 0] > math.cos(math.radians(20.0)), c.q
        heading = math.atan2(r_mav[1, 2], r_mav[0, 2]) + math.pi  # image top (-z) forward
        rz = np.array(
            [
                [math.cos(heading), -math.sin(heading), 0.0],
                [math.sin(heading), math.cos(heading), 0.0],
                [0.0, 0.0, 1.0],
            ]
        )
        assert rotation_angle_deg(r_mav, rz @ pitch_down) < 20.0, c.q


# Live, every keyframe within 3 cm (the issue asks 0.1 m; 1-6 mm is usual here): the
# first one too, which waits for a settled clock estimate (it used to be tagged with
# the latency of the first few messages, 2-11 cm off).
LIVE_HORIZONTAL_M = 0.03


def true_clock_offset_ms(ap: FakeAutopilot) -> float:
    """local - autopilot, from the replay's own clock."""
    boot_ms = 500_000.0
    return (ap.monotonic_ns_for_boot_ms(boot_ms) - boot_ms * 1e6) / 1e6


@needs_exiftool
def test_live_udp_autopilot_with_clock_offset(
    kf_bin: Path, short_nadir: Path, tmp_path: Path, fake_autopilot: Any
) -> None:
    """TIMESYNC pins the clock, though a ground station on the link answers every
    request first with its own clock, an hour off."""
    ap = fake_autopilot(short_nadir / "flight.tlog", boot_offset_ms=1_234_567, rogue_timesync=True)

    def during(ap: FakeAutopilot, proc: Any) -> None:
        # The ground station asks the camera who it is.
        ap.wait_for("HEARTBEAT", timeout=10)
        ap.request_message(mav2.MAVLINK_MSG_ID_CAMERA_INFORMATION)
        # It missed the second capture report and asks for it again (param2: the image
        # index, param3 0: that one only), then for one never taken.
        ap.wait_for("CAMERA_IMAGE_CAPTURED", 2, timeout=10)
        ap.request_message(mav2.MAVLINK_MSG_ID_CAMERA_IMAGE_CAPTURED, 1, 0)
        ap.request_message(mav2.MAVLINK_MSG_ID_CAMERA_IMAGE_CAPTURED, 500, 0)

    out, log = live_run(kf_bin, short_nadir, tmp_path, ap, "--model", "Survey cam 2", during=during)
    errs = check_live_tags(short_nadir, out, ap)
    assert max(e[0] for e in errs) < LIVE_HORIZONTAL_M, errs
    assert max(e[1] for e in errs) < 0.1, errs
    assert max(e[2] for e in errs) < 0.2, errs

    summary = json.loads((out / "summary.json").read_text())
    tel = summary["telemetry"]
    assert ap.rogue_answers > 0
    assert tel["clock"] == "timesync"
    error_ms = tel["clock_offset_ms"] - true_clock_offset_ms(ap)
    print(f"TIMESYNC clock offset error {error_ms:.3f} ms")
    assert abs(error_ms) < 5.0
    # the daemon's log says where its clock came from
    assert "following the autopilot at system 1 component 1" in log, log
    assert "autopilot clock: timesync, offset" in log, log

    # The MAVLink camera protocol: who we are, and one capture per keyframe.
    info = ap.wait_for("CAMERA_INFORMATION", timeout=5)[0]
    intr = json.loads((short_nadir / "intrinsics.json").read_text())
    assert info.focal_length == pytest.approx(intr["focal_length_mm"], rel=1e-5)
    assert info.sensor_size_h == pytest.approx(intr["sensor_width_mm"], rel=1e-5)
    assert info.resolution_h == 480
    # named as the keyframes' EXIF names the camera (--model over the calibration's)
    model_name = bytes(info.model_name).rstrip(b"\0").decode()
    assert model_name == "Survey cam 2"
    first = keyframes(out)[0]["file"]
    assert exif([out / first])[first]["IFD0:Model"] == model_name
    assert info.flags & mav2.CAMERA_CAP_FLAGS_CAPTURE_IMAGE
    acks = [m for m in ap.received("COMMAND_ACK") if m.command == 512]
    # CAMERA_INFORMATION and the resent capture accepted, the unknown one failed
    assert [a.result for a in acks] == [
        mav2.MAV_RESULT_ACCEPTED,
        mav2.MAV_RESULT_ACCEPTED,
        mav2.MAV_RESULT_FAILED,
    ]
    check_captures(short_nadir, out, ap, resent=(1,))
    assert tel["captures_resent"] == 1 and tel["captures_sent"] == len(keyframes(out)), tel
    assert tel["captures_pending"] == 0 and tel["captures_dropped"] == 0, tel
    hb = ap.received("HEARTBEAT")
    assert hb and hb[0].type == mav2.MAV_TYPE_CAMERA
    assert hb[0].get_srcComponent() == mav2.MAV_COMP_ID_CAMERA
    # it asked the autopilot for its stream rates once (acknowledged: not again)
    assert ap.message_intervals == {
        mav2.MAVLINK_MSG_ID_ATTITUDE: 50_000,
        mav2.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 50_000,
        mav2.MAVLINK_MSG_ID_GPS_RAW_INT: 200_000,
        mav2.MAVLINK_MSG_ID_SYSTEM_TIME: 1_000_000,
    }
    rate_cmds = [m for m in ap.received("COMMAND_LONG") if m.command == 511]
    assert len(rate_cmds) == 4, rate_cmds
    assert "asked the autopilot for attitude and position at 20 Hz" in log, log


@needs_exiftool
def test_live_udp_autopilot_without_timesync(
    kf_bin: Path, short_nadir: Path, tmp_path: Path, fake_autopilot: Any
) -> None:
    """An autopilot that does not answer TIMESYNC: the clock comes from the arrival
    times alone, and the tags are as good."""
    ap = fake_autopilot(
        short_nadir / "flight.tlog", boot_offset_ms=1_234_567, answer_timesync=False
    )

    def during(ap: FakeAutopilot, proc: Any) -> None:
        # The ground station asks for three photographs 0.3 s apart (interval capture),
        # then how many images the camera has taken.
        ap.wait_for("CAMERA_IMAGE_CAPTURED", 1, timeout=10)
        ap.command(mav2.MAV_CMD_IMAGE_START_CAPTURE, 0, 0.3, 3, 0)
        ap.wait_for("CAMERA_IMAGE_CAPTURED", 4, timeout=10)
        ap.request_message(mav2.MAVLINK_MSG_ID_CAMERA_CAPTURE_STATUS)

    out, log = live_run(kf_bin, short_nadir, tmp_path, ap, during=during)
    errs = check_live_tags(short_nadir, out, ap)
    assert max(e[0] for e in errs) < LIVE_HORIZONTAL_M, errs
    assert max(e[1] for e in errs) < 0.1, errs
    assert max(e[2] for e in errs) < 0.2, errs
    tel = json.loads((out / "summary.json").read_text())["telemetry"]
    assert ap.received("TIMESYNC"), "the daemon asked"
    assert tel["clock"] == "arrival"
    # the smallest latency seen on loopback, plus time_boot_ms's millisecond steps
    error_ms = tel["clock_offset_ms"] - true_clock_offset_ms(ap)
    print(f"arrival clock offset error {error_ms:.3f} ms")
    assert abs(error_ms) < 5.0
    assert "autopilot clock: arrival, offset" in log, log
    assert "autopilot clock: timesync" not in log, log
    check_captures(short_nadir, out, ap)

    # The interval capture: accepted, three ticks, each an image asked of the selector
    # and served by the next sharp frame (a keyframe due anyway serves one too), or
    # skipped while the one before still waited for a sharp frame.
    acks = [m for m in ap.received("COMMAND_ACK") if m.command == mav2.MAV_CMD_IMAGE_START_CAPTURE]
    assert [a.result for a in acks] == [mav2.MAV_RESULT_ACCEPTED]
    assert tel["captures_requested"] + tel["captures_refused"] == 3, tel
    assert tel["captures_requested"] >= 2, tel
    assert tel["captures_unserved"] == 0, tel  # each served within the flight
    (status,) = ap.wait_for("CAMERA_CAPTURE_STATUS", timeout=5)
    assert status.image_count >= 4 and status.image_status in (0, 3), status
    asked_ns = [
        r.monotonic_ns
        for r in ap.sent("COMMAND_LONG")
        if r.msg.command == mav2.MAV_CMD_IMAGE_START_CAPTURE
    ][0]
    rows = decisions(out)
    commanded = [k for k in keyframes(out) if rows[int(k["index"])]["reason"] == "commanded"]
    assert commanded, "no keyframe was taken for the requests"
    for k in commanded:
        # (a frame read just before the request may serve it)
        assert asked_ns - 0.5e9 <= int(k["time_ns"]) <= asked_ns + 0.6e9 + 1.2e9, k
    assert "interval capture requested by system 1 component 1" in log, log


@needs_exiftool
def test_live_udp_autopilot_with_noise(
    kf_bin: Path, short_nadir: Path, tmp_path: Path, fake_autopilot: Any
) -> None:
    noise = Noise(attitude_deg=0.5, position_m=0.5, altitude_m=0.3)
    ap = fake_autopilot(
        short_nadir / "flight.tlog", noise=noise, seed=4, mavlink1=True, boot_offset_ms=2_345_678
    )
    out, log = live_run(kf_bin, short_nadir, tmp_path, ap)
    assert_at_noise_level(np.array(check_live_tags(short_nadir, out, ap)), noise, "noisy live")
    # Noise on the values, not on the clock: the mapping is as exact as without it.
    tel = json.loads((out / "summary.json").read_text())["telemetry"]
    error_ms = tel["clock_offset_ms"] - true_clock_offset_ms(ap)
    print(f"noisy link: clock offset error {error_ms:.3f} ms ({tel['clock']})")
    assert abs(error_ms) < 5.0
    # This autopilot reads MAVLink 1 only: the camera heard it, went over to MAVLink 1
    # after 3 s, and its TIMESYNC requests were answered from then on.
    assert "the autopilot speaks MAVLink 1 only: sending MAVLink 1 too" in log, log
    assert ap.ignored_v2 > 0
    assert tel["clock"] == "timesync"
    assert ap.received("HEARTBEAT")[-1].get_msgbuf()[:1] == b"\xfe"


@needs_exiftool
@pytest.mark.parametrize("timesync", [False, True], ids=["arrival", "timesync"])
def test_live_udp_autopilot_behind_a_jittery_radio(
    kf_bin: Path, short_nadir: Path, tmp_path: Path, fake_autopilot: Any, timesync: bool
) -> None:
    """A telemetry radio's delay: 5-60 ms, different for every datagram (so they
    overtake one another), TIMESYNC answers included, on top of a clock offset.
    Without TIMESYNC the least delayed arrivals map the autopilot's clock to about the
    radio's least delay (5 ms here, which no estimate can see); with it, the bounds of
    the quickest exchanges halve that, the source stays TIMESYNC all flight however
    slow most answers are, and the summary says how far off it can be. Either way the
    tags stay within the issue's 0.1 m and 0.2 degrees; UTC follows the same mapping."""
    ap = fake_autopilot(
        short_nadir / "flight.tlog",
        boot_offset_ms=1_234_567,
        latency_ms=(5.0, 60.0),
        seed=7,
        answer_timesync=timesync,
    )
    out, log = live_run(kf_bin, short_nadir, tmp_path, ap)
    tel = json.loads((out / "summary.json").read_text())["telemetry"]
    error_ms = tel["clock_offset_ms"] - true_clock_offset_ms(ap)
    print(
        f"jittery radio ({tel['clock']}): clock offset error {error_ms:.3f} ms, "
        f"uncertainty {tel['clock_uncertainty_ms']} ms"
    )
    if timesync:
        assert tel["clock"] == "timesync", tel
        # Up 0 ms (plus scheduling), down at least 5: the middle is 2.5 ms high.
        assert abs(error_ms) < 5.0, error_ms
        assert abs(error_ms) <= tel["clock_uncertainty_ms"] + 0.5, tel
        assert tel["clock_uncertainty_ms"] < 10.0, tel
        assert "no TIMESYNC answers for a while" not in log, log
    else:
        assert tel["clock"] == "arrival", tel
        assert tel["clock_uncertainty_ms"] is None, tel
        assert abs(error_ms) < 10.0, error_ms
    # UTC: the clock's error plus SYSTEM_TIME's millisecond steps
    errs = check_live_tags(short_nadir, out, ap, utc_tolerance_us=10_000, utc_first=False)
    print(
        f"jittery radio: max horizontal {max(e[0] for e in errs):.4f} m, "
        f"attitude {max(e[2] for e in errs):.4f} deg"
    )
    assert max(e[0] for e in errs) < 0.1, errs
    assert max(e[1] for e in errs) < 0.1, errs
    assert max(e[2] for e in errs) < 0.2, errs


def test_live_link_drop_garbage_and_return(
    kf_bin: Path, short_nadir: Path, tmp_path: Path, fake_autopilot: Any
) -> None:
    ap = fake_autopilot(short_nadir / "flight.tlog")

    def during(ap: FakeAutopilot, proc: Any) -> None:
        import time

        ap.wait_for("HEARTBEAT", timeout=10)
        time.sleep(2.5)
        ap.inject_garbage(3000, with_magic=True)
        ap.pause()
        time.sleep(2.0)
        ap.resume()
        ap.inject_garbage(500)

    out, _ = live_run(kf_bin, short_nadir, tmp_path, ap, "--telemetry-wait", "100", during=during)
    summary = json.loads((out / "summary.json").read_text())
    tel = summary["telemetry"]
    assert tel["rejected_frames"] + tel["skipped_bytes"] > 0
    kfs = keyframes(out)
    ok = [k for k in kfs if k["geotag"] == "ok"]
    stale = [k for k in kfs if k["geotag"] != "ok"]
    assert ok, "telemetry before and after the drop tags keyframes"
    # keyframes taken while the link was down are not given a made-up position
    for k in stale:
        assert k["lat"] == ""
        assert "stale" in k["geotag"] or "gap" in k["geotag"]
    last_ok = max(int(k["index"]) for k in ok)
    assert stale and last_ok > max(int(k["index"]) for k in stale), "tags resume after the drop"


@needs_exiftool
def test_live_udpin_daemon_listens(
    kf_bin: Path, short_nadir: Path, tmp_path: Path, fake_autopilot: Any
) -> None:
    """The usual deployment: keyframed listens (udpin) and the autopilot (or a MAVLink
    router) streams to it without waiting to hear from it first."""
    import time

    port = free_port(socket.SOCK_DGRAM)
    ap = fake_autopilot(short_nadir / "flight.tlog", target=("127.0.0.1", port))
    out = tmp_path / "live"
    proc = subprocess.Popen(
        [str(kf_bin), "select", str(short_nadir / "video.avi"), "--out", str(out), "--quiet"]
        + ["--telemetry", f"udpin:127.0.0.1:{port}"]
        + ["--calibration", str(short_nadir / "intrinsics.json")],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    time.sleep(0.3)
    ap.start()
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 0, stderr
    errs = np.array(check_live_tags(short_nadir, out, ap))
    assert (
        errs[:, 0].max() < LIVE_HORIZONTAL_M and errs[:, 1].max() < 0.1 and errs[:, 2].max() < 0.2
    ), errs
    # our HEARTBEATs reach the autopilot through the address it streams to
    assert ap.wait_for("HEARTBEAT", timeout=5)


@needs_exiftool
def test_two_vehicles_on_one_port_the_chosen_one_tags(
    kf_bin: Path, short_nadir: Path, tmp_path: Path, fake_autopilot: Any
) -> None:
    """Two vehicles stream to the camera's one udpin port: system 2 flies the flight,
    system 1 (the default choice) reports positions 1.1 km north on another boot clock.
    With `--autopilot 2` every tag and the clock come from system 2, TIMESYNC and the
    camera protocol talk to it, not to the other. This camera has no calibration:
    CAMERA_INFORMATION says NaN for what it does not know, never 0."""
    import time

    def as_system(sysid: int, north_deg: float) -> list[TlogRecord]:
        out = []
        for rec in read_tlog(short_nadir / "flight.tlog"):
            msg = copy.deepcopy(rec.msg)
            msg.get_header().srcSystem = sysid
            if msg.get_type() in ("GLOBAL_POSITION_INT", "GPS_RAW_INT"):
                msg.lat += int(north_deg * 1e7)
            out.append(TlogRecord(rec.unix_us, msg))
        return out

    write_tlog(tmp_path / "vehicle2.tlog", as_system(2, 0.0))
    write_tlog(tmp_path / "vehicle1.tlog", as_system(1, 0.01))
    port = free_port(socket.SOCK_DGRAM)
    ap = fake_autopilot(tmp_path / "vehicle2.tlog", target=("127.0.0.1", port))
    decoy = fake_autopilot(
        tmp_path / "vehicle1.tlog", target=("127.0.0.1", port), boot_offset_ms=3_000_000
    )
    assert (ap.system_id, decoy.system_id) == (2, 1)
    out = tmp_path / "live"
    proc = subprocess.Popen(
        [str(kf_bin), "select", str(short_nadir / "video.avi"), "--out", str(out), "--quiet"]
        + ["--telemetry", f"udpin:127.0.0.1:{port}", "--autopilot", "2"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    time.sleep(0.3)
    decoy.start()  # heard first: the default choice would follow it
    time.sleep(0.5)
    ap.start()
    ap.wait_for("HEARTBEAT", timeout=10)
    ap.request_message(mav2.MAVLINK_MSG_ID_CAMERA_INFORMATION)
    _, log = proc.communicate(timeout=120)
    assert proc.returncode == 0, log
    errs = np.array(check_live_tags(short_nadir, out, ap))
    assert (
        errs[:, 0].max() < LIVE_HORIZONTAL_M and errs[:, 1].max() < 0.1 and errs[:, 2].max() < 0.2
    ), errs
    assert "following the autopilot at system 2 component 1" in log, log
    tel = json.loads((out / "summary.json").read_text())["telemetry"]
    assert tel["clock"] == "timesync", tel
    assert abs(tel["clock_offset_ms"] - true_clock_offset_ms(ap)) < 5.0, tel
    assert tel["other_sources"] > 0, tel  # the decoy was heard, and left alone
    # Our requests and reports went to system 2 only.
    assert ap.received("TIMESYNC") and ap.received("CAMERA_IMAGE_CAPTURED")
    for kind in ("TIMESYNC", "CAMERA_IMAGE_CAPTURED", "COMMAND_LONG"):
        assert not decoy.received(kind), kind  # no requests, reports or stream rates
    assert ap.message_intervals, "the stream rates were asked of the chosen autopilot"
    info = ap.wait_for("CAMERA_INFORMATION", timeout=5)[0]
    assert math.isnan(info.focal_length), info
    assert math.isnan(info.sensor_size_h) and math.isnan(info.sensor_size_v), info
    assert (info.resolution_h, info.resolution_v) == (480, 270), info


def _rx(a: float) -> np.ndarray:
    return np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])


def _ry(a: float) -> np.ndarray:
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


def _rz(a: float) -> np.ndarray:
    return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])


def gimbal_tlog(
    src: Path, dst: Path, mount_pitch_deg: float, frame: str, gap_s: tuple[float, float]
) -> None:
    """The flight as if its camera hung on a stabilising gimbal under a wobbling body.

    The reported body attitude gets an extra roll/pitch wobble of several degrees; a
    GIMBAL_DEVICE_ATTITUDE_STATUS after each ATTITUDE_QUATERNION reports the true
    camera's attitude (gimbal FRD, x along the optical axis), in the vehicle frame (a
    separate gimbal component on its own boot clock) or the earth frame (from the
    autopilot, device id 1, as ArduPilot sends it). No gimbal report inside gap_s.
    """
    epoch_us = synth.EPOCH_UNIX_S * 1_000_000
    body = mav2.MAVLink(None, srcSystem=1, srcComponent=1)
    if frame == "vehicle":
        gim = mav2.MAVLink(None, srcSystem=1, srcComponent=mav2.MAV_COMP_ID_GIMBAL)
        flags, device, boot0 = mav2.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME, 0, 555_000
    else:
        gim = body
        flags, device, boot0 = mav2.GIMBAL_DEVICE_FLAGS_YAW_IN_EARTH_FRAME, 1, 0
    mount = _ry(math.radians(mount_pitch_deg))
    out = bytearray()
    for rec in read_tlog(src):
        msg = rec.msg
        t = (rec.unix_us - epoch_us) / 1e6
        extra = None
        if msg.get_type() in ("ATTITUDE", "ATTITUDE_QUATERNION"):
            if msg.get_type() == "ATTITUDE":
                r_true = synth._euler_to_rotmat(
                    np.array([msg.roll]), np.array([msg.pitch]), np.array([msg.yaw])
                )[0]
            else:
                q = np.array([[msg.q1, msg.q2, msg.q3, msg.q4]])
                r_true = synth._quat_to_rotmat(q)[0]
            wobble = _rx(math.radians(8.0) * math.sin(2 * math.pi * 0.4 * t)) @ _ry(
                math.radians(6.0) * math.sin(2 * math.pi * 0.3 * t + 1.0)
            )
            r_rep = r_true @ wobble
            yaw = math.atan2(r_rep[1, 0], r_rep[0, 0])
            if msg.get_type() == "ATTITUDE":
                msg.roll = math.atan2(r_rep[2, 1], r_rep[2, 2])
                msg.pitch = math.asin(max(-1.0, min(1.0, -r_rep[2, 0])))
                msg.yaw = yaw
            else:
                msg.q1, msg.q2, msg.q3, msg.q4 = (
                    float(v) for v in synth._rotmat_to_quat(r_rep[None])[0]
                )
                r_gimbal = r_true @ mount
                if frame == "vehicle":
                    r_gimbal = _rz(-yaw) @ r_gimbal
                if not gap_s[0] <= t < gap_s[1]:
                    extra = gim.gimbal_device_attitude_status_encode(
                        0,
                        0,
                        boot0 + msg.time_boot_ms,
                        flags,
                        [float(v) for v in synth._rotmat_to_quat(r_gimbal[None])[0]],
                        math.nan,
                        math.nan,
                        math.nan,
                        0,
                        math.nan,
                        math.nan,
                        device,
                    )
        body.seq = msg.get_seq()
        out += struct.pack(">Q", rec.unix_us) + msg.pack(body)
        if extra is not None:
            out += struct.pack(">Q", rec.unix_us) + extra.pack(gim)
            if gim is not body:
                gim.seq = (gim.seq + 1) % 256
    dst.write_bytes(bytes(out))


@needs_exiftool
@pytest.mark.parametrize("frame", ["vehicle", "earth"])
def test_gimbal_attitude_tags_the_camera_not_the_body(
    kf_bin: Path, short_nadir: Path, tmp_path: Path, frame: str
) -> None:
    meta = json.loads((short_nadir / "meta.json").read_text())
    gap = (3.0, 5.0)
    tlog = tmp_path / "gimbal.tlog"
    gimbal_tlog(short_nadir / "flight.tlog", tlog, meta["mount_pitch_deg"], frame, gap)
    truth = Truth(short_nadir)
    fps = json.loads((short_nadir / "intrinsics.json").read_text())["fps"]
    common = ["--telemetry", str(tlog), "--video-start", str(synth.EPOCH_UNIX_S)]

    out = tmp_path / "gimbal"
    r = run_select(kf_bin, short_nadir, out, *common, "--mount", "gimbal")
    assert r.returncode == 0, r.stderr
    kfs = keyframes(out)
    tags = exif([out / k["file"] for k in kfs])
    dec = decisions(out)
    worst, inside = 0.0, 0
    for k in kfs:
        idx = int(k["index"])
        t = tags[k["file"]]
        assert "GPS:GPSLatitude" in t, "position does not depend on the gimbal"
        if gap[0] + 0.05 <= idx / fps < gap[1]:
            inside += 1
            assert "XMP-Camera:Yaw" not in t, k["file"]
            assert "gimbal" in dec[idx]["geotag"], dec[idx]["geotag"]
        elif idx / fps < gap[0] - 0.05 or idx / fps >= gap[1] + 0.3:
            assert dec[idx]["geotag"] == "ok", dec[idx]["geotag"]
            worst = max(worst, tag_errors(t, truth.at(idx / fps))[2])
    summary = json.loads((out / "summary.json").read_text())
    assert summary["telemetry"]["gimbal_messages"] > 100
    print(f"gimbal ({frame} frame): attitude error max {worst:.4f} deg; {inside} in the gap")
    assert inside >= 1
    assert worst < 0.2, f"attitude error {worst:.3f} deg"

    # The same flight with the camera taken as fixed to the wobbling body is off by the
    # wobble: the gimbal's report is what made the tags right.
    fixed = tmp_path / "fixed"
    r = run_select(kf_bin, short_nadir, fixed, *common)
    assert r.returncode == 0, r.stderr
    kfs = keyframes(fixed)
    tags = exif([fixed / k["file"] for k in kfs])
    errs = [tag_errors(tags[k["file"]], truth.at(int(k["index"]) / fps))[2] for k in kfs]
    assert max(errs) > 3.0, max(errs)


@needs_exiftool
def test_live_gimbal_component_over_udp(
    kf_bin: Path, short_nadir: Path, tmp_path: Path, fake_autopilot: Any
) -> None:
    """A separate gimbal component on the link, on its own boot clock: its reports are
    stamped on arrival, and the live tags follow the camera, not the wobbling body."""
    meta = json.loads((short_nadir / "meta.json").read_text())
    tlog = tmp_path / "gimbal.tlog"
    gimbal_tlog(short_nadir / "flight.tlog", tlog, meta["mount_pitch_deg"], "vehicle", (0.0, 0.0))
    ap = fake_autopilot(tlog, boot_offset_ms=777_000)
    out, _ = live_run(kf_bin, short_nadir, tmp_path, ap, "--mount", "gimbal")
    errs = check_live_tags(short_nadir, out, ap)
    assert max(e[0] for e in errs) < 0.1, errs
    assert max(e[2] for e in errs) < 0.2, errs
    summary = json.loads((out / "summary.json").read_text())
    assert summary["telemetry"]["gimbal_messages"] > 100


@needs_exiftool
def test_make_and_model_are_tagged_with_or_without_a_calibration(
    kf_bin: Path, short_nadir: Path, tmp_path: Path
) -> None:
    """EXIF Make/Model group images into cameras in COLMAP and ODM: the user's values
    win over the calibration file's; without a calibration they are all that is
    tagged of the camera (no invented focal length); unset, none, calibrated or not."""
    cases = {
        "bare": [],
        "calibrated, unnamed": ["--calibration", str(short_nadir / "intrinsics.json")],
        "named": ["--make", "Acme Aero", "--model", "PiCam HQ 6mm"],
        "calibrated": [
            "--calibration",
            str(short_nadir / "intrinsics.json"),
            "--make",
            "Acme Aero",
            "--model",
            "PiCam HQ 6mm",
        ],
    }
    for name, extra in cases.items():
        out = tmp_path / name
        r = run_select(kf_bin, short_nadir, out, "--max-frames", "30", *extra)
        assert r.returncode == 0, r.stderr
        (t,) = [exif([p])[p.name] for p in sorted(out.glob("*.jpg"))[:1]]
        if name in ("bare", "calibrated, unnamed"):
            assert "IFD0:Make" not in t and "IFD0:Model" not in t, t
            assert ("ExifIFD:FocalLengthIn35mmFormat" in t) == (name != "bare"), t
            continue
        assert t["IFD0:Make"] == "Acme Aero" and t["IFD0:Model"] == "PiCam HQ 6mm", t
        assert t["ExifIFD:ExifImageWidth"] == 480 and t["ExifIFD:ExifImageHeight"] == 270
        if name == "named":
            assert "ExifIFD:FocalLengthIn35mmFormat" not in t and "XMP-Camera:ModelType" not in t
        else:
            assert t["ExifIFD:FocalLengthIn35mmFormat"] > 0 and "XMP-Camera:ModelType" in t
    r = run_select(kf_bin, short_nadir, tmp_path / "bad", "--make", "x" * 64)
    assert r.returncode == 2 and "--make" in r.stderr and "63 printable" in r.stderr, r.stderr


def test_select_takes_the_daemons_telemetry_settings(
    kf_bin: Path, short_nadir: Path, tmp_path: Path
) -> None:
    """`select --set telemetry.KEY=VALUE`: the daemon's [telemetry] settings offline. A
    3D fix is not enough when RTK (fix type 5) is required: no position is tagged, and
    the decision says why; keys this command has options for, other sections and bad
    values are refused before anything is read."""
    start = str(synth.EPOCH_UNIX_S)
    tlog = str(short_nadir / "flight.tlog")
    out = tmp_path / "rtk"
    r = run_select(
        kf_bin, short_nadir, out, "--telemetry", tlog, "--video-start", start,
        "--set", "telemetry.min_fix_type=5",
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    kfs = keyframes(out)
    assert kfs and all(k["lat"] == "" for k in kfs), kfs
    assert all("no GPS fix (fix type 3)" in k["geotag"] for k in kfs), kfs
    assert all(k["cam_qw"] != "" for k in kfs), "attitude needs no fix"
    for bad, needle in (
        ("telemetry.url=udpin:0.0.0.0:1", "--telemetry"),
        ("selection.target=0.5", "only [telemetry] keys"),
        ("telemetry.stale_ms=-5", "telemetry.stale_ms"),
        ("telemetry.no_such_key=1", "unknown key"),
    ):
        r = run_select(kf_bin, short_nadir, tmp_path / "bad", "--set", bad)
        assert r.returncode == 2 and needle in r.stderr, (bad, r.stderr)
        assert "Sanitizer" not in r.stderr
