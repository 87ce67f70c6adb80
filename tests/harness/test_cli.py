"""`keyframed select` from the outside: outputs, and every kind of bad input."""

from __future__ import annotations

import csv
import glob
import json
import os
import signal
import subprocess
import time
from pathlib import Path

import cv2
import numpy as np
import pytest


def run(kf_bin: Path, *args: str | Path, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(kf_bin), *map(str, args)], capture_output=True, text=True, timeout=timeout
    )


def assert_clean_failure(p: subprocess.CompletedProcess[str], needle: str, code: int) -> None:
    """One error line holding `needle`, and the documented exit status: 2 a bad command
    line, 3 an input that could not be read or an output not written."""
    assert p.returncode == code, (p.returncode, p.stderr)
    lines = [line for line in p.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, f"expected one error line, got: {p.stderr!r}"
    assert needle in lines[0], lines[0]


def test_select_writes_keyframes_decisions_and_summary(kf_bin: Path, pan_video: Path, tmp_path):
    out = tmp_path / "out"
    p = run(kf_bin, "select", pan_video, "--out", out)
    assert p.returncode == 0, p.stderr
    rows = list(csv.DictReader((out / "decisions.csv").open()))
    assert [int(r["index"]) for r in rows] == list(range(90))
    kept = [int(r["index"]) for r in rows if r["kept"] == "1"]
    jpgs = sorted(int(f.stem) for f in out.glob("*.jpg"))
    assert jpgs == kept
    assert kept[0] == 0
    assert len(kept) >= 3  # 6 px/frame over 480 px: 0.70 overlap every ~24 frames
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames_read"] == 90
    assert summary["kept"] == len(kept)
    assert (
        summary["kept"] + summary["rejected_blur"] + summary["rejected_overlap"]
        == summary["frames_read"]
    )
    blur = [
        r
        for r in rows
        if r["kept"] == "0"
        and (r["reason"] == "blurry" or (r["reason"] == "lost" and r["sharp"] == "0"))
    ]
    assert summary["rejected_blur"] == len(blur)
    assert summary["frames_per_second"] > 0
    assert "keyframes:" in p.stdout and str(out) in p.stdout
    assert not list(out.glob("*.tmp"))
    # every selection setting used, by the name `select`'s options and [selection] give it
    assert set(summary["settings"]) == {
        "mode", "target", "band", "analysis_width", "blur_mode", "blur_threshold",
        "blur_floor", "blur_ratio", "blur_quantile", "blur_window", "blur_step", "blur_width",
        "orb_features", "paper_threshold", "paper_min_matches", "min_overlap", "motion_ratio",
        "motion_min_fraction", "motion_window", "capture_wait_ms", "max_tracks", "min_tracks",
        "min_inliers", "ransac_px", "fast_threshold", "lk_window", "lk_levels", "blur_warmup",
    }  # fmt: skip
    assert summary["settings"]["min_tracks"] == 80 and summary["settings"]["lk_window"] == 13


def test_an_earlier_run_in_the_output_directory(any_bin: Path, pan_video: Path, tmp_path):
    """A second run into the same --out is refused with one line (its keyframes would
    mix with the first run's: an SfM tool reads them all); with --overwrite the first
    run's keyframes, decisions and summary go, and nothing else in the directory."""
    out = tmp_path / "out"
    first = run(any_bin, "select", pan_video, "--out", out, "--target", "0.85")
    assert first.returncode == 0, first.stderr
    before = json.loads((out / "summary.json").read_text())
    (out / "notes.txt").write_text("the pilot's notes\n")
    (out / "0042.jpg").write_bytes(b"a photo of the pilot's, numbered")
    again = run(any_bin, "select", pan_video, "--out", out, "--target", "0.6")
    assert_clean_failure(again, "earlier run's output", 3)
    assert "--overwrite" in again.stderr
    # said at once, before the video is even looked at
    early = run(any_bin, "select", tmp_path / "missing.avi", "--out", out)
    assert_clean_failure(early, "earlier run's output", 3)
    assert json.loads((out / "summary.json").read_text()) == before  # untouched
    p = run(any_bin, "select", pan_video, "--out", out, "--target", "0.6", "--overwrite")
    assert p.returncode == 0, p.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["kept"] < before["kept"]
    kept = [
        int(r["index"]) for r in csv.DictReader((out / "decisions.csv").open()) if r["kept"] == "1"
    ]
    assert sorted(int(f.stem) for f in out.glob("*.jpg") if len(f.stem) >= 6) == kept
    assert len(kept) == summary["kept"]
    assert (out / "notes.txt").read_text() == "the pilot's notes\n"
    assert (out / "0042.jpg").is_file()  # not a keyframe's name (six digits or more)
    # numbered pictures without a run's record are someone else's: they would mix
    # with the keyframes (or one be replaced): refused, and with --overwrite left be
    photos = tmp_path / "photos"
    photos.mkdir()
    (photos / "100001.jpg").write_bytes(b"a camera's picture")
    p = run(any_bin, "select", pan_video, "--out", photos, "--max-frames", "10")
    assert_clean_failure(p, "picture(s) named as keyframes are", 3)
    assert sorted(f.name for f in photos.iterdir()) == ["100001.jpg"]
    p = run(any_bin, "select", pan_video, "--out", photos, "--max-frames", "10", "--overwrite")
    assert p.returncode == 0, p.stderr
    assert (photos / "100001.jpg").read_bytes() == b"a camera's picture"
    # nor can the record be given a keyframe's name in --out (a keyframe would replace it)
    p = run(
        any_bin, "select", pan_video, "--out", tmp_path / "o3", "--mcap", tmp_path / "o3/000000.jpg"
    )
    assert_clean_failure(p, "has a keyframe's name in --out", 3)


def test_a_fifo_no_one_writes_to_ends_on_ctrl_c(any_bin: Path, tmp_path):
    """A named pipe that no writer opens blocks the video's open for good: Ctrl-C (or
    SIGTERM) ends the command then and there, exit 130, with nothing written."""
    fifo = tmp_path / "camera.avi"
    os.mkfifo(fifo)
    out = tmp_path / "out"
    for sig in (signal.SIGINT, signal.SIGTERM):
        proc = subprocess.Popen(
            [str(any_bin), "select", str(fifo), "--out", str(out)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            # until it waits in open() for a writer (its handlers are in place by then)
            deadline = time.monotonic() + 60
            wchan = Path(f"/proc/{proc.pid}/wchan")
            while wchan.read_text() not in ("wait_for_partner", "fifo_open"):
                assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
                time.sleep(0.05)
            proc.send_signal(sig)
            _, stderr = proc.communicate(timeout=10)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
        assert proc.returncode == 130, stderr
        assert "Sanitizer" not in stderr
        assert not out.exists()


def test_jsonl_decisions_and_paper_mode(kf_bin: Path, pan_video: Path, tmp_path):
    out = tmp_path / "paper"
    p = run(kf_bin, "select", pan_video, "--out", out, "--mode", "paper", "--decisions", "jsonl")
    assert p.returncode == 0, p.stderr
    rows = [json.loads(line) for line in (out / "decisions.jsonl").open()]
    assert len(rows) == 90
    assert all(r["paper_distance"] is not None for r in rows[1:])
    assert rows[0]["kept"] and rows[0]["reason"] == "first"


def test_missing_file(any_bin: Path, tmp_path):
    assert_clean_failure(
        run(any_bin, "select", tmp_path / "nope.avi", "--out", tmp_path / "o"), "no such file", 3
    )


def test_not_a_video(any_bin: Path, tmp_path):
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"\x00\x01 definitely not a video " * 1000)
    assert_clean_failure(
        run(any_bin, "select", junk, "--out", tmp_path / "o"), "not a readable video", 3
    )


@pytest.mark.parametrize("ext", [".jpg", ".png"])
def test_a_photo_is_not_a_video(any_bin: Path, tmp_path, ext: str):
    # FFmpeg would read it as a one-frame video; the user most likely meant a video.
    img = np.random.default_rng(0).integers(0, 255, (120, 160, 3), dtype=np.uint8)
    photo = tmp_path / f"photo{ext}"
    assert cv2.imwrite(str(photo), img)
    out = tmp_path / "o"
    assert_clean_failure(
        run(any_bin, "select", photo, "--out", out), "a still image, not a video", 3
    )
    assert not any(out.glob("*.jpg"))


def test_a_raw_mjpeg_file_is_a_video(kf_bin: Path, pan_video: Path, tmp_path):
    # Concatenated JPEGs (what an MJPEG camera dumped to disk looks like) start with a
    # JPEG's signature; they are still a video, not a photo.
    cap = cv2.VideoCapture(str(pan_video))
    chunks: list[bytes] = []
    while len(chunks) < 12:
        ok, img = cap.read()
        assert ok
        chunks.append(cv2.imencode(".jpg", img)[1].tobytes())
    stream = tmp_path / "camera.mjpeg"
    stream.write_bytes(b"".join(chunks))
    out = tmp_path / "o"
    p = run(kf_bin, "select", stream, "--out", out)
    assert p.returncode == 0, p.stderr
    assert json.loads((out / "summary.json").read_text())["frames_read"] == 12


def test_directory_instead_of_video(any_bin: Path, tmp_path):
    assert_clean_failure(run(any_bin, "select", tmp_path, "--out", tmp_path / "o"), "directory", 3)


def test_an_mp4_cut_before_its_index_is_one_clear_error(any_bin: Path, tmp_path):
    """An MP4 whose recording was cut (its index, written last, is missing): one line
    from keyframed, none from FFmpeg underneath."""
    import cv2

    mp4 = tmp_path / "whole.mp4"
    w = cv2.VideoWriter(str(mp4), cv2.VideoWriter.fourcc(*"mp4v"), 30, (160, 120))
    assert w.isOpened()
    for i in range(30):
        w.write(np.full((120, 160, 3), i * 8, np.uint8))
    w.release()
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(mp4.read_bytes()[: mp4.stat().st_size // 2])
    assert_clean_failure(
        run(any_bin, "select", cut, "--out", tmp_path / "o"), "not a readable video", 3
    )


def test_truncated_video_keeps_what_was_read_and_fails(any_bin: Path, pan_video: Path, tmp_path):
    cut = tmp_path / "cut.avi"
    data = pan_video.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    out = tmp_path / "o"
    p = run(any_bin, "select", cut, "--out", out)
    assert p.returncode == 3
    assert_clean_failure(p, "ended early", 3)
    summary = json.loads((out / "summary.json").read_text())
    assert 10 < summary["frames_read"] < 90
    assert summary["truncated"] is True
    # Every keyframe decided before the break is on disk.
    kept = [r for r in csv.DictReader((out / "decisions.csv").open()) if r["kept"] == "1"]
    assert len(kept) == len(list(out.glob("*.jpg"))) >= 1


@pytest.mark.parametrize("suffix", [".ts", ".mkv"])
def test_streamed_containers_are_read_whole(any_bin: Path, tmp_path, suffix):
    """MPEG-TS and Matroska carry no frame index: a complete file is not reported as
    truncated (FFmpeg's rate for an MPEG-4 TS is its 90 kHz clock, and the frame count
    it derives from it is not believed), and every frame is read."""
    from conftest import write_pan_video

    whole = write_pan_video(tmp_path / f"whole{suffix}", frames=60, fourcc="mp4v")
    out = tmp_path / "o"
    p = run(any_bin, "select", whole, "--out", out)
    assert p.returncode == 0, p.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames_read"] == 60
    assert summary["truncated"] is False


def test_cut_transport_stream_is_truncated(any_bin: Path, tmp_path):
    """An MPEG-TS has no index, but one cut at a random byte ends part-way through a
    188-byte packet: the frames before the cut are read, and the run fails as
    truncated."""
    from conftest import write_pan_video

    whole = write_pan_video(tmp_path / "whole.ts", frames=60, fourcc="mp4v")
    data = whole.read_bytes()
    cut = tmp_path / "cut.ts"
    cut.write_bytes(data[: (len(data) // 2 // 188) * 188 + 100])
    out = tmp_path / "o"
    p = run(any_bin, "select", cut, "--out", out)
    assert p.returncode == 3, p.stderr
    assert_clean_failure(p, "ended early", 3)
    assert "transport packet" in p.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["truncated"] is True
    assert 10 < summary["frames_read"] < 60


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--bogus"], "unknown option --bogus"),
        (["--target", "1.5"], "--target"),
        (["--target", "x"], "not a number"),
        (["--mode", "magic"], "unknown mode"),
        (["--band", "0.9,0.2"], "band"),
        (["--jpeg-quality", "0"], "--jpeg-quality"),
        (["--blur-window"], "needs a value"),
        # what was typed is echoed on the one line, its control characters escaped
        (["--make", "Acme\nCam"], "(got 'Acme\\nCam')"),
        # cross-field and core rules name the options involved and their values
        (["--target", "0.5"], "--band LO (0.6) must not exceed --target (0.5)"),
        (["--analysis-width", "10"], "--analysis-width: must be 0 (full) or >= 64"),
        (["--min-overlap", "0.65"], "--min-overlap (0.65) must not exceed --band LO (0.6)"),
        (["--max-tracks", "20", "--min-tracks", "30"], "--min-tracks (30) must not exceed"),
        # tracks replenished only below min-tracks: fewer than min-inliers lose the track
        (["--min-inliers", "100"], "--min-inliers (100) must not exceed --min-tracks (80)"),
        (
            ["--mode", "paper", "--paper-min-matches", "5000"],
            "--paper-min-matches (5000) must not exceed --orb-features (2500)",
        ),
        # a live link's frames are stamped as they arrive, not from a given start
        (
            ["--telemetry", "udpin:127.0.0.1:9", "--video-start", "2026-06-01T10:00:00Z"],
            "--video-start aligns a video with a tlog",
        ),
    ],
)
def test_bad_options(any_bin: Path, pan_video: Path, tmp_path, args: list[str], needle: str):
    p = run(any_bin, "select", pan_video, "--out", tmp_path / "o", *args)
    assert p.returncode == 2
    assert_clean_failure(p, needle, 2)


@pytest.mark.parametrize("size", [(640, 16), (4000, 8), (16, 16)])
def test_frames_too_small_to_analyse(any_bin: Path, tmp_path, size: tuple[int, int]):
    """A strip of a few rows, or a thumbnail: one line and exit 3 before any output,
    in either mode (ORB's pyramid failed inside OpenCV before: exit 1, its message)."""
    video = tmp_path / "strip.avi"
    w = cv2.VideoWriter(str(video), cv2.VideoWriter.fourcc(*"MJPG"), 30, size)
    rng = np.random.default_rng(3)
    for _ in range(10):
        w.write(rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8))
    w.release()
    for mode in ("geometric", "paper"):
        p = run(any_bin, "select", video, "--out", tmp_path / mode, "--mode", mode)
        assert p.returncode == 3, p.stderr
        assert_clean_failure(p, f"frames of {size[0]}x{size[1]} are too small to analyse", 3)
        assert not (tmp_path / mode).exists()


def test_frames_too_large_to_analyse(any_bin: Path, tmp_path):
    """Past 16384 pixels a side (or 64 megapixels): one line, exit 3, before any
    output, not gigabytes of frame buffers on a companion computer."""
    video = tmp_path / "wide.avi"
    w = cv2.VideoWriter(str(video), cv2.VideoWriter.fourcc(*"MJPG"), 30, (16400, 64))
    for _ in range(3):
        w.write(np.random.default_rng(3).integers(0, 255, (64, 16400, 3), dtype=np.uint8))
    w.release()
    p = run(any_bin, "select", video, "--out", tmp_path / "o", "--analysis-width", "0")
    assert p.returncode == 3, p.stderr
    assert_clean_failure(p, "frames of 16400x64 are too large to analyse", 3)
    assert not (tmp_path / "o").exists()


def test_a_frame_size_that_changes_part_way_is_not_silent(any_bin: Path, tmp_path):
    """A raw MJPEG stream whose pictures grow part-way: OpenCV's reader hands back the
    last picture of the first size for every later frame (FFmpeg's scaler refuses the
    new size, and OpenCV does not say), so the rest is not seen. The run says so."""
    rng = np.random.default_rng(5)
    video = tmp_path / "grow.mjpeg"
    with video.open("wb") as f:
        for i in range(60):
            w, h = (480, 270) if i < 30 else (960, 540)
            img = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
            f.write(cv2.imencode(".jpg", img)[1].tobytes())
    p = run(any_bin, "select", video, "--out", tmp_path / "o")
    assert "repeat one picture" in p.stderr and "frame size changes part-way" in p.stderr, p.stderr
    assert "Sanitizer" not in p.stderr


def test_unknown_command_and_help(any_bin: Path):
    assert_clean_failure(run(any_bin, "frobnicate"), "unknown command", 2)
    h = run(any_bin, "select", "--help")
    assert h.returncode == 0 and "--target" in h.stdout


def test_unwritable_output(any_bin: Path, pan_video: Path, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert_clean_failure(
        run(any_bin, "select", pan_video, "--out", blocker / "sub"), "cannot create", 3
    )


def test_full_disk_is_an_error_not_a_crash(any_bin: Path, pan_video: Path, tmp_path):
    # A tiny tmpfs is not available without privileges everywhere; /dev/full is.
    out = tmp_path / "o"
    out.mkdir()
    (out / "decisions.csv").symlink_to("/dev/full")
    p = run(any_bin, "select", pan_video, "--out", out)
    assert p.returncode == 3
    assert "cannot" in p.stderr


def test_progress_line_on_request(kf_bin: Path, pan_video: Path, tmp_path):
    p = run(kf_bin, "select", pan_video, "--out", tmp_path / "o", "--progress")
    assert p.returncode == 0
    assert "frame 90/90" in p.stderr and "kept" in p.stderr


def test_progress_is_automatic_on_a_terminal_only(kf_bin: Path, pan_video: Path, tmp_path):
    # stderr a pseudo-terminal: progress shows without asking; a pipe: it does not.
    import pty

    leader, follower = pty.openpty()
    with subprocess.Popen(
        [str(kf_bin), "select", str(pan_video), "--out", str(tmp_path / "tty")],
        stdout=subprocess.DEVNULL,
        stderr=follower,
    ) as p:
        os.close(follower)
        chunks = []
        while True:  # read as it runs, so a full terminal buffer cannot stall it
            try:
                chunk = os.read(leader, 65536)
            except OSError:  # EIO: the program has exited and closed the terminal
                break
            if not chunk:
                break
            chunks.append(chunk)
        os.close(leader)
        p.wait(timeout=120)
    assert p.returncode == 0
    assert "frame 90/90" in b"".join(chunks).decode(errors="replace")
    piped = run(kf_bin, "select", pan_video, "--out", tmp_path / "pipe")
    assert piped.returncode == 0 and "frame 90/90" not in piped.stderr


def test_interrupt_stops_cleanly_with_outputs_flushed(kf_bin: Path, tmp_path):
    import signal
    import time

    from conftest import write_pan_video

    video = write_pan_video(tmp_path / "long.avi", frames=1500, step=1.0, size=(640, 360))
    out = tmp_path / "o"
    proc = subprocess.Popen(
        [str(kf_bin), "select", str(video), "--out", str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    # Interrupted once it is selecting (its decisions file is open), not while it starts:
    # a signal before main() is the inherited disposition's (pytest-xdist's workers
    # ignore SIGINT), not the program's.
    decisions = out / "decisions.csv"
    deadline = time.monotonic() + 30
    while not decisions.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 130, err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["interrupted"] is True
    assert 0 < summary["frames_read"] < 1500
    rows = list(csv.DictReader((out / "decisions.csv").open()))
    assert len(rows) == summary["frames_read"]
    assert len(list(out.glob("*.jpg"))) == summary["kept"]


def test_corrupt_video_never_crashes(any_bin: Path, pan_video: Path, tmp_path):
    """Garbage written over the middle of the file: decode what can be, never crash."""
    import random

    data = bytearray(pan_video.read_bytes())
    rng = random.Random(7)
    start = len(data) // 3
    for i in range(start, start + len(data) // 4):
        if rng.random() < 0.2:
            data[i] = rng.randrange(256)
    bad = tmp_path / "corrupt.avi"
    bad.write_bytes(bytes(data))
    out = tmp_path / "o"
    p = run(any_bin, "select", bad, "--out", out)
    assert p.returncode in (0, 3), p  # finished, or a clean input error; never a signal
    if p.returncode == 3:
        assert len([x for x in p.stderr.splitlines() if x.strip()]) == 1, p.stderr
    summary = json.loads((out / "summary.json").read_text())
    kept = [r for r in csv.DictReader((out / "decisions.csv").open()) if r["kept"] == "1"]
    assert len(kept) == len(list(out.glob("*.jpg"))) == summary["kept"]


@pytest.mark.skipif(
    bool(glob.glob("/dev/video*")) or bool(glob.glob("/dev/media*")),
    reason="this machine has a camera device: the no-camera case cannot be seen here",
)
def test_probe_list_without_a_camera_says_so(kf_bin: Path) -> None:
    """An operator's first check on a new vehicle: with no camera, --list says so and
    exits 1, as the probe without --list does, rather than printing nothing."""
    p = run(kf_bin, "probe-v4l2", "--list")
    assert p.returncode == 1, (p.returncode, p.stdout, p.stderr)
    assert '"reason":"no V4L2 device found under /dev"' in p.stdout, p.stdout
    p = run(kf_bin, "probe-libcamera", "--list")
    assert p.returncode == 1, (p.returncode, p.stdout, p.stderr)
    assert "no camera found" in p.stderr, p.stderr


def test_options_that_have_no_effect_are_said(kf_bin: Path, pan_video: Path, tmp_path) -> None:
    """An option the others make pointless (another mode's, a live link's without one)
    is still accepted, but said, so that a user does not believe it was applied."""
    cases = [
        (["--orb-features", "300"], "--orb-features has no effect in the geometric mode"),
        (["--mode", "paper", "--max-tracks", "300"], "--max-tracks has no effect in the paper"),
        (["--blur-threshold", "50"], "--blur-threshold has no effect in the adaptive blur mode"),
        (["--blur-mode", "absolute", "--blur-ratio", "0.5"], "--blur-ratio has no effect"),
        (["--mount", "0,-45,0"], "--mount has no effect without --telemetry (no attitude"),
        (["--autopilot", "1"], "--autopilot has no effect without --telemetry (no link"),
        (["--telemetry-wait", "5"], "--telemetry-wait has no effect without a live"),
    ]
    for i, (args, needle) in enumerate(cases):
        p = run(
            kf_bin, "select", pan_video, "--out", tmp_path / f"o{i}", "--max-frames", "20", *args
        )
        assert p.returncode == 0, (args, p.stderr)
        warnings = [ln for ln in p.stderr.splitlines() if "has no effect" in ln]
        assert len(warnings) == 1 and needle in warnings[0], (args, p.stderr)
    # Options that do apply: nothing said.
    p = run(kf_bin, "select", pan_video, "--out", tmp_path / "ok", "--max-frames", "20",
            "--mode", "paper", "--orb-features", "300",
            "--blur-mode", "absolute", "--blur-threshold", "5")  # fmt: skip
    assert p.returncode == 0, p.stderr
    assert "has no effect" not in p.stderr, p.stderr
