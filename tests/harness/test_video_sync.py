"""`select --video-start auto`: a video placed in a tlog by the motion both recorded
(the camera's turns seen in the images against the attitude the autopilot logged)."""

from __future__ import annotations

import json
import signal
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from fake_autopilot import TlogRecord, read_tlog, write_tlog
from flights import flight
from keyframed import synth
from test_geotag import Truth, exif, keyframes, needs_exiftool, tag_errors
from test_run import flight_dir, rows, start

CLIP_FIRST = 150  # the clip starts 5 s into the flight (30 fps) ...
CLIP_FRAMES = 600  # ... and lasts 20 s, over the survey's U-turn


@pytest.fixture(scope="module")
def nadir() -> Path:
    return flight("nadir", width=480, height=270)


def cut(video: Path, out: Path, first: int, count: int) -> Path:
    """Frames first .. first + count - 1 of video as a video of their own (container
    time 0 at `first`), as a camera started after the tlog would have recorded."""
    cap = cv2.VideoCapture(str(video))
    fps = cap.get(cv2.CAP_PROP_FPS)
    size = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
    writer = cv2.VideoWriter(str(out), cv2.VideoWriter.fourcc(*"MJPG"), fps, size)
    i = 0
    while True:
        ok, frame = cap.read()
        if not ok or i >= first + count:
            break
        if i >= first:
            writer.write(frame)
        i += 1
    writer.release()
    assert i == first + count, f"{video} has {i} frames"
    return out


def select_auto(
    kf_bin: Path, video: Path, fl: Path, out: Path, *extra: str, given: bool = True
) -> Any:
    """`select --telemetry TLOG --video-start auto`, or with `given` False the same
    without --video-start (auto is the default with a tlog)."""
    cmd = [str(kf_bin), "select", str(video), "--out", str(out), "--telemetry"]
    cmd += [str(fl / "flight.tlog"), *(["--video-start", "auto"] if given else []), *extra]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=180)


@pytest.fixture(scope="module")
def clip(nadir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return cut(
        nadir / "video.avi", tmp_path_factory.mktemp("clip") / "clip.avi", CLIP_FIRST, CLIP_FRAMES
    )


def video_start(out: Path) -> dict[str, Any]:
    start = json.loads((out / "summary.json").read_text())["video_start"]
    assert start["method"] == "motion"
    return start


@needs_exiftool
def test_a_clip_is_placed_in_its_tlog_and_tagged_as_the_truth(
    kf_bin: Path, nadir: Path, clip: Path, tmp_path: Path
) -> None:
    """A video that starts 5 s into the tlog, with nothing to say so: the motion
    places it within 5 ms (a sixth of a frame), and its keyframes carry the pose the
    ground truth has for their frames, as with --video-start given exactly. The
    command is the plain `select VIDEO --telemetry FLIGHT.tlog --calibration FILE
    --out DIR` (auto is the default with a tlog)."""
    out = tmp_path / "out"
    r = select_auto(
        kf_bin, clip, nadir, out, "--calibration", str(nadir / "intrinsics.json"), given=False
    )
    assert r.returncode == 0, r.stderr
    start = video_start(out)
    expected = synth.EPOCH_UNIX_S + CLIP_FIRST / 30.0
    print(
        f"clip placed {1e3 * (start['unix_s'] - expected):+.2f} ms from the truth, "
        f"correlation {start['correlation']}, next best {start['runner_up']}, "
        f"{start['seconds']} s"
    )
    assert abs(start["unix_s"] - expected) < 0.005
    assert start["correlation"] > 0.9 and start["runner_up"] < 0.8 * start["correlation"]
    assert "video start 2026-06-01T10:00:0" in r.stderr
    kfs = keyframes(out)
    assert len(kfs) >= 5 and all(k["geotag"] == "ok" for k in kfs)
    tags = exif([out / k["file"] for k in kfs])
    truth = Truth(nadir)
    errs = np.array(
        [tag_errors(tags[k["file"]], truth.at((int(k["index"]) + CLIP_FIRST) / 30.0)) for k in kfs]
    )
    assert errs[:, 0].max() < 0.1 and errs[:, 1].max() < 0.1 and errs[:, 2].max() < 0.2, errs


def test_a_camera_latency_is_measured_with_the_motion(
    kf_bin: Path, nadir: Path, clip: Path, tmp_path: Path
) -> None:
    """--time-offset adds a latency to the frame times at tagging; the motion measured
    where the frames really were, so the start is moved back by it and the tagged
    instants (keyframes.csv's time_ns) stay where the motion put them."""
    plain, late = tmp_path / "plain", tmp_path / "late"
    assert select_auto(kf_bin, clip, nadir, plain, "--quiet").returncode == 0
    r = select_auto(kf_bin, clip, nadir, late, "--quiet", "--time-offset", "80")
    assert r.returncode == 0, r.stderr
    shift = video_start(plain)["unix_s"] - video_start(late)["unix_s"]
    assert shift == pytest.approx(0.080, abs=1e-6)
    tagged = {k["index"]: int(k["time_ns"]) for k in keyframes(plain)}
    for k in keyframes(late):
        if k["index"] in tagged:
            assert abs(int(k["time_ns"]) - tagged[k["index"]]) <= 1000


def test_an_oblique_orbit_is_placed_through_its_mount(kf_bin: Path, tmp_path: Path) -> None:
    """The orbit's camera looks 55 degrees down: its turn about the optical axis mixes
    the vehicle's yaw, pitch and roll rates through the mount."""
    orbit = flight("orbit", width=480, height=270)
    out = tmp_path / "out"
    r = select_auto(
        kf_bin,
        orbit / "video.avi",
        orbit,
        out,
        "--calibration",
        str(orbit / "intrinsics.json"),
        "--mount",
        "0,-55,0",
    )
    assert r.returncode == 0, r.stderr
    start = video_start(out)
    assert abs(start["unix_s"] - synth.EPOCH_UNIX_S) < 0.005, start


def test_a_video_that_hardly_turns_is_not_placed(any_bin: Path, tmp_path: Path) -> None:
    """Three seconds of straight survey: no turn to line up. A clear error, exit 3,
    no keyframes, never a guess."""
    short = flight("nadir", width=320, height=180, seconds=3.0)
    out = tmp_path / "out"
    r = select_auto(any_bin, short / "video.avi", short, out)
    assert r.returncode == 3, r.stderr
    assert "cannot place the video in the tlog by its motion" in r.stderr
    assert "--video-start TIME" in r.stderr and "Traceback" not in r.stderr
    assert not list(out.glob("*.jpg"))


def test_another_flights_tlog_is_not_matched(any_bin: Path, clip: Path, tmp_path: Path) -> None:
    """The nadir clip against the orbit's tlog: its U-turn has no counterpart there
    (the orbit turns steadily), so no lag is accepted."""
    orbit = flight("orbit", width=480, height=270)
    r = select_auto(any_bin, clip, orbit, tmp_path / "out")
    assert r.returncode == 3, r.stderr
    assert "cannot place the video" in r.stderr


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--video-start", "auto"], "give --telemetry FILE.tlog"),
        (
            ["--video-start", "auto", "--telemetry", "udpin:127.0.0.1:9"],
            "--video-start aligns a video with a tlog",
        ),
    ],
)
def test_auto_needs_a_tlog(
    any_bin: Path, nadir: Path, tmp_path: Path, args: list[str], message: str
) -> None:
    cmd = [str(any_bin), "select", str(nadir / "video.avi"), "--out", str(tmp_path / "o"), *args]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and message in r.stderr, r.stderr


def test_the_daemon_places_a_replayed_video_by_its_motion(
    kf_bin: Path, nadir: Path, clip: Path, tmp_path: Path
) -> None:
    """`keyframed run` on the clip with its tlog and camera.start_time = "auto": the
    video is placed before the camera starts, and every keyframe is tagged with the
    position the ground truth has for its frame."""
    proc = start(
        kf_bin,
        tmp_path,
        f"camera.path={clip}",
        "camera.start_time=auto",
        "camera.realtime=false",
        f"telemetry.url=tlog:{nadir / 'flight.tlog'}",
        f"tagging.calibration={nadir / 'intrinsics.json'}",
    )
    _, stderr = proc.communicate(timeout=180)
    assert proc.returncode == 0, stderr
    assert "video start 2026-06-01T10:00:0" in stderr, stderr
    kfs = rows(flight_dir(tmp_path) / "keyframes" / "keyframes.csv")
    # read as fast as it decodes: a loaded machine drops frames, and so keyframes
    assert len(kfs) >= 2 and all(k["geotag"] == "ok" for k in kfs), kfs
    truth = Truth(nadir)
    for k in kfs:
        lat, lon, alt, _ = truth.at((int(k["index"]) + CLIP_FIRST) / 30.0)
        d_n = (float(k["lat"]) - lat) * 111_320.0
        d_e = (float(k["lon"]) - lon) * 111_320.0 * np.cos(np.radians(lat))
        assert np.hypot(d_n, d_e) < 0.1 and abs(float(k["alt_amsl"]) - alt) < 0.1, k


class PlacingDaemon:
    """`keyframed run` placing the 30 s nadir flight (960x540: a pass of several
    seconds) in its tlog by motion, its stderr read as it comes."""

    def __init__(self, kf_bin: Path, tmp_path: Path) -> None:
        big = flight("nadir")
        self.proc = start(
            kf_bin,
            tmp_path,
            f"camera.path={big / 'video.avi'}",
            "camera.start_time=auto",
            f"telemetry.url=tlog:{big / 'flight.tlog'}",
        )
        self.lines: list[str] = []
        err = self.proc.stderr
        assert err is not None
        self.reader = threading.Thread(target=lambda: self.lines.extend(err), daemon=True)
        self.reader.start()

    def wait_for(self, text: str, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while not any(text in line for line in self.lines):
            assert self.proc.poll() is None and time.monotonic() < deadline, "".join(self.lines)
            time.sleep(0.05)

    def stderr(self) -> str:
        """Everything it wrote (once it has exited: all of it)."""
        if self.proc.poll() is not None:
            self.reader.join(timeout=5)
        return "".join(self.lines)


def test_the_daemon_answers_sigterm_while_placing_the_video(kf_bin: Path, tmp_path: Path) -> None:
    """The pass over a long video comes before the camera starts: SIGTERM ends it
    promptly and cleanly."""
    placing = PlacingDaemon(kf_bin, tmp_path)
    proc = placing.proc
    placing.wait_for("by their motion", 30)
    time.sleep(0.5)  # into the pass over the video
    assert proc.poll() is None, placing.stderr()
    t0 = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    proc.wait(timeout=20)
    took = time.monotonic() - t0
    stderr = placing.stderr()
    assert proc.returncode == 0, stderr
    assert took < 2.0, f"SIGTERM took {took:.2f} s"
    assert "stopping before the video was placed" in stderr, stderr


def test_a_sighup_while_placing_the_video_is_taken_once_it_is_placed(
    kf_bin: Path, tmp_path: Path
) -> None:
    """A reload asked for during the pass is not lost: it runs once the outputs are open."""
    placing = PlacingDaemon(kf_bin, tmp_path)
    proc = placing.proc
    try:
        placing.wait_for("by their motion", 30)
        time.sleep(0.3)  # into the pass over the video
        proc.send_signal(signal.SIGHUP)
        placing.wait_for("reloaded once the video is placed", 10)
        placing.wait_for("reload: selection settings unchanged", 120)
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    stderr = placing.stderr()
    assert proc.returncode == 0, stderr
    placed = stderr.index("video start 2026-06-01T10:00:0")
    assert stderr.index("reload: selection settings unchanged") > placed, stderr


def test_the_daemon_refuses_auto_without_a_tlog(kf_bin: Path, clip: Path, tmp_path: Path) -> None:
    proc = start(kf_bin, tmp_path, f"camera.path={clip}", "camera.start_time=auto")
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 78, stderr
    assert "camera.start_time" in stderr and "a tlog as telemetry.url" in stderr, stderr


def test_the_daemon_exits_when_the_motion_cannot_place_the_video(
    kf_bin: Path, tmp_path: Path
) -> None:
    short = flight("nadir", width=320, height=180, seconds=3.0)
    proc = start(
        kf_bin,
        tmp_path,
        f"camera.path={short / 'video.avi'}",
        "camera.start_time=auto",
        f"telemetry.url=tlog:{short / 'flight.tlog'}",
    )
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 1, stderr
    assert "camera.start_time = auto: cannot place the video" in stderr, stderr
    assert "set camera.start_time to the video's start" in stderr


@pytest.mark.parametrize("station_ahead_s", [40.0, -3.5])
def test_a_tlog_recorded_on_a_wrong_clock_places_the_clip_by_gps_time(
    kf_bin: Path, nadir: Path, clip: Path, tmp_path: Path, station_ahead_s: float
) -> None:
    """The station that recorded the tlog had its clock off (by more than the flight
    lasts, or behind): the start found is on the autopilot's GPS time (SYSTEM_TIME),
    as a given --video-start would be."""
    tlog_dir = tmp_path / "skewed"
    tlog_dir.mkdir()
    shift_us = round(station_ahead_s * 1e6)
    records = read_tlog(nadir / "flight.tlog")
    write_tlog(tlog_dir / "flight.tlog", [TlogRecord(r.unix_us + shift_us, r.msg) for r in records])
    out = tmp_path / "out"
    r = select_auto(kf_bin, clip, tlog_dir, out, "--quiet")
    assert r.returncode == 0, r.stderr
    assert abs(video_start(out)["unix_s"] - (synth.EPOCH_UNIX_S + CLIP_FIRST / 30.0)) < 0.005
    kfs = keyframes(out)
    assert kfs and all(k["geotag"] == "ok" for k in kfs), kfs


def test_ctrl_c_while_placing_the_video_interrupts_select(kf_bin: Path, tmp_path: Path) -> None:
    big = flight("nadir")  # 960x540, 30 s: a pass of several seconds
    proc = subprocess.Popen(
        [str(kf_bin), "select", str(big / "video.avi"), "--out", str(tmp_path / "o")]
        + ["--telemetry", str(big / "flight.tlog"), "--video-start", "auto"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    time.sleep(1.5)
    assert proc.poll() is None
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=20)
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr and "cannot place" not in stderr, stderr
