"""The benchmark programs run and print what docs/performance.md quotes: short runs,
so that a benchmark broken by a change is noticed here, not when someone measures.
No timing is asserted (the numbers are the machine's); the tables' shape and the
counts that do not depend on speed are."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import ROOT, keyframed_bin
from flights import flight
from mcap.reader import make_reader


def bench(name: str) -> Path:
    exe = keyframed_bin().resolve().parents[1] / "tools" / "bench" / name
    if not exe.exists():
        pytest.skip(f"{exe} not built")
    return exe


def row(text: str, label: str) -> list[float]:
    """The numbers on the table row that starts with ``label``."""
    m = re.search(rf"^\s*{re.escape(label)}\s+(.*)$", text, re.MULTILINE)
    assert m, f"no row {label!r} in:\n{text}"
    return [float(v) for v in re.findall(r"\d+(?:\.\d+)?", m.group(1))]


def test_selector_benchmark_on_1080p_frames() -> None:
    fl = flight("nadir", width=1920, height=1080, seconds=2.0, fps=60.0)
    p = subprocess.run(
        [str(bench("keyframed-bench")), str(fl / "video.avi"), "--frames", "40"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert p.returncode == 0, p.stderr
    out = p.stdout + p.stderr
    print(out)
    assert "40 frames of 1920x1080" in out
    # the geometric and the paper mode side by side: median / p99 of each
    for stage in ("blur score (S9 Laplacian)", "overlap (track/ORB+match)", "total decision"):
        geo_median, geo_p99, paper_median, paper_p99, *_ = row(out, stage)
        assert 0 < geo_median <= geo_p99 and 0 < paper_median <= paper_p99, (stage, out)
    assert row(out, "frames/s (single thread)")[0] > 0
    # the steady state allocates nothing (held by keyframed_alloc_test too)
    assert row(out, "heap allocations/frame")[0] == 0.0
    for stage in (
        "JPEG from YUV420 (camera)",
        "EXIF + XMP tags (exiv2)",
        "the same, a fisheye lens",
    ):
        median, p99 = row(out, stage)[-2:]
        assert 0 < median <= p99, (stage, median, p99)


def test_mavlink_parser_benchmark_reads_every_whole_packet() -> None:
    p = subprocess.run(
        [str(bench("keyframed-mavlink-bench")), "20000"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert p.returncode == 0, p.stderr
    print(p.stdout)
    # each row: MB/s, messages read, of how many, frames rejected
    clean = row(p.stdout, "telemetry ")
    lossy = row(p.stdout, "telemetry, 3 bytes lost in 1 of 10")
    junk = row(p.stdout, "random bytes, 1/4 start bytes")
    assert clean[0] > 0 and clean[1] == clean[2] == 20000 and clean[3] == 0, clean
    # every packet that arrived whole is read; the damaged ones are rejected
    assert lossy[0] > 0 and lossy[1] == lossy[2] == 18000 and 1900 <= lossy[3] <= 2000, lossy
    assert junk[0] > 0 and junk[1] == junk[2] == 0, junk


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_mcap_benchmark_writes_a_readable_file(tmp_path: Path, compression: str) -> None:
    path = tmp_path / "bench.mcap"
    p = subprocess.run(
        [str(bench("keyframed-mcap-bench")), str(path), "50", "20000", compression],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert p.returncode == 0, p.stderr
    print(p.stdout)
    m = re.search(r"(\d+) messages of (\d+) bytes, .* ([\d.]+) MB/s", p.stdout)
    assert m and (m.group(1), m.group(2)) == ("50", "20000"), p.stdout
    assert float(m.group(3)) > 0
    with path.open("rb") as f:
        messages = list(make_reader(f).iter_messages())
    # CompressedImage messages around each 20,000-byte payload
    assert len(messages) == 50 and all(len(msg.data) > 20000 for _, _, msg in messages)


def test_latency_benchmark_receives_every_keyframe() -> None:
    """One short flight through the daemon to a Zenoh subscriber and a ground station:
    every keyframe written is received and stored, and the latency lines are printed."""
    p = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "bench" / "latency_bench.py")]
        + ["--width", "480", "--height", "270", "--seconds", "6", "--runs", "1"]
        + ["--bin", str(keyframed_bin())],
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert p.returncode == 0, p.stdout + p.stderr
    print(p.stdout)
    got, written = row(p.stdout, "keyframes received")
    assert got == written > 0, p.stdout
    m = re.search(
        r"decision to receipt\s+median ([\d.]+) ms, p99 ([\d.]+), max ([\d.]+) over (\d+)",
        p.stdout,
    )
    assert m, p.stdout
    median, p99, worst, count = (float(v) for v in m.groups())
    assert 0 < median <= p99 <= worst and count == written, p.stdout
    # and at the ground station, every keyframe stored in its dataset
    got, written = row(p.stdout, "in the station's dataset")
    assert got == written, p.stdout
    m = re.search(
        r"decision to stored\s+median ([\d.]+) ms, p99 ([\d.]+), max ([\d.]+) over (\d+)",
        p.stdout,
    )
    assert m, p.stdout
    median, p99, worst, count = (float(v) for v in m.groups())
    assert 0 < median <= p99 <= worst and count == written, p.stdout


def test_daemon_benchmark_with_its_peers() -> None:
    """tools/bench/daemon_bench.sh --full on a 2 s 1080p flight: the daemon with a fake
    autopilot and a ground station; its rows printed, every keyframe geotagged and
    received, and (--rss) the daemon's memory sampled while it ran."""
    p = subprocess.run(
        [str(ROOT / "tools" / "bench" / "daemon_bench.sh"), "2", "--full", "--rss"],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
    )
    assert p.returncode == 0, p.stdout + p.stderr
    print(p.stdout)
    out = p.stdout
    assert row(out, "frames_read")[0] > 0 and row(out, "frames_dropped")[0] == 0, out
    kept = row(out, "kept")[0]
    assert kept > 0 and row(out, "geotagged")[0] == kept, out
    assert row(out, "ground station received")[0] == kept, out
    assert row(out, "cpu_percent")[0] > 0 and row(out, "max_rss_mb")[0] > 0, out
    rss = re.search(
        r"VmRSS from \d+ s to (\d+) s \((\d+) samples\): ([\d.]+) MB then, ([\d.]+) MB at the end, "
        r"([\d.]+)-([\d.]+) MB, growth ([-+][\d.]+) MB a minute",
        out,
    )
    assert rss is not None, out
    low, high = float(rss[5]), float(rss[6])
    assert int(rss[2]) >= 3 and 0 < low <= float(rss[3]) <= high and low <= float(rss[4]) <= high
    # the samples are the daemon's: near its peak (VmHWM, read as it wrote its summary;
    # the teardown after that may add a little), not a shell's few MB
    assert row(out, "max_rss_mb")[0] / 2 < high <= row(out, "max_rss_mb")[0] + 5, out
