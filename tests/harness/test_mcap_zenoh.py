"""MCAP flight record and Zenoh stream of `keyframed select`, checked with independent
tools: pymcap-cli's doctor, the Python `mcap` reader, Foxglove's own compiled protobuf
schemas (foxglove-schemas-protobuf) and a Python eclipse-zenoh peer."""

from __future__ import annotations

import csv
import json
import resource
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from fake_autopilot import read_tlog
from flights import flight
from keyframed import synth
from ports import free_port

mcap_reader = pytest.importorskip("mcap.reader")
zenoh = pytest.importorskip("zenoh")
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration  # noqa: E402
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage  # noqa: E402
from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix  # noqa: E402
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame  # noqa: E402
from mcap_protobuf.decoder import DecoderFactory  # noqa: E402

PYMCAP_CLI = shutil.which("pymcap-cli") or str(Path(sys.executable).parent / "pymcap-cli")


@pytest.fixture(scope="module")
def short_nadir() -> Path:
    return flight("nadir", width=480, height=270, seconds=8.0)


def select(kf_bin: Path, video: Path, out: Path, *extra: str, **kw: Any) -> Any:
    cmd = [str(kf_bin), "select", str(video), "--out", str(out), "--quiet", *extra]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=kw.pop("timeout", 180), **kw)


def keyframe_rows(out: Path) -> list[dict[str, str]]:
    with (out / "keyframes.csv").open() as fh:
        return list(csv.DictReader(fh))


def messages(path: Path, *, seeking: bool = True) -> list[tuple[str, Any, Any]]:
    """(topic, schema, message) for every message. A file cut short (seeking=False) is
    read from the start with NonSeekingReader up to its torn last chunk, whose length
    field is still the writer's placeholder: the reader stops there with an error."""
    out = []
    with path.open("rb") as fh:
        if seeking:
            it = mcap_reader.make_reader(fh).iter_messages(log_time_order=False)
        else:
            it = mcap_reader.NonSeekingReader(fh).iter_messages(log_time_order=False)
        try:
            for schema, ch, msg in it:
                out.append((ch.topic, schema, msg))
        except Exception:
            if seeking:
                raise
    return out


def by_topic(msgs: list[tuple[str, Any, Any]], topic: str) -> list[Any]:
    return [m for t, _, m in msgs if t == topic]


def doctor(path: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [PYMCAP_CLI, "doctor", str(path)], capture_output=True, text=True, timeout=120
    )


# ---- (a) the record is valid and complete ------------------------------------------


def test_mcap_record_is_valid_and_complete(kf_bin: Path, short_nadir: Path, tmp_path: Path):
    out, rec = tmp_path / "out", tmp_path / "flight.mcap"
    r = select(
        kf_bin,
        short_nadir / "video.avi",
        out,
        "--mcap",
        str(rec),
        "--telemetry",
        str(short_nadir / "flight.tlog"),
        "--video-start",
        str(synth.EPOCH_UNIX_S),
        "--calibration",
        str(short_nadir / "intrinsics.json"),
    )
    assert r.returncode == 0, r.stderr
    d = doctor(rec)
    text = " ".join(d.stdout.split())
    assert d.returncode == 0 and "passed MCAP doctor checks" in text, d.stdout + d.stderr
    assert "warning" not in text.lower(), text  # formats.md: "without warnings"

    msgs = messages(rec)
    rows = keyframe_rows(out)
    assert len(rows) >= 5
    summary = json.loads((out / "summary.json").read_text())

    # One keyframe message per kept frame, byte-identical to the tagged JPEG, decoded
    # with Foxglove's own schema (field numbers must match theirs).
    kf = [(m, CompressedImage.FromString(m.data)) for m in by_topic(msgs, "/keyframed/keyframe")]
    assert len(kf) == len(rows) == summary["kept"]
    for (m, img), row in zip(sorted(kf, key=lambda x: x[0].sequence), rows, strict=True):
        assert img.data == (out / row["file"]).read_bytes()
        assert img.format == "jpeg" and img.frame_id == "camera"
        assert m.sequence == int(row["sequence"]) + 1
        assert m.log_time == int(row["time_ns"])
        assert img.timestamp.seconds * 10**9 + img.timestamp.nanos == int(row["time_ns"])

    meta = [json.loads(m.data) for m in by_topic(msgs, "/keyframed/keyframe_meta")]
    assert [x["file"] for x in meta] == [row["file"] for row in rows]
    assert all(x["scores"] is not None for x in meta)

    # Every analysed frame has its decision.
    dec = [json.loads(m.data) for m in by_topic(msgs, "/keyframed/decision")]
    assert sorted(x["index"] for x in dec) == list(range(summary["frames_read"]))
    # a kept frame's row says how it was tagged, as decisions.csv does
    kept_rows = {int(r["index"]): r for r in csv.DictReader((out / "decisions.csv").open())}
    kept = [x for x in dec if x["kept"]]
    assert kept and all(x["geotag"] == kept_rows[x["index"]]["geotag"] for x in kept), kept

    # Poses and calibration, also with Foxglove's schemas.
    fixes = [LocationFix.FromString(m.data) for m in by_topic(msgs, "/keyframed/location")]
    assert len(fixes) == summary["telemetry"]["geotagged"] > 0
    tagged = [row for row in rows if row["lat"]]
    for fix, row in zip(fixes, tagged, strict=True):
        assert fix.latitude == pytest.approx(float(row["lat"]), abs=1e-8)
        assert fix.longitude == pytest.approx(float(row["lon"]), abs=1e-8)
    poses = [PoseInFrame.FromString(m.data) for m in by_topic(msgs, "/keyframed/camera_pose")]
    assert len(poses) == len([row for row in rows if row["cam_qw"]])
    for p in poses:
        q = p.pose.orientation
        assert q.x**2 + q.y**2 + q.z**2 + q.w**2 == pytest.approx(1.0, abs=1e-6)
    (cal_msg,) = by_topic(msgs, "/camera/calibration")
    cal = CameraCalibration.FromString(cal_msg.data)
    intr = json.loads((short_nadir / "intrinsics.json").read_text())
    assert (cal.width, cal.height) == (480, 270)
    assert cal.K[0] == pytest.approx(intr["fx"] * 480 / intr["width"], rel=1e-6)

    # The schemas in the file decode the messages on their own (mcap-protobuf-support).
    with rec.open("rb") as fh:
        reader = mcap_reader.make_reader(fh, decoder_factories=[DecoderFactory()])
        channels = reader.get_summary().channels.values()
        proto_topics = [c.topic for c in channels if c.message_encoding == "protobuf"]
        decoded = [m for _, _, _, m in reader.iter_decoded_messages(topics=proto_topics)]
    # The tlog's packets ride along, with the autopilot's track and attitude decoded.
    raw = by_topic(msgs, "/mavlink/raw")
    track = by_topic(msgs, "/vehicle/location") + by_topic(msgs, "/vehicle/pose")
    assert len(raw) == len(read_tlog(short_nadir / "flight.tlog")) and len(track) > len(kf)
    # + calibration + log
    assert len(decoded) == len(kf) + len(fixes) + len(poses) + len(raw) + len(track) + 2


# ---- (b) crash safety ----------------------------------------------------------------


def test_sigkill_loses_at_most_the_last_second(kf_bin: Path, short_nadir: Path, tmp_path: Path):
    out, rec = tmp_path / "out", tmp_path / "killed.mcap"
    # --realtime: frames come at the video's 30 fps, as from a camera.
    p = subprocess.Popen(
        [str(kf_bin), "select", str(short_nadir / "video.avi"), "--out", str(out), "--quiet"]
        + ["--realtime", "--mcap", str(rec)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    time.sleep(4.0)
    p.send_signal(signal.SIGKILL)
    p.wait(timeout=10)
    rows = keyframe_rows(out)  # flushed row by row
    msgs = messages(rec, seeking=False)
    dec = sorted(json.loads(m.data)["index"] for m in by_topic(msgs, "/keyframed/decision"))
    # About 4 s at 30 fps were analysed; the timed flush (1 s) keeps all but the last
    # second or so (allow 1.5 s for start-up and a loaded machine).
    assert dec == list(range(len(dec)))
    assert len(dec) >= 30 * 4 - 30 * 2.5, len(dec)
    # Every keyframe before the last recovered decision is there, byte-identical.
    images = {
        m.sequence - 1: CompressedImage.FromString(m.data).data
        for m in by_topic(msgs, "/keyframed/keyframe")
    }
    expected = [row for row in rows if int(row["index"]) <= dec[-1]]
    assert len(expected) >= 1
    for row in expected:
        assert images[int(row["sequence"])] == (out / row["file"]).read_bytes()


# ---- disk full: the recorder stops, the run goes on ----------------------------------


def test_write_error_stops_only_the_recorder(kf_bin: Path, pan_video: Path, tmp_path: Path):
    out, rec = tmp_path / "out", tmp_path / "full.mcap"

    def limit_file_size() -> None:
        # Any file larger than 200 kB fails to grow (EFBIG), as on a full disk;
        # keyframes (about 50 kB each) still fit.
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, 200_000))

    r = select(kf_bin, pan_video, out, "--mcap", str(rec), preexec_fn=limit_file_size)
    assert r.returncode == 0, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if "MCAP recorder stopped" in ln]
    assert len(lines) == 1, r.stderr
    assert str(rec) in lines[0]
    assert "File too large" in lines[0], lines[0]  # the OS's reason, not only "I/O error"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["kept"] == len(keyframe_rows(out)) >= 2
    # Not a failure of the run, but said in the summary a script reads.
    assert summary["error"] == "" and "File too large" in summary["record_error"], summary
    whole = select(kf_bin, pan_video, tmp_path / "whole", "--mcap", str(tmp_path / "ok.mcap"))
    assert whole.returncode == 0, whole.stderr
    assert json.loads((tmp_path / "whole" / "summary.json").read_text())["record_error"] == ""


# ---- (c) Zenoh --------------------------------------------------------------------------


def peer_config(listen: list[str] | None = None, connect: list[str] | None = None) -> str:
    return json.dumps(
        {
            "mode": "peer",
            "scouting": {"multicast": {"enabled": False}},
            "listen": {"endpoints": listen or []},
            "connect": {"endpoints": connect or []},
        }
    )


@pytest.mark.parametrize("transport", ["tcp", "udp"])
def test_zenoh_subscriber_receives_every_keyframe_and_can_query(
    kf_bin: Path, pan_video: Path, tmp_path: Path, transport: str
):
    """Over TCP, and over UDP (a radio link's usual transport): every keyframe, whole."""
    port = free_port(socket.SOCK_DGRAM if transport == "udp" else socket.SOCK_STREAM)
    endpoint = f"{transport}/127.0.0.1:{port}"
    cfg = tmp_path / "zenoh.json5"
    cfg.write_text(peer_config(connect=[endpoint]))
    out = tmp_path / "out"

    received: list[tuple[str, bytes, dict[str, Any]]] = []
    receipt_ns: list[int] = []  # CLOCK_MONOTONIC, as the daemon's stamps with --realtime
    status: list[dict[str, Any]] = []

    def on_keyframe(s: Any) -> None:
        receipt_ns.append(time.monotonic_ns())
        received.append(
            (str(s.key_expr), s.payload.to_bytes(), json.loads(s.attachment.to_bytes()))
        )

    session = zenoh.open(zenoh.Config.from_json5(peer_config(listen=[endpoint])))
    try:
        sub = session.declare_subscriber("keyframed/test1/keyframe", on_keyframe)
        st = session.declare_subscriber(
            "keyframed/test1/status", lambda s: status.append(json.loads(s.payload.to_bytes()))
        )
        # --realtime keeps the daemon (and its queryable) up for the video's 3 s.
        p = subprocess.Popen(
            [str(kf_bin), "select", str(pan_video), "--out", str(out), "--quiet", "--realtime"]
            + ["--zenoh-config", str(cfg), "--vehicle", "test1"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        deadline = time.monotonic() + 20
        while not received and time.monotonic() < deadline and p.poll() is None:
            time.sleep(0.01)
        assert received, "no keyframe arrived"
        # The daemon is still running: fetch keyframe 0 from its store, and all of them.
        replies = list(session.get("keyframed/test1/keyframes/0", timeout=5.0))
        one = [r.ok for r in replies if r.ok is not None]
        assert len(one) == 1, [r.err.payload.to_string() for r in replies if r.err]
        assert str(one[0].key_expr) == "keyframed/test1/keyframes/0"
        first_file = json.loads(one[0].attachment.to_bytes())["file"]
        assert one[0].payload.to_bytes() == (out / first_file).read_bytes()
        missing = list(session.get("keyframed/test1/keyframes/999999", timeout=5.0))
        assert missing and missing[0].err is not None
        assert "no keyframe" in missing[0].err.payload.to_string()
        # A number outside the query's own range: said so, stored or not.
        outside = list(session.get("keyframed/test1/keyframes/0?range=1..3", timeout=5.0))
        assert outside and outside[0].err is not None
        assert "outside the range" in outside[0].err.payload.to_string()
        # "00" parses as 0, but a reply on keyframes/0 would not match the query's key
        # and it would go unanswered: refused, saying why.
        odd = list(session.get("keyframed/test1/keyframes/00", timeout=5.0))
        assert odd and odd[0].err is not None
        assert "not a keyframe sequence number: '00'" in odd[0].err.payload.to_string()
        # Another flight's keyframes by name: never a path out of the store.
        for flight in ("..", "../../etc", "nope"):
            ans = list(session.get(f"keyframed/test1/keyframes/0?flight={flight}", timeout=5.0))
            assert ans and ans[0].err is not None, flight
            assert f"no flight '{flight}' here" in ans[0].err.payload.to_string()
        stdout, stderr = p.communicate(timeout=60)
        assert p.returncode == 0, stderr
        time.sleep(0.2)
        sub.undeclare()
        st.undeclare()
    finally:
        session.close()

    rows = keyframe_rows(out)
    assert len(rows) >= 2
    assert len(received) == len(rows)
    for (key, payload, meta), row, got in zip(received, rows, receipt_ns, strict=True):
        assert key == "keyframed/test1/keyframe"
        assert payload == (out / row["file"]).read_bytes()
        assert meta["vehicle"] == "test1"
        assert meta["sequence"] == int(row["sequence"])
        assert meta["frame_index"] == int(row["index"])
        assert meta["time_ns"] == int(row["time_ns"])
        # Captured, then decided, then received: the stamps the latency benchmark uses.
        assert meta["time_ns"] <= meta["decided_ns"] <= got, (meta, got)
        assert meta["file"] == row["file"]
        assert set(meta["scores"]) >= {"sharpness", "threshold", "overlap", "features"}
    assert status and status[-1]["state"] == "done"
    assert status[-1]["kept"] == len(rows)


def test_two_select_runs_of_one_vehicle_reach_a_ground_station_apart(
    kf_bin: Path, pan_video: Path, tmp_path: Path
) -> None:
    """Every `select` run numbers its keyframes from 0. Each names a flight of its own
    (its start, UTC to the ms), so a ground station that stored the first run keeps the
    second's as another flight instead of dropping them as duplicates."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    cfg = tmp_path / "zenoh.json5"
    cfg.write_text(peer_config(connect=[endpoint]))
    dataset = tmp_path / "dataset"
    ground = subprocess.Popen(
        [sys.executable, "-m", "keyframed.ground", "--out", str(dataset), "--quiet"]
        + ["--listen", endpoint, "--until-idle", "4", "--vehicle", "uav9"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 30
        while True:  # until the station listens
            with socket.socket() as probe:
                if probe.connect_ex(("127.0.0.1", port)) == 0:
                    break
            assert ground.poll() is None and time.monotonic() < deadline, "no ground station"
            time.sleep(0.1)
        runs = []
        for n in (1, 2):
            out = tmp_path / f"run{n}"
            r = select(
                kf_bin, pan_video, out, "--realtime", "--zenoh-config", str(cfg),
                "--vehicle", "uav9", timeout=60,
            )  # fmt: skip
            assert r.returncode == 0, r.stderr
            runs.append(out)
        stdout, stderr = ground.communicate(timeout=60)
    finally:
        if ground.poll() is None:
            ground.kill()
            ground.communicate()
    assert ground.returncode == 0, stderr
    summary = json.loads(stdout.strip().splitlines()[-1])
    sent = [(out / row["file"]).read_bytes() for out in runs for row in keyframe_rows(out)]
    assert len(keyframe_rows(runs[0])) >= 2 and len(keyframe_rows(runs[1])) >= 2
    assert summary["keyframes"] == len(sent) and summary["missing"] == [], summary
    assert summary["last_flight_ended"] is True, summary  # the second run's final status
    assert "has not ended" not in stderr, stderr
    stored = [p.read_bytes() for p in (dataset / "uav9" / "images").glob("*.jpg")]
    assert sorted(stored) == sorted(sent)
    with (dataset / "uav9" / "keyframes.jsonl").open() as fh:
        flights = [json.loads(line)["flight"] for line in fh]
    assert len(set(flights)) == 2 and all(f and f.endswith("Z") for f in flights), flights


def test_a_query_gets_at_most_64_keyframes_and_where_to_go_on(
    kf_bin: Path, pan_video: Path, tmp_path: Path
):
    """A query for a whole flight (here an earlier one of 70 keyframes, served from its
    directory) is answered with 64 keyframes and an error reply naming the range that
    follows, which brings the rest."""
    state = tmp_path / "state"
    earlier = state / "flights" / "20260101T000000Z" / "keyframes"
    earlier.mkdir(parents=True)
    lines = ["sequence,index,time_ns,file"]
    for i in range(70):
        (earlier / f"{i:06d}.jpg").write_bytes(b"\xff\xd8 keyframe %d \xff\xd9" % i)
        lines.append(f"{i},{10 * i},{1000 * i},{i:06d}.jpg")
    (earlier / "keyframes.csv").write_text("\n".join(lines) + "\n")
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    cfg = tmp_path / "zenoh.json5"
    cfg.write_text(peer_config(connect=[endpoint]))
    (tmp_path / "etc").mkdir()
    args = [str(kf_bin), "run", "--config-dir", str(tmp_path / "etc")]
    for s in (
        f"output.state_dir={state}",
        f"zenoh.config={cfg}",
        "zenoh.vehicle=capped",
        "telemetry.url=",
        "camera.source=file",
        f"camera.path={pan_video}",  # 3 s in real time: the queryable is up meanwhile
        "output.mcap=false",
    ):
        args += ["--set", s]
    session = zenoh.open(zenoh.Config.from_json5(peer_config(listen=[endpoint])))
    p = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        key = "keyframed/capped/keyframes/*"
        replies: list[Any] = []
        deadline = time.monotonic() + 20
        while not replies and time.monotonic() < deadline and p.poll() is None:
            replies = list(session.get(f"{key}?flight=20260101T000000Z", timeout=5.0))
        # Zenoh's default consolidation may hand the replies over in any order.
        ok = {str(r.ok.key_expr): r.ok for r in replies if r.ok is not None}
        errors = [r.err.payload.to_string() for r in replies if r.err is not None]
        assert sorted(ok) == sorted(f"keyframed/capped/keyframes/{i}" for i in range(64))
        assert (
            ok["keyframed/capped/keyframes/5"].payload.to_bytes()
            == (earlier / "000005.jpg").read_bytes()
        )
        # The parameters to go on with, the flight kept: followed as they stand.
        hint = "at most 64 keyframes a query: ask again with "
        assert errors == [hint + "range=64..;flight=20260101T000000Z"], errors
        rest = list(session.get(f"{key}?{errors[0].removeprefix(hint)}", timeout=5.0))
        assert sorted(str(r.ok.key_expr) for r in rest if r.ok is not None) == sorted(
            f"keyframed/capped/keyframes/{i}" for i in range(64, 70)
        )
        assert not [r for r in rest if r.err is not None]
        # A range's end is kept too.
        part = list(session.get(f"{key}?flight=20260101T000000Z;range=1..66", timeout=5.0))
        errors = [r.err.payload.to_string() for r in part if r.err is not None]
        assert errors == [hint + "range=65..66;flight=20260101T000000Z"], errors
        rest = list(session.get(f"{key}?{errors[0].removeprefix(hint)}", timeout=5.0))
        assert sorted(str(r.ok.key_expr) for r in rest if r.ok is not None) == [
            "keyframed/capped/keyframes/65",
            "keyframed/capped/keyframes/66",
        ]
        p.send_signal(signal.SIGTERM)
        _, stderr = p.communicate(timeout=30)
        assert p.returncode == 0, stderr
    finally:
        if p.poll() is None:
            p.kill()
        session.close()


# ---- (d) bad input ---------------------------------------------------------------------


def test_unwritable_mcap_path_is_a_clear_error(kf_bin: Path, pan_video: Path, tmp_path: Path):
    bad = tmp_path / "no-such-dir" / "x.mcap"
    r = select(kf_bin, pan_video, tmp_path / "out", "--mcap", str(bad))
    assert r.returncode != 0
    assert "--mcap" in r.stderr and str(bad) in r.stderr, r.stderr
    assert r.stderr.count("\n") <= 2, r.stderr
    # nothing was selected: the same command corrected is not refused for an earlier run
    r = select(kf_bin, pan_video, tmp_path / "out", "--max-frames", "5")
    assert r.returncode == 0, r.stderr


def test_an_mcap_path_naming_an_input_or_output_is_refused(
    kf_bin: Path, pan_video: Path, tmp_path: Path
):
    """--mcap onto the video, the record being replayed, the calibration or the run's
    own summary would destroy it: refused before anything is opened, the file intact."""
    video = tmp_path / "video.avi"
    shutil.copyfile(pan_video, video)
    (tmp_path / "link.avi").symlink_to(video)
    record = tmp_path / "rec.mcap"
    r = select(kf_bin, pan_video, tmp_path / "first", "--mcap", str(record), "--max-frames", "5")
    assert r.returncode == 0, r.stderr
    calib = tmp_path / "calib.yaml"
    calib.write_text("%YAML:1.0\n---\nimage_width: 320\n")
    out = tmp_path / "out"
    cases = [
        (video, [], tmp_path / "link.avi"),  # another spelling of the same file
        (record, [], record),
        (video, ["--calibration", str(calib)], calib),
        (video, [], out / "summary.json"),
    ]
    for source, extra, mcap in cases:
        before = Path(mcap).resolve().read_bytes() if Path(mcap).exists() else None
        r = select(kf_bin, source, out, "--mcap", str(mcap), *extra)
        assert r.returncode != 0 and "would overwrite it" in r.stderr, (mcap, r.stderr)
        if before is not None:
            assert Path(mcap).resolve().read_bytes() == before, mcap
        assert not out.exists() or not list(out.iterdir()), list(out.iterdir())


@pytest.mark.parametrize(
    "text, words",
    [
        ("{ mode: 'peer', this is not json5 ", "zenoh config"),
        ('{ "mode": "satellite" }', "zenoh config"),
        (None, "zenoh config"),  # missing file
    ],
)
def test_bad_zenoh_config_is_a_clear_error(
    kf_bin: Path, pan_video: Path, tmp_path: Path, text: str | None, words: str
):
    cfg = tmp_path / "zenoh.json5"
    if text is not None:
        cfg.write_text(text)
    r = select(kf_bin, pan_video, tmp_path / "out", "--zenoh-config", str(cfg), timeout=60)
    assert r.returncode != 0
    assert "--zenoh-config" in r.stderr and words in r.stderr, r.stderr
    assert "panic" not in r.stderr
    # nothing was selected: no earlier run's output is left to refuse the next run for
    assert not (tmp_path / "out" / "keyframes.csv").exists()
    assert not (tmp_path / "out" / "decisions.csv").exists()


def test_bad_vehicle_name_is_rejected(kf_bin: Path, pan_video: Path, tmp_path: Path):
    # the rule of zenoh.vehicle and keyframed-ground's --vehicle, one for all three
    for name in ("a/b", "@x", "uav:1", "x" * 65, "..", "ü"):
        r = select(kf_bin, pan_video, tmp_path / "out", "--vehicle", name, "--zenoh-config", "x")
        assert r.returncode == 2, (name, r.stderr)
        assert "--vehicle: vehicle name may hold only" in r.stderr, (name, r.stderr)
