"""Flight records damaged in ways the chunk CRCs do not catch (a record edited, a
writer's bug, memory that went bad before the CRC was taken): an empty picture, a
time no record can hold, a frame index past any flight. A replay skips what cannot
be a frame or a packet of the flight, and never crashes, overflows (the sanitizer
build runs each too) or writes two keyframes to one file."""

from __future__ import annotations

import csv
import json
import subprocess
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from flights import flight

mcap_reader = pytest.importorskip("mcap.reader")
from mcap.writer import CompressionType, Writer  # noqa: E402
from mcap_protobuf.decoder import DecoderFactory  # noqa: E402

# (topic, n-th message on it, log time, the message: decoded for a protobuf channel,
# else its bytes) -> (log time, bytes) to write instead, or None to keep it.
Edit = Callable[[str, int, int, Any], tuple[int, bytes] | None]


@pytest.fixture(scope="module")
def record(kf_bin: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 3 s `keyframed run` record with its preview stream, decisions and the tlog's
    MAVLink packets."""
    fl = flight("nadir", width=320, height=180, seconds=3.0)
    base = tmp_path_factory.mktemp("record")
    (base / "etc" / "conf.d").mkdir(parents=True)
    (base / "etc" / "keyframed.toml").write_text("")
    sets = [
        f"output.state_dir={base / 'state'}",
        "zenoh.enabled=false",
        "camera.source=file",
        f"camera.path={fl / 'video.avi'}",
        f"telemetry.url={fl / 'flight.tlog'}",
        "camera.start_time=1780308000",
    ]
    args = [str(kf_bin), "run", "--config-dir", str(base / "etc")]
    for s in sets:
        args += ["--set", s]
    r = subprocess.run(args, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    return (base / "state" / "latest" / "flight.mcap").resolve()


def rewrite(src: Path, dst: Path, edit: Edit) -> Path:
    """SRC's channels and messages into DST, each message through EDIT."""
    decoders = DecoderFactory()
    with open(src, "rb") as f, open(dst, "wb") as out:
        reader = mcap_reader.make_reader(f)
        writer = Writer(out, compression=CompressionType.NONE)
        writer.start()
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        counts: dict[str, int] = {}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if channel.id not in channels:
                sid = 0
                if schema is not None:
                    if schema.id not in schemas:
                        schemas[schema.id] = writer.register_schema(
                            schema.name, schema.encoding, schema.data
                        )
                    sid = schemas[schema.id]
                channels[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, sid
                )
            n = counts.get(channel.topic, 0)
            counts[channel.topic] = n + 1
            body: Any = message.data
            if channel.message_encoding == "protobuf" and schema is not None:
                decode = decoders.decoder_for(channel.message_encoding, schema)
                assert decode is not None
                body = decode(message.data)
            edited = edit(channel.topic, n, message.log_time, body)
            log_time, data = edited if edited is not None else (message.log_time, message.data)
            writer.add_message(channels[channel.id], log_time, data, log_time)
        writer.finish()
    return dst


def replay(binary: Path, rec: Path, out: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(binary), "select", str(rec), "--out", str(out), "--quiet"],
        capture_output=True,
        text=True,
        timeout=180,
    )


def assert_no_crash(r: subprocess.CompletedProcess[str]) -> None:
    assert "Sanitizer" not in r.stderr and "runtime error" not in r.stderr, r.stderr
    assert r.returncode in (0, 3), (r.returncode, r.stderr)


def rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def preview(n_edit: int, change: Callable[[Any], None]) -> Edit:
    """The n-th preview picture changed by CHANGE (on the decoded CompressedImage)."""

    def edit(topic: str, n: int, log_time: int, body: Any) -> tuple[int, bytes] | None:
        if topic != "/camera/preview" or n != n_edit:
            return None
        change(body)
        return log_time, body.SerializeToString()

    return edit


def test_an_empty_picture_is_skipped_not_an_uncaught_exception(
    any_bin: Path, record: Path, tmp_path: Path
) -> None:
    def empty(topic: str, n: int, log_time: int, body: Any) -> tuple[int, bytes] | None:
        if topic != "/camera/preview" or n != 30:
            return None
        body.data = b""  # proto3 leaves an empty field out: written here by hand,
        return log_time, body.SerializeToString() + b"\x12\x00"  # data (2), 0 bytes

    rec = rewrite(record, tmp_path / "empty.mcap", empty)
    r = replay(any_bin, rec, tmp_path / "out")
    assert_no_crash(r)
    assert r.returncode == 0, r.stderr
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    whole = replay(any_bin, record, tmp_path / "whole")
    assert whole.returncode == 0, whole.stderr
    frames = json.loads((tmp_path / "whole" / "summary.json").read_text())["frames_read"]
    assert summary["frames_read"] == frames - 1


def test_a_time_no_record_can_hold_is_skipped_and_times_never_go_back(
    any_bin: Path, record: Path, tmp_path: Path
) -> None:
    def far(m: Any) -> None:
        m.timestamp.seconds = 1 << 62  # seconds * 1e9 overflows int64

    rec = rewrite(record, tmp_path / "far.mcap", preview(10, far))
    r = replay(any_bin, rec, tmp_path / "out")
    assert_no_crash(r)
    assert r.returncode == 0, r.stderr
    times = [int(d["timestamp_ns"]) for d in rows(tmp_path / "out" / "decisions.csv")]
    assert times == sorted(times) and times[0] > 0, times


def test_times_far_apart_in_both_directions_do_not_overflow(
    any_bin: Path, record: Path, tmp_path: Path
) -> None:
    """Every picture and one MAVLink packet 9e9 s either side of 1970: nothing left to
    replay is said (exit 3); no difference of two such times is taken."""

    def swing(topic: str, n: int, log_time: int, body: Any) -> tuple[int, bytes] | None:
        if topic not in ("/camera/preview", "/mavlink/raw"):
            return None
        if topic == "/mavlink/raw" and n != 100:
            return None
        body.timestamp.seconds = -9_000_000_000 if n % 2 else 9_000_000_000
        return log_time, body.SerializeToString()

    r = replay(any_bin, rewrite(record, tmp_path / "swing.mcap", swing), tmp_path / "out")
    assert_no_crash(r)
    assert r.returncode == 3 and "no preview stream" in r.stderr, r.stderr

    def one_packet(topic: str, n: int, log_time: int, body: Any) -> tuple[int, bytes] | None:
        if topic != "/mavlink/raw" or n != 100:
            return None
        body.timestamp.seconds = -9_000_000_000
        return log_time, body.SerializeToString()

    r = replay(any_bin, rewrite(record, tmp_path / "packet.mcap", one_packet), tmp_path / "o2")
    assert_no_crash(r)
    assert r.returncode == 0, r.stderr


def test_frame_indices_past_any_flight_give_no_two_keyframes_one_file(
    any_bin: Path, record: Path, tmp_path: Path
) -> None:
    """Decision rows whose index does not fit (sscanf would saturate it to INT64_MAX)
    are not the frames' indices: the frames keep indices of their own, one file each."""

    def huge(topic: str, n: int, log_time: int, body: Any) -> tuple[int, bytes] | None:
        if topic != "/keyframed/decision":
            return None
        text = bytes(body).decode()
        return log_time, ('{"index":99999999999999999999999' + text[text.index(",") :]).encode()

    r = replay(any_bin, rewrite(record, tmp_path / "huge.mcap", huge), tmp_path / "out")
    assert_no_crash(r)
    assert r.returncode == 0, r.stderr
    kfs = rows(tmp_path / "out" / "keyframes.csv")
    files = {k["file"] for k in kfs}
    assert len(kfs) >= 2 and len(files) == len(kfs), kfs
    assert all((tmp_path / "out" / f).is_file() for f in files)
