"""The MCAP flight record of `keyframed run`: unix log times, the daemon's log in
it, doctor-clean files, rotated parts that replay as one flight."""

from __future__ import annotations

import csv
import itertools
import json
import math
import re
import shutil
import signal
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fake_autopilot import autopilot_fixture, read_tlog, write_tlog
from flights import flight
from ports import free_port, zenoh_connect_config

mcap_reader = pytest.importorskip("mcap.reader")
from mcap.records import Channel as McapChannel  # noqa: E402
from mcap.stream_reader import StreamReader  # noqa: E402
from mcap_protobuf.decoder import DecoderFactory  # noqa: E402

fake_autopilot = autopilot_fixture()

PYMCAP_CLI = shutil.which("pymcap-cli") or str(Path(sys.executable).parent / "pymcap-cli")


@pytest.fixture(scope="module")
def short_nadir() -> Path:
    return flight("nadir", width=480, height=270, seconds=8.0)


def run(
    kf_bin: Path, tmp_path: Path, *sets: str, autopilot: Any = None
) -> tuple[float, float, str]:
    """`keyframed run` to the end of the video; its unix start and end, its stderr."""
    cfg = tmp_path / "etc"
    (cfg / "conf.d").mkdir(parents=True, exist_ok=True)
    (cfg / "keyframed.toml").write_text("")
    args = [str(kf_bin), "run", "--config-dir", str(cfg)]
    base = [f"output.state_dir={tmp_path / 'state'}", "zenoh.enabled=false", "camera.source=file"]
    for s in base + list(sets):
        args += ["--set", s]
    t0 = time.time()
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    if autopilot is not None:
        time.sleep(0.3)
        autopilot.start()
    _, stderr = proc.communicate(timeout=120)
    t1 = time.time()
    assert proc.returncode == 0, stderr
    return t0, t1, stderr


def messages(path: Path) -> list[tuple[str, Any, Any]]:
    out = []
    with open(path, "rb") as f:
        reader = mcap_reader.make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, message in reader.iter_messages():
            out.append((channel.topic, message, channel))
    return out


def decoded(path: Path, topic: str) -> list[Any]:
    with open(path, "rb") as f:
        reader = mcap_reader.make_reader(f, decoder_factories=[DecoderFactory()])
        return [m.decoded_message for m in reader.iter_decoded_messages(topics=[topic])]


def doctor(path: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [PYMCAP_CLI, "doctor", str(path)], capture_output=True, text=True, timeout=120
    )


def replay(kf_bin: Path, mcap: Path, out: Path, *args: str) -> None:
    """`keyframed select RECORD --out OUT ARGS...`, which must succeed."""
    r = subprocess.run(
        [str(kf_bin), "select", str(mcap), "--out", str(out), "--quiet", *args],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr


def assert_doctor_clean(path: Path) -> None:
    r = doctor(path)
    text = " ".join(r.stdout.split())
    assert r.returncode == 0 and "passed MCAP doctor checks" in text, r.stdout + r.stderr
    assert "warning" not in text.lower(), text


def test_run_record_is_in_unix_time_holds_the_log_and_passes_doctor(
    kf_bin: Path, short_nadir: Path, tmp_path: Path
) -> None:
    # An autopilot that never speaks: the daemon warns, and the warning is recorded.
    t0, t1, stderr = run(
        kf_bin,
        tmp_path,
        f"camera.path={short_nadir / 'video.avi'}",
        "telemetry.url=udpin:127.0.0.1:9",
        "telemetry.start_wait_ms=200",
        f"tagging.calibration={short_nadir / 'intrinsics.json'}",
    )
    assert "no attitude and position yet" in stderr
    mcap = (tmp_path / "state" / "latest" / "flight.mcap").resolve()
    msgs = messages(mcap)
    topics = {t for t, _, _ in msgs}
    assert {"/keyframed/decision", "/camera/preview", "/camera/calibration"} <= topics
    lo, hi = int(t0 * 1e9), int(t1 * 1e9)
    for topic, m, _ in msgs:
        assert lo <= m.log_time <= hi, (topic, m.log_time, lo, hi)
        assert m.publish_time == m.log_time, topic
    # calibration and log: stamped when written, in unix time inside the message too
    (cal,) = decoded(mcap, "/camera/calibration")
    assert lo <= cal.timestamp.ToNanoseconds() <= hi and cal.width == 480
    logs = decoded(mcap, "/keyframed/log")
    assert all(lo <= g.timestamp.ToNanoseconds() <= hi for g in logs)
    warnings = [g for g in logs if g.level == 3]  # foxglove.Log.WARNING
    assert any("no attitude and position yet" in g.message for g in warnings), [
        (g.level, g.message) for g in logs
    ]
    assert any(g.name == "keyframed.telemetry" for g in warnings)
    assert any("recording started" in g.message for g in logs)
    # the preview stream (full size: lossless PNG, which zstd would only grow, so
    # the record is stored uncompressed and doctor has nothing to warn about) keeps
    # the run's clock inside its messages, for replay
    decisions = [json.loads(m.data) for t, m, _ in msgs if t == "/keyframed/decision"]
    previews = decoded(mcap, "/camera/preview")
    assert previews[0].timestamp.ToNanoseconds() == decisions[0]["timestamp_ns"]
    assert_doctor_clean(mcap)

    # Replayed without --calibration: the record's own calibration (K, D; no sensor
    # size, so no focal length in mm) tags the keyframes with the 35 mm equivalent.
    from PIL import Image

    out = tmp_path / "replay"
    replay(kf_bin, mcap, out)
    intr = json.loads((short_nadir / "intrinsics.json").read_text())
    jpegs = sorted(out.glob("*.jpg"))
    assert jpegs
    for jpeg in jpegs:
        exif = Image.open(jpeg).getexif().get_ifd(0x8769)
        assert exif.get(0xA405) == round(intr["fx"] * 36 / 480), "FocalLengthIn35mmFilm"

    # Replayed with other settings: the same frames decided anew, closer together.
    tight = tmp_path / "replay-tight"
    replay(kf_bin, mcap, tight, "--target", "0.85", "--band", "0.75,0.95")
    base, again = rows(out / "decisions.csv"), rows(tight / "decisions.csv")
    assert [x["index"] for x in again] == [x["index"] for x in base]
    kept_base = [x for x in base if x["kept"] == "1"]
    kept_tight = [x for x in again if x["kept"] == "1"]
    print(f"replay: {len(kept_base)} keyframes at target 0.70, {len(kept_tight)} at 0.85")
    assert len(kept_tight) > 1.5 * len(kept_base), (len(kept_tight), len(kept_base))
    overlaps = [float(x["overlap"]) for x in kept_tight[1:] if x["overlap"]]
    assert overlaps and float(np.median(overlaps)) > 0.8, overlaps


def test_options_on_a_replay_go_on_top_of_the_records_settings(
    kf_bin: Path, pan_video: Path, tmp_path: Path
) -> None:
    """A replay's options are checked against the record's settings, not the built-in
    defaults: one that fits them is taken, one that does not is refused (exit 2,
    nothing written) instead of the record's settings being dropped for the defaults."""
    run(
        kf_bin, tmp_path, f"camera.path={pan_video}", "camera.realtime=false",
        "telemetry.url=", "selection.target=0.5", "selection.band_low=0.4",
        "selection.band_high=0.8", "selection.min_overlap=0.3",
    )  # fmt: skip
    rec = (tmp_path / "state" / "latest" / "flight.mcap").resolve()

    def select(out: str, *args: str) -> subprocess.CompletedProcess[str]:
        cmd = [str(kf_bin), "select", str(rec), "--out", str(tmp_path / out), "--quiet", *args]
        return subprocess.run(cmd, capture_output=True, text=True, timeout=120)

    # --band 0.45,0.8 is under the default min-overlap (0.5), over the record's (0.3).
    fits = select("fits", "--band", "0.45,0.8")
    assert fits.returncode == 0, fits.stderr
    settings = json.loads((tmp_path / "fits/summary.json").read_text())["settings"]
    assert (settings["target"], settings["band"], settings["min_overlap"]) == (
        0.5,
        [0.45, 0.8],
        0.3,
    )
    # --band 0.55,0.8 fits the defaults (target 0.7) but not the record's target (0.5).
    clash = select("clash", "--band", "0.55,0.8")
    assert clash.returncode == 2, clash.stderr
    assert "--band LO (0.55) must not exceed --target (0.5)" in clash.stderr, clash.stderr
    assert "over the record's settings" in clash.stderr, clash.stderr
    assert not (tmp_path / "clash").exists() or not list((tmp_path / "clash").iterdir())
    # The record's own clock and telemetry: another tlog, a start time, the real clock
    # are refused as a bad command line, each at once with one answer.
    tlog = tmp_path / "other.tlog"
    tlog.write_bytes(b"")
    for args, needle in (
        (["--telemetry", str(tlog)], "no --telemetry with it"),
        (["--telemetry", str(tlog), "--video-start", "2026-06-01T10:00:00Z"], "no --telemetry"),
        (["--video-start", "2026-06-01T10:00:00Z"], "no --realtime or --video-start"),
        (["--realtime"], "no --realtime or --video-start"),
    ):
        refused = select("refused", *args)
        assert refused.returncode == 2, (args, refused.stderr)
        assert needle in refused.stderr, (args, refused.stderr)


def test_a_fisheye_calibration_is_recorded_and_replayed_as_fisheye(
    kf_bin: Path, short_nadir: Path, tmp_path: Path
) -> None:
    """A fisheye lens's calibration goes into the record as Foxglove's kannala_brandt
    (OpenCV's fisheye k1..k4), and a replay of the record tags its keyframes as the
    same fisheye, not as a pinhole with those four numbers."""
    from keyframed.ground import read_tags

    intr = json.loads((short_nadir / "intrinsics.json").read_text())
    d = [0.041, -0.0093, 0.0021, -0.00037]
    intr |= {"model": "fisheye", "distortion": d, "fx": 150.0, "fy": 150.0}
    calib = tmp_path / "fisheye.json"
    calib.write_text(json.dumps(intr))
    run(
        kf_bin,
        tmp_path,
        f"camera.path={short_nadir / 'video.avi'}",
        "camera.realtime=false",
        'telemetry.url=""',
        f"tagging.calibration={calib}",
    )
    mcap = (tmp_path / "state" / "latest" / "flight.mcap").resolve()
    (cal,) = decoded(mcap, "/camera/calibration")
    assert cal.distortion_model == "kannala_brandt"
    assert list(cal.D) == pytest.approx(d)
    assert list(cal.K) == pytest.approx([150, 0, intr["cx"], 0, 150, intr["cy"], 0, 0, 1])

    again = tmp_path / "replay"
    replay(kf_bin, mcap, again)
    jpegs = sorted(again.glob("*.jpg"))
    assert jpegs
    xmp = jpegs[0].read_bytes()
    assert b'Camera:ModelType="fisheye"' in xmp
    assert b'Keyframed:FisheyeDistortion="0.041,-0.0093,0.0021,-0.00037"' in xmp
    assert b"PerspectiveDistortion" not in xmp
    tags = read_tags(xmp)
    assert tags.lens == "fisheye" and tags.distortion == pytest.approx(d)


def rows(path: Path) -> list[dict[str, str]]:
    with open(path) as f:
        return list(csv.DictReader(f))


def matrix(w: float, x: float, y: float, z: float) -> Any:
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def rot(axis: str, a: float) -> Any:
    c, s = math.cos(a), math.sin(a)
    return {
        "x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[axis]


def counts(path: Path) -> dict[str, int]:
    with open(path, "rb") as f:
        summ = mcap_reader.make_reader(f).get_summary()
    topics = {c.id: c.topic for c in summ.channels.values()}
    return {topics[c]: n for c, n in summ.statistics.channel_message_counts.items()}


def test_rotated_record_replays_as_one_flight_and_every_part_passes_doctor(
    kf_bin: Path, short_nadir: Path, tmp_path: Path, fake_autopilot: Any
) -> None:
    mport = free_port(socket.SOCK_DGRAM)
    ap = fake_autopilot(short_nadir / "flight.tlog", target=("127.0.0.1", mport))
    t0, t1, stderr = run(
        kf_bin,
        tmp_path,
        f"camera.path={short_nadir / 'video.avi'}",
        f"telemetry.url=udpin:127.0.0.1:{mport}",
        "output.preview_width=240",
        "output.mcap_rotate_mb=1",
        autopilot=ap,
    )
    fd = (tmp_path / "state" / "latest").resolve()
    parts = sorted(fd.glob("flight*.mcap"))
    assert len(parts) >= 3 and parts[-1].name == "flight.mcap", parts  # flight-001, ...
    for part in parts:
        assert_doctor_clean(part)
        # each part says how the flight selected: it replays on its own as the flight did
        assert counts(part).get("/keyframed/settings") == 1, part
    # each rotation is a log line, recorded too
    assert "MCAP: recording continues in " + str(fd / "flight-001.mcap") in stderr, stderr
    logged = [g.message for p in parts for g in decoded(p, "/keyframed/log")]
    assert sum("MCAP: recording continues in" in m for m in logged) == len(parts) - 1, logged
    live = json.loads((fd / "summary.json").read_text())

    out = tmp_path / "replay"
    r = subprocess.run(
        [str(kf_bin), "select", str(fd / "flight.mcap"), "--out", str(out), "--quiet"]
        + ["--mcap", str(tmp_path / "replay.mcap")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    replay = json.loads((out / "summary.json").read_text())
    assert replay["frames_read"] == live["frames_read"] == 240, (replay, live)
    # the replay's record keeps the original flight's times
    lo, hi = int(t0 * 1e9), int(t1 * 1e9)
    msgs = messages(tmp_path / "replay.mcap")
    decisions = [m for t, m, _ in msgs if t == "/keyframed/decision"]
    assert len(decisions) == 240
    assert all(lo <= m.log_time <= hi for _, m, _ in msgs)
    assert_doctor_clean(tmp_path / "replay.mcap")

    # The replay's record carries the preview and the MAVLink stream on: it replays
    # in its turn, to the same decisions.
    raw = sum(counts(p).get("/mavlink/raw", 0) for p in parts)
    again = counts(tmp_path / "replay.mcap")
    assert raw > 100 and again.get("/mavlink/raw") == raw, (raw, again)
    assert again.get("/camera/preview") == 240
    # the autopilot's track and attitude at the stream's rate, decoded from MAVLink
    fixes = [f for p in parts for f in decoded(p, "/vehicle/location")]
    poses = [q for p in parts for q in decoded(p, "/vehicle/pose")]
    assert len(fixes) > 8 * 2 and len(poses) > 8 * 2, (len(fixes), len(poses))
    assert all(abs(f.latitude - 51.89) < 0.01 and f.frame_id == "vehicle" for f in fixes)
    for q in (p.pose.orientation for p in poses):
        assert abs(q.w**2 + q.x**2 + q.y**2 + q.z**2 - 1) < 1e-3
    # each pose is the attitude packet received at that instant, decoded again here
    from pymavlink.dialects.v20 import common

    mav = common.MAVLink(None)
    attitudes = {}
    for p in parts:
        for pkt in decoded(p, "/mavlink/raw"):
            if pkt.message_id in (30, 31):
                attitudes[pkt.timestamp.ToNanoseconds()] = mav.decode(bytearray(pkt.packet))
    kinds = set()
    for pose in poses:
        m = attitudes[pose.timestamp.ToNanoseconds()]
        kinds.add(m.get_type())
        o = pose.pose.orientation
        got = matrix(o.w, o.x, o.y, o.z)
        if m.get_type() == "ATTITUDE_QUATERNION":
            want = matrix(m.q1, m.q2, m.q3, m.q4)
        else:  # body to NED: yaw about z, then pitch about y, then roll about x
            want = rot("z", m.yaw) @ rot("y", m.pitch) @ rot("x", m.roll)
        assert np.allclose(got, want, atol=1e-5), (m, got, want)
    print(f"{len(poses)} poses from {sorted(kinds)}")
    assert again.get("/vehicle/location") == len(fixes)
    out2 = tmp_path / "replay2"
    r = subprocess.run(
        [str(kf_bin), "select", str(tmp_path / "replay.mcap"), "--out", str(out2), "--quiet"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    keys = ("index", "timestamp_ns", "kept", "reason", "sharpness", "overlap")
    a, b = rows(out / "decisions.csv"), rows(out2 / "decisions.csv")
    assert len(a) == len(b) == 240
    assert [[x[k] for k in keys] for x in a] == [[y[k] for k in keys] for y in b]
    assert (out2 / "keyframes.csv").read_text() == (out / "keyframes.csv").read_text()


def nal_types(packet: bytes) -> list[int]:
    """The NAL unit types of an Annex B H.264 packet, in order."""
    types, i = [], packet.find(b"\x00\x00\x01")
    while i >= 0 and i + 3 < len(packet):
        types.append(packet[i + 3] & 0x1F)
        i = packet.find(b"\x00\x00\x01", i + 3)
    return types


def test_h264_video_stream_is_foxglove_compressed_video_and_replays(
    kf_bin: Path, short_nadir: Path, tmp_path: Path
) -> None:
    """output.preview_format = "h264": the record's stream is foxglove.CompressedVideo
    as Foxglove wants it (Annex B, one picture a message, an IDR with its SPS every
    second), an ordinary decoder plays it, each part of a rotated record on its own,
    Zenoh's preview key still gets JPEGs, and the record replays to about the live
    decisions (the video is lossy)."""
    import cv2
    import zenoh

    # The watcher listens and the daemon dials it: no reconnection back-off to wait out.
    zport = free_port()
    zconf = zenoh_connect_config(tmp_path / "zenoh.json5", zport)
    conf = zenoh.Config()
    conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{zport}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    watcher = zenoh.open(conf)
    stills: list[bytes] = []
    sub = watcher.declare_subscriber(
        "keyframed/uav9/preview", lambda s: stills.append(s.payload.to_bytes())
    )
    try:
        run(
            kf_bin,
            tmp_path,
            f"camera.path={short_nadir / 'video.avi'}",
            "output.preview_format=h264",
            "output.preview_width=480",  # the video's own width
            "output.mcap_rotate_mb=1",  # about 1.8 MB of video: two parts
            "zenoh.enabled=true",
            f"zenoh.config={zconf}",
            "zenoh.vehicle=uav9",
        )
    finally:
        sub.undeclare()
        watcher.close()
    mcap = (tmp_path / "state" / "latest" / "flight.mcap").resolve()
    parts = [mcap, *sorted(mcap.parent.glob("flight-*.mcap"))]
    assert len(parts) >= 2, parts
    pictures, decisions = [], []
    for part in parts:
        assert_doctor_clean(part)
        msgs = messages(part)
        assert not [t for t, _, _ in msgs if t == "/camera/preview"]
        video = [(m, c) for t, m, c in msgs if t == "/camera/video"]
        assert video[0][1].message_encoding == "protobuf"
        with open(part, "rb") as f:
            schemas = mcap_reader.make_reader(f).get_summary().schemas
        assert schemas[video[0][1].schema_id].name == "foxglove.CompressedVideo"
        decisions += [json.loads(m.data) for t, m, _ in msgs if t == "/keyframed/decision"]
        in_part = decoded(part, "/camera/video")
        # A part opens with an IDR picture: it plays on its own, from its first message.
        assert 5 in nal_types(in_part[0].data), part
        stream = tmp_path / f"{part.stem}.h264"
        stream.write_bytes(b"".join(p.data for p in in_part))
        cap = cv2.VideoCapture(str(stream))  # an ordinary decoder (OpenCV's FFmpeg)
        played = 0
        while True:
            ok, img = cap.read()
            if not ok:
                break
            assert img.shape[:2] == (270, 480)
            played += 1
        assert played == len(in_part), (part, played, len(in_part))
        pictures += in_part
    assert len(decisions) == 240 and len(pictures) == 240, (len(decisions), len(pictures))
    assert all(p.format == "h264" and p.frame_id == "camera" for p in pictures)
    assert [p.timestamp.ToNanoseconds() for p in pictures] == [d["timestamp_ns"] for d in decisions]
    idr = [i for i, p in enumerate(pictures) if 5 in nal_types(p.data)]
    assert idr == list(range(0, 240, 30)), idr  # the video's 30 fps: one a second
    assert all(7 in nal_types(pictures[i].data) for i in idr)  # each with its SPS
    assert all(len(nal_types(p.data)) >= 1 for p in pictures)
    video_bytes = sum(len(p.data) for p in pictures)
    print(f"H.264 480x270: {video_bytes / 240 / 1000:.1f} kB a frame, {len(parts)} parts")

    # Zenoh's live view: JPEG stills about twice a second.
    assert len(stills) >= 5 and all(s[:2] == b"\xff\xd8" for s in stills), len(stills)

    # Replayed: the same frames, decided again on the decoded video.
    out = tmp_path / "replay"
    replay(kf_bin, mcap, out, "--mcap", str(tmp_path / "replay.mcap"))
    live = rows(mcap.parent / "decisions.csv")
    again = rows(out / "decisions.csv")
    assert [x["index"] for x in again] == [x["index"] for x in live]
    sharp_live = np.array([float(x["sharpness"]) for x in live])
    sharp_again = np.array([float(x["sharpness"]) for x in again])
    rel = np.abs(sharp_again - sharp_live) / sharp_live
    kept_live = sum(x["kept"] == "1" for x in live)
    kept_again = sum(x["kept"] == "1" for x in again)
    print(
        f"replay of H.264: sharpness within {np.median(rel):.1%} (median),"
        f" {kept_again} keyframes against {kept_live} live"
    )
    assert np.median(rel) < 0.15, rel
    assert abs(kept_again - kept_live) <= max(2, kept_live // 5), (kept_again, kept_live)
    # its record carries the packets on, as they were
    assert [p.data for p in decoded(tmp_path / "replay.mcap", "/camera/video")] == [
        p.data for p in pictures
    ]


def test_sigkill_of_the_daemon_loses_about_the_last_second(
    kf_bin: Path, short_nadir: Path, tmp_path: Path
) -> None:
    """`keyframed run` killed outright (SIGKILL: no flush, no summary section) in the
    middle of a flight: the record reads back up to about a second before the kill,
    its decisions without a hole, and `pymcap-cli recover` makes a doctor-clean file
    of it with every message that was readable."""
    cfg = tmp_path / "etc"
    (cfg / "conf.d").mkdir(parents=True)
    (cfg / "keyframed.toml").write_text("")
    args = [str(kf_bin), "run", "--config-dir", str(cfg)]
    for s in (
        f"output.state_dir={tmp_path / 'state'}",
        "zenoh.enabled=false",
        "camera.source=file",
        "telemetry.url=",
        f"camera.path={short_nadir / 'video.avi'}",  # 8 s at 30 fps, in real time
    ):
        args += ["--set", s]
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    mcap = tmp_path / "state" / "latest" / "flight.mcap"
    deadline = time.monotonic() + 30
    while not mcap.exists() and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.05)
    time.sleep(4.0)
    assert proc.poll() is None, proc.communicate()[1]
    killed = time.time()
    proc.kill()
    proc.wait(timeout=10)
    mcap = mcap.resolve()

    read: list[Any] = []
    with mcap.open("rb") as fh:
        try:
            for _, _, msg in mcap_reader.NonSeekingReader(fh).iter_messages(log_time_order=False):
                read.append(msg)
        except Exception:
            pass  # the torn last chunk: the reader stops there
    assert read
    lost = killed - max(m.log_time for m in read) / 1e9
    print(f"SIGKILL: {len(read)} messages read back, the last {lost:.2f} s before the kill lost")
    # The writer ends a chunk at least once a second; allow half a second for a loaded
    # machine.
    assert 0 <= lost < 1.5, lost

    out = tmp_path / "recovered.mcap"
    r = subprocess.run(
        [PYMCAP_CLI, "recover", str(mcap), "-o", str(out), "--compression", "none", "--force"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode in (0, 3) and out.exists(), r.stdout + r.stderr
    assert_doctor_clean(out)
    with out.open("rb") as fh:
        reader = mcap_reader.make_reader(fh)
        recovered = list(reader.iter_messages(log_time_order=False))
    assert len(recovered) >= len(read)
    index = sorted(
        json.loads(m.data)["index"] for _, ch, m in recovered if ch.topic == "/keyframed/decision"
    )
    # Every decision up to the torn end, in order, none twice: a chunk lost inside the
    # file would leave a second's gap (some 30 frames). Frames the capture dropped on a
    # loaded machine (their numbers skipped, as in decisions.csv) leave a few.
    assert len(index) >= 60 and index[0] == 0, index[:5]
    pairs = list(itertools.pairwise(index))
    assert all(1 <= b - a <= 8 for a, b in pairs), [(a, b) for a, b in pairs if b - a != 1]

    # Every channel the cut file declared, with messages before the cut or not.
    declared: set[str] = set()
    with mcap.open("rb") as fh:
        try:
            for record in StreamReader(fh).records:
                if isinstance(record, McapChannel):
                    declared.add(record.topic)
        except Exception:
            pass  # the torn last chunk
    assert {ch.topic for _, ch, _ in recovered} <= declared

    # The next start repairs it in place, on its own: doctor-clean, a seeking reader
    # reads it, with what pymcap-cli recovered, and every channel declared.
    again = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and again.poll() is None:
            if mcap.read_bytes()[-8:] == b"\x89MCAP0\r\n":
                break
            time.sleep(0.1)
        again.send_signal(signal.SIGTERM)
        _, stderr = again.communicate(timeout=30)
    finally:
        if again.poll() is None:
            again.kill()
    assert again.returncode == 0, stderr
    assert f"flight record {mcap} was left unfinished" in stderr, stderr
    assert not list(mcap.parent.glob("*.recovering"))
    assert_doctor_clean(mcap)
    with mcap.open("rb") as fh:
        reader = mcap_reader.make_reader(fh)
        repaired = list(reader.iter_messages(log_time_order=False))
        summary = reader.get_summary()
    assert summary is not None
    assert len(repaired) == len(recovered)
    assert [m.data for _, _, m in repaired] == [m.data for _, _, m in recovered]
    assert {c.topic for c in summary.channels.values()} == declared
    empty = declared - {ch.topic for _, ch, _ in recovered}
    print(f"repaired: {len(declared)} channels, without messages: {sorted(empty)}")


@pytest.mark.skipif(shutil.which("strace") is None, reason="needs strace")
@pytest.mark.parametrize("fsync", [True, False])
def test_mcap_fsync_syncs_the_record_at_each_timed_flush(
    kf_bin: Path, tmp_path: Path, fsync: bool
) -> None:
    """output.mcap_fsync (default on): the record reaches the disk about once a second,
    so a power cut loses about a second; off, only at open and close."""
    fl = flight("nadir", width=320, height=180, seconds=6.0)
    cfg = tmp_path / "etc"
    (cfg / "conf.d").mkdir(parents=True)
    (cfg / "keyframed.toml").write_text("" if fsync else "[output]\nmcap_fsync = false\n")
    trace = tmp_path / "strace.txt"
    args = ["strace", "-f", "-y", "-e", "trace=fsync,fdatasync", "-o", str(trace)]
    args += [str(kf_bin), "run", "--config-dir", str(cfg)]
    for s in (
        f"output.state_dir={tmp_path / 'state'}",
        "zenoh.enabled=false",
        "camera.source=file",
        "telemetry.url=",
        f"camera.path={fl / 'video.avi'}",
    ):
        args += ["--set", s]
    r = subprocess.run(args, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    syncs = [ln for ln in trace.read_text().splitlines() if "flight.mcap>" in ln]
    print(f"mcap_fsync={fsync}: {len(syncs)} syncs of flight.mcap in a 6 s run")
    if fsync:
        assert len(syncs) >= 4, syncs
        # and the file's name: the directory is synced by the same thread right after
        # the file's first sync (its schemas and channels), before any other sync
        lines = trace.read_text().splitlines()
        first = next(i for i, ln in enumerate(lines) if "flight.mcap>" in ln)
        tid = lines[first].split()[0]
        # (strace splits a call another thread interrupted into "<unfinished ...>" and
        # "<... fdatasync resumed>" lines: the resumed line ends the same call)
        after = [ln for ln in lines[first + 1 :] if ln.split()[0] == tid and "resumed>" not in ln]
        flight_dir = re.search(r"<([^>]*)/flight\.mcap>", lines[first])
        assert flight_dir and after, lines[first:]
        assert f"<{flight_dir.group(1)}>)" in after[0], after[:2]
    else:
        assert len(syncs) <= 2, syncs


def two_vehicle_tlog(src: Path, dst: Path) -> tuple[int, int]:
    """src's flight with a second vehicle (system 2, also component 1) on the same link,
    one degree further north; returns how many GLOBAL_POSITION_INT each one sent."""
    from pymavlink.dialects.v20 import common

    records = read_tlog(src)
    out, own, other = [], 0, 0
    for rec in records:
        out.append(rec)
        kind = rec.msg.get_type()
        if kind not in ("HEARTBEAT", "GLOBAL_POSITION_INT", "ATTITUDE", "ATTITUDE_QUATERNION"):
            continue
        twin = common.MAVLink(None).decode(bytearray(rec.msg.get_msgbuf()))
        twin._header.srcSystem = 2
        if kind == "GLOBAL_POSITION_INT":
            twin.lat += 10_000_000
            own, other = own + 1, other + 1
        out.append(type(rec)(rec.unix_us + 1, twin))
    write_tlog(dst, out)
    return own, other


def test_offline_record_carries_the_tlog_and_the_chosen_autopilot_only(
    kf_bin: Path, short_nadir: Path, tmp_path: Path
) -> None:
    from keyframed import synth

    tlog = tmp_path / "two.tlog"
    own, other = two_vehicle_tlog(short_nadir / "flight.tlog", tlog)
    packets = sorted(bytes(r.msg.get_msgbuf()) for r in read_tlog(tlog))
    # ArduPilot's own messages ride along too (another dialect: unchecked, but from a
    # component heard), not a frame of an unknown id from a sender never heard (noise).
    from pymavlink.dialects.v20 import ardupilotmega

    last = read_tlog(tlog)[-1].unix_us
    ekf = ardupilotmega.MAVLink(None, srcSystem=1, srcComponent=1).ekf_status_report_encode(
        0x1FF, 0.1, 0.2, 0.3, 0.4, 0.5
    )
    ekf_bytes = bytes(ekf.pack(ardupilotmega.MAVLink(None, srcSystem=1, srcComponent=1)))
    stranger = bytes(ekf.pack(ardupilotmega.MAVLink(None, srcSystem=77, srcComponent=1)))
    # The autopilot's estimator not aligned yet: a zero quaternion and NaN angles are
    # no attitude, on /vehicle/pose as for the tags (recorded raw all the same).
    ap = ardupilotmega.MAVLink(None, srcSystem=1, srcComponent=1)
    unset = bytes(ap.attitude_quaternion_encode(10**7, 0, 0, 0, 0, 0, 0, 0).pack(ap))
    nan = float("nan")
    no_angles = bytes(ap.attitude_encode(10**7 + 1, nan, nan, nan, 0, 0, 0).pack(ap))
    with tlog.open("ab") as f:
        f.write(struct.pack(">Q", last + 1) + ekf_bytes)
        f.write(struct.pack(">Q", last + 2) + stranger)
        f.write(struct.pack(">Q", last + 3) + unset)
        f.write(struct.pack(">Q", last + 3_000_000) + no_angles)
    packets = sorted(packets + [ekf_bytes, unset, no_angles])

    for system, lat0 in ((1, 51.89), (2, 52.89)):
        rec = tmp_path / f"sys{system}.mcap"
        r = subprocess.run(
            [str(kf_bin), "select", str(short_nadir / "video.avi")]
            + ["--out", str(tmp_path / f"o{system}"), "--quiet", "--telemetry", str(tlog)]
            + ["--video-start", str(synth.EPOCH_UNIX_S)]
            + ["--autopilot", str(system), "--mcap", str(rec)],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert r.returncode == 0, r.stderr
        assert_doctor_clean(rec)
        c = counts(rec)
        # every packet of the link, both vehicles', byte for byte
        assert c.get("/mavlink/raw") == len(packets), (c, len(packets))
        assert sorted(bytes(p.packet) for p in decoded(rec, "/mavlink/raw")) == packets
        fixes = decoded(rec, "/vehicle/location")
        assert len(fixes) == (own if system == 1 else other) > 0
        assert all(abs(f.latitude - lat0) < 0.01 for f in fixes), (system, fixes[0])
        poses = decoded(rec, "/vehicle/pose")
        assert len(poses) > len(fixes)
        for p in poses:
            o = p.pose.orientation
            norm = math.sqrt(o.x * o.x + o.y * o.y + o.z * o.z + o.w * o.w)
            assert abs(norm - 1.0) < 1e-6, p
