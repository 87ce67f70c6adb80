"""The fake autopilot, driven by a pymavlink client playing the daemon's part."""

from __future__ import annotations

import math
import socket
import statistics
import time
from pathlib import Path

import numpy as np
import pytest
from fake_autopilot import (
    MAV_CMD_REQUEST_MESSAGE,
    FakeAutopilot,
    Message,
    Noise,
    autopilot_fixture,
    read_tlog,
    timesync_target,
)
from flights import flight
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

fake_autopilot = autopilot_fixture()

CAMERA_SYS, CAMERA_COMP = 1, 100  # the daemon: a camera component on the vehicle


@pytest.fixture(scope="module")
def tlog() -> Path:
    return flight("nadir", seconds=3, width=320, height=180) / "flight.tlog"


def connect(ap: FakeAutopilot, timeout: float = 2.0) -> mavutil.mavfile:
    """A daemon-like client: udpout to the autopilot, HEARTBEAT first."""
    conn = mavutil.mavlink_connection(
        f"udpout:127.0.0.1:{ap.port}",
        source_system=CAMERA_SYS,
        source_component=CAMERA_COMP,
        robust_parsing=True,
    )
    conn.mav.heartbeat_send(mavlink.MAV_TYPE_CAMERA, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    return conn


def collect(conn: mavutil.mavfile, seconds: float, types: list[str] | None = None) -> list:
    """(monotonic_ns at receipt, message) for everything heard within ``seconds``."""
    out = []
    deadline = time.monotonic() + seconds
    while (left := deadline - time.monotonic()) > 0:
        msg = conn.recv_match(type=types, blocking=True, timeout=min(left, 0.05))
        if msg is not None:
            out.append((time.monotonic_ns(), msg))
    return out


def started(ap: FakeAutopilot, conn: mavutil.mavfile) -> FakeAutopilot:
    """Start once the autopilot heard the client (so no message is lost to no-peer)."""
    ap.start()
    ap.wait_for("HEARTBEAT", timeout=2.0)
    return ap


def fields(msg: Message) -> dict:
    d = msg.to_dict()
    d.pop("mavpackettype")
    return d


def test_read_tlog(tlog):
    recs = read_tlog(tlog)
    kinds = [r.type for r in recs]
    span_s = (recs[-1].unix_us - recs[0].unix_us) / 1e6
    assert 5.5 < span_s < 6.5  # 2 s before frame 0, 3 s of video, 1 s after
    for kind, rate in (("ATTITUDE", 50), ("GLOBAL_POSITION_INT", 10), ("GPS_RAW_INT", 5)):
        assert abs(kinds.count(kind) - rate * span_s) <= 2
    assert [r.unix_us for r in recs] == sorted(r.unix_us for r in recs)
    systime = next(r for r in recs if r.type == "SYSTEM_TIME")
    assert systime.msg.time_unix_usec == systime.unix_us


def test_realtime_rates_offset_and_pacing(tlog, fake_autopilot):
    offset = -20_000
    ap = fake_autopilot(tlog, boot_offset_ms=offset)
    conn = connect(ap)
    started(ap, conn)
    got = collect(conn, 1.3)
    att = [(t, m) for t, m in got if m.get_type() == "ATTITUDE"]
    # 50 Hz, by the autopilot's own send times (a receiver held up on a busy machine
    # would count them late, in the next window)
    in_1s = [
        r
        for r in ap.sent("ATTITUDE")
        if ap.start_monotonic_ns + 0.2e9 <= r.monotonic_ns < ap.start_monotonic_ns + 1.2e9
    ]
    assert 40 <= len(in_1s) <= 60
    gpi = [m for _, m in got if m.get_type() == "GLOBAL_POSITION_INT"]
    assert 10 <= len(gpi) <= 16
    assert all(m.get_msgbuf()[0] == 0xFD for _, m in got)  # MAVLink 2
    assert {(m.get_srcSystem(), m.get_srcComponent()) for _, m in got} == {(1, 1)}

    # the k-th replayed ATTITUDE is the tlog's k-th with time_boot_ms shifted
    truth = ap.tlog_messages("ATTITUDE")
    lags_ms = []
    for k, (t_recv, msg) in enumerate(att):
        want = fields(truth[k].msg)
        want["time_boot_ms"] += offset
        assert fields(msg) == want
        # paced on the tlog clock: never early (a loaded machine may make it late)
        lags_ms.append((t_recv - ap.monotonic_ns_for_unix_us(truth[k].unix_us)) / 1e6)
        assert lags_ms[-1] > -1.0
        # the boot clock mapping agrees with the stamp the message carries
        t_boot = ap.monotonic_ns_for_boot_ms(msg.time_boot_ms)
        assert abs(t_boot - ap.monotonic_ns_for_unix_us(truth[k].unix_us)) < 1e6
    assert statistics.median(lags_ms) < 150.0
    sent = ap.sent("ATTITUDE")  # the autopilot's own send times, nearer the truth
    assert (
        statistics.median(r.monotonic_ns - ap.monotonic_ns_for_unix_us(r.unix_us) for r in sent)
        < 50e6
    )
    seqs = [m.get_seq() for _, m in got]
    assert all((b - a) % 256 == 1 for a, b in zip(seqs, seqs[1:], strict=False))


def test_fast_replay_is_exact_and_finishes(tlog, fake_autopilot):
    ap = fake_autopilot(tlog, boot_offset_ms=5000, speed=5.0)
    conn = connect(ap)
    started(ap, conn)
    # read while it plays: a socket buffer holds only a few hundred datagrams
    got = [m for _, m in collect(conn, ap.replay_seconds + 0.3)]
    assert ap.finished.is_set()
    assert len(got) == len(ap.records)
    for rec, msg in zip(ap.records, got, strict=True):
        want = fields(rec.msg)
        if "time_boot_ms" in want:
            want["time_boot_ms"] += 5000
        assert msg.get_type() == rec.type
        assert fields(msg) == want
    assert [m.get_seq() for m in got] == [i % 256 for i in range(len(got))]
    assert ap.dropped == 0
    assert len(ap.sent()) == len(ap.records) + 0  # no TIMESYNC asked, nothing else sent
    assert ap.alive  # still listening (and answering TIMESYNC) after the tlog ends


def test_timesync_answers_with_the_shifted_boot_clock(tlog, fake_autopilot):
    offset = 3_600_000
    ap = fake_autopilot(tlog, boot_offset_ms=offset)
    conn = connect(ap)
    started(ap, conn)
    conn.recv_match(type="ATTITUDE", blocking=True, timeout=1.0)
    for i in range(5):
        ts1 = time.monotonic_ns() + i
        t_send = time.monotonic_ns()
        conn.mav.timesync_send(0, ts1)
        reply = None
        last_att = None
        while reply is None:
            msg = conn.recv_match(type=["TIMESYNC", "ATTITUDE"], blocking=True, timeout=1.0)
            assert msg is not None, "no TIMESYNC reply"
            t_recv = time.monotonic_ns()
            if msg.get_type() == "ATTITUDE":
                last_att = (t_recv, msg)
            else:
                reply = msg
        assert reply.ts1 == ts1
        assert reply.tc1 != 0
        assert (t_recv - t_send) < 100e6
        # tc1 is the autopilot's boot clock in ns, offset included: compare with the
        # time_boot_ms the replayed stream carries, advanced by the local time since
        mid = (t_send + t_recv) // 2
        expect_ms = ap.boot_ms_at_monotonic_ns(mid)
        assert abs(reply.tc1 / 1e6 - expect_ms) < 20.0
        if last_att is not None:
            t_att, att = last_att
            from_stream = att.time_boot_ms + (t_recv - t_att) / 1e6
            assert abs(reply.tc1 / 1e6 - from_stream) < 20.0
        assert timesync_target(reply) == (CAMERA_SYS, CAMERA_COMP)
    assert len(ap.received("TIMESYNC")) == 5
    # a TIMESYNC response (tc1 != 0), or a request for another system, is not answered
    n_sent = len(ap.sent("TIMESYNC"))
    conn.mav.timesync_send(123, 456)
    ap.wait_for("TIMESYNC", count=6)
    time.sleep(0.1)
    assert len(ap.sent("TIMESYNC")) == n_sent


def test_noise_has_the_requested_sigma(tlog, fake_autopilot):
    noise = Noise(attitude_deg=2.0, position_m=3.0, altitude_m=1.5)
    ap = fake_autopilot(tlog, noise=noise, seed=7, speed=6.0)
    conn = connect(ap)
    started(ap, conn)
    # read while it plays: a socket buffer holds only a few hundred datagrams
    got = [m for _, m in collect(conn, ap.replay_seconds + 0.3)]
    assert ap.finished.is_set()
    assert len(got) == len(ap.records)
    sig = math.radians(noise.attitude_deg)

    def pairs(kind: str) -> list:
        truth = [r.msg for r in ap.records if r.type == kind]
        recv = [m for m in got if m.get_type() == kind]
        assert len(truth) == len(recv)
        return list(zip(truth, recv, strict=True))

    att = pairs("ATTITUDE")
    for name in ("roll", "pitch"):
        d = np.array([getattr(m, name) - getattr(t, name) for t, m in att])
        assert abs(d.std() / sig - 1.0) < 0.2
        assert abs(d.mean()) < 4 * sig / math.sqrt(len(d))
    dyaw = np.array([(m.yaw - t.yaw + math.pi) % (2 * math.pi) - math.pi for t, m in att])
    assert abs(dyaw.std() / sig - 1.0) < 0.2
    assert all(m.time_boot_ms == t.time_boot_ms for t, m in att)

    rotvecs = []
    for t, m in pairs("ATTITUDE_QUATERNION"):
        qt = np.array([t.q1, t.q2, t.q3, t.q4])
        qm = np.array([m.q1, m.q2, m.q3, m.q4])
        assert abs(np.linalg.norm(qm) - 1.0) < 1e-6
        # body-frame error rotation conj(qt) * qm, small: its vector part * 2
        w = qt @ qm
        v = qt[0] * qm[1:] - qm[0] * qt[1:] - np.cross(qt[1:], qm[1:])
        rotvecs.append(2.0 * v * np.sign(w))
    rv = np.array(rotvecs)
    assert np.all(np.abs(rv.std(axis=0) / sig - 1.0) < 0.2)

    metres_per_deg_lat = 111_200.0
    for kind, tol in (("GLOBAL_POSITION_INT", 0.3), ("GPS_RAW_INT", 0.4)):
        pp = pairs(kind)
        lat0 = math.radians(pp[0][0].lat * 1e-7)
        dn = np.array([(m.lat - t.lat) * 1e-7 * metres_per_deg_lat for t, m in pp])
        de = np.array([(m.lon - t.lon) * 1e-7 * metres_per_deg_lat * math.cos(lat0) for t, m in pp])
        du = np.array([(m.alt - t.alt) / 1000.0 for t, m in pp])
        assert abs(dn.std() / noise.position_m - 1.0) < tol
        assert abs(de.std() / noise.position_m - 1.0) < tol
        assert abs(du.std() / noise.altitude_m - 1.0) < tol
        if kind == "GLOBAL_POSITION_INT":
            d_rel = np.array([(m.relative_alt - t.relative_alt) / 1000.0 for t, m in pp])
            assert np.array_equal(d_rel, du)  # the whole altitude moves, not one field


def test_noise_is_deterministic_for_a_seed(tlog):
    noise = Noise(attitude_deg=1.0, position_m=1.0, altitude_m=1.0)

    def values(seed: int) -> list:
        ap = FakeAutopilot(tlog, noise=noise, seed=seed)
        ap.stop()
        return [fields(r.msg) for r in ap.planned()]

    assert values(3) == values(3)
    assert values(3) != values(4)
    ap = FakeAutopilot(tlog)
    ap.stop()
    assert [fields(r.msg) for r in ap.planned()] == [fields(r.msg) for r in ap.records]


def test_mavlink1_mode(tlog, fake_autopilot):
    ap = fake_autopilot(tlog, mavlink1=True, boot_offset_ms=100)
    client = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    client.settimeout(0.2)
    try:
        mav = mavlink.MAVLink(None, srcSystem=CAMERA_SYS, srcComponent=CAMERA_COMP)
        hb = mav.heartbeat_encode(mavlink.MAV_TYPE_CAMERA, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        client.sendto(hb.pack(mav), ("127.0.0.1", ap.port))
        ap.start()
        datagrams = []
        deadline = time.monotonic() + 0.6
        while time.monotonic() < deadline:
            try:
                datagrams.append(client.recv(2048))
            except TimeoutError:
                pass
    finally:
        client.close()
    assert len(datagrams) > 20
    assert all(d[0] == 0xFE for d in datagrams)
    parser = mavlink.MAVLink(None)
    msgs = [parser.decode(bytearray(d)) for d in datagrams]
    assert [m.get_seq() for m in msgs] == list(range(len(msgs)))
    truth = ap.tlog_messages("ATTITUDE")
    atts = [m for m in msgs if m.get_type() == "ATTITUDE"]
    assert atts and atts[0].time_boot_ms == truth[0].msg.time_boot_ms + 100
    gps = next(m for m in msgs if m.get_type() == "GPS_RAW_INT")
    assert gps.alt_ellipsoid == 0  # MAVLink 1 carries no extension fields


def test_pause_drops_the_link(tlog, fake_autopilot):
    ap = fake_autopilot(tlog)
    conn = connect(ap)
    started(ap, conn)
    before = collect(conn, 0.3, ["ATTITUDE"])
    assert len(before) >= 10
    ap.pause()
    assert ap.paused
    collect(conn, 0.05)  # whatever was in flight
    t_pause = time.monotonic_ns()
    conn.mav.heartbeat_send(mavlink.MAV_TYPE_CAMERA, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    n_hb = len(ap.received("HEARTBEAT"))
    assert collect(conn, 0.5) == []
    assert len(ap.received("HEARTBEAT")) == n_hb  # not heard while the link is down
    assert ap.dropped > 20
    ap.resume()
    after = collect(conn, 0.3, ["ATTITUDE"])
    assert len(after) >= 10
    last, first = before[-1][1], after[0][1]
    # the messages due meanwhile were lost, not queued: a jump in time and sequence
    gap_ms = first.time_boot_ms - last.time_boot_ms
    paused_ms = (after[0][0] - t_pause) / 1e6
    assert gap_ms >= paused_ms - 50
    # and the lost ones used up their sequence numbers, as on a real link
    index = {r.msg.time_boot_ms: i for i, r in enumerate(ap.records) if r.type == "ATTITUDE"}
    assert last.get_seq() == index[last.time_boot_ms] % 256
    assert first.get_seq() == index[first.time_boot_ms] % 256
    # nothing arrives late either: the first after resume is fresh
    lag_ms = (after[0][0] - ap.monotonic_ns_for_boot_ms(first.time_boot_ms)) / 1e6
    assert lag_ms < 100


def test_records_client_messages_and_requests_messages(tlog, fake_autopilot):
    ap = fake_autopilot(tlog, start_delay_s=10.0)  # nothing replayed in this test
    conn = connect(ap)
    ap.start()
    conn.mav.command_ack_send(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAV_RESULT_ACCEPTED)
    conn.mav.statustext_send(mavlink.MAV_SEVERITY_INFO, b"keyframe 1")
    conn.mav.heartbeat_send(mavlink.MAV_TYPE_CAMERA, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    hbs = ap.wait_for("HEARTBEAT", count=2)
    ack = ap.wait_for("COMMAND_ACK")[0]
    assert ack.command == MAV_CMD_REQUEST_MESSAGE
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    assert ap.wait_for("STATUSTEXT")[0].text == "keyframe 1"
    assert [m.get_type() for m in ap.received()] == [
        "HEARTBEAT",
        "COMMAND_ACK",
        "STATUSTEXT",
        "HEARTBEAT",
    ]
    assert {(m.get_srcSystem(), m.get_srcComponent()) for m in hbs} == {(CAMERA_SYS, CAMERA_COMP)}
    times = [t for t, _ in ap.received_with_times()]
    assert times == sorted(times)
    with pytest.raises(TimeoutError):
        ap.wait_for("CAMERA_INFORMATION", timeout=0.1)

    # the autopilot asks the camera for a message: to the ids it heard by default
    assert ap.request_message(mavlink.MAVLINK_MSG_ID_CAMERA_INFORMATION)
    assert ap.request_message(mavlink.MAVLINK_MSG_ID_CAMERA_SETTINGS, 0, target_component=0)
    cmds = [m for _, m in collect(conn, 0.3, ["COMMAND_LONG"])]
    assert len(cmds) == 2
    assert cmds[0].command == MAV_CMD_REQUEST_MESSAGE
    assert cmds[0].param1 == mavlink.MAVLINK_MSG_ID_CAMERA_INFORMATION
    assert (cmds[0].target_system, cmds[0].target_component) == (CAMERA_SYS, CAMERA_COMP)
    assert (cmds[1].target_system, cmds[1].target_component) == (CAMERA_SYS, 0)
    assert cmds[1].param1 == mavlink.MAVLINK_MSG_ID_CAMERA_SETTINGS
    assert (cmds[0].get_srcSystem(), cmds[0].get_srcComponent()) == (1, 1)
    ap.clear_received()
    assert ap.received() == []


def test_garbage_is_skipped_and_the_stream_goes_on(tlog, fake_autopilot):
    ap = fake_autopilot(tlog, seed=5)
    conn = connect(ap)
    started(ap, conn)
    assert len(collect(conn, 0.2, ["ATTITUDE"])) >= 5
    junk = ap.inject_garbage(300)
    assert len(junk) == 300 and not ({0xFD, 0xFE} & set(junk))
    got = [m for _, m in collect(conn, 0.4)]
    bad = [m for m in got if m.get_type() == "BAD_DATA"]
    assert bad and b"".join(bytes(m.data) for m in bad) == junk
    assert conn.mav.total_receive_errors >= 1
    assert sum(m.get_type() == "ATTITUDE" for m in got) >= 15

    # bogus headers may swallow what follows, but the parser resynchronises
    junk = ap.inject_garbage(200, with_magic=True)
    assert junk[0] == 0xFD
    got = [m for _, m in collect(conn, 0.6)]
    assert sum(m.get_type() == "ATTITUDE" for m in got[-20:]) >= 8

    # the other way round: garbage from the daemon is counted, not recorded
    conn.write(bytes(range(200)))
    conn.mav.heartbeat_send(mavlink.MAV_TYPE_CAMERA, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    ap.wait_for("HEARTBEAT", count=2)
    assert ap.receive_errors >= 1
    assert "BAD_DATA" not in {m.get_type() for m in ap.received()}


def test_target_mode_sends_without_hearing_first(tlog, fake_autopilot):
    conn = mavutil.mavlink_connection(
        "udpin:127.0.0.1:0", source_system=CAMERA_SYS, source_component=CAMERA_COMP
    )
    port = conn.port.getsockname()[1]
    ap = fake_autopilot(tlog, target=("127.0.0.1", port))
    ap.start()
    got = collect(conn, 0.4, ["ATTITUDE"])
    assert len(got) >= 12
    first = next(i for i, r in enumerate(ap.records) if r.type == "ATTITUDE")
    assert got[0][1].get_seq() == first  # what came before it went out too
    # the client replies to where the packets came from: the autopilot's port
    conn.mav.heartbeat_send(mavlink.MAV_TYPE_CAMERA, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    ap.wait_for("HEARTBEAT")
    assert ap.peer == ("127.0.0.1", port)
    conn.close()


def test_stop_cleans_up_and_never_hangs(tlog):
    with FakeAutopilot(tlog, speed=2.0) as ap:
        assert ap.alive and ap.started
        port = ap.port
    assert not ap.alive and ap.closed
    ap.stop()  # idempotent
    with pytest.raises(RuntimeError):
        ap.start()
    # the port is free again
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", port))
    s.close()

    ap = FakeAutopilot(tlog)  # never started
    ap.stop()
    assert ap.closed and not ap.alive
    assert not ap.finished.is_set()

    ap = FakeAutopilot(tlog).start()
    t0 = time.monotonic()
    ap.stop()
    assert time.monotonic() - t0 < 0.5
    with pytest.raises(TimeoutError):
        ap.wait_for("HEARTBEAT", timeout=1.0)  # returns at once once stopped

    with pytest.raises(ValueError):
        FakeAutopilot(tlog, boot_offset_ms=-10_000_000)
