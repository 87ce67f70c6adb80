"""A fake autopilot for end-to-end tests: replays a telemetry log over UDP with pymavlink.

``FakeAutopilot`` reads a ``.tlog`` (records of an 8-byte big-endian unix time in
microseconds followed by one MAVLink 1 or 2 packet, as MAVProxy and
``keyframed.synth`` write them) and replays it on a UDP socket bound to 127.0.0.1 in
real time, the way a flight controller behind a telemetry radio or a MAVLink router
would stream it to a companion computer:

* The record at tlog time ``T`` is sent at ``start + (T - T0) / speed`` on the local
  ``time.monotonic_ns()`` clock; ``monotonic_ns_for_unix_us`` gives that instant, so a
  test can compare the daemon's clock mapping with the truth.
* Every message is re-encoded with pymavlink (MAVLink 2, or MAVLink 1 with
  ``mavlink1=True``) under the tlog's system/component ids with a running sequence
  number. ``time_boot_ms`` fields are shifted by ``boot_offset_ms``; ``noise`` adds
  Gaussian noise (deterministic for a ``seed``) to the attitude and position messages;
  ``with_noise`` and ``write_tlog`` write the same noisy flight as a tlog.
* The autopilot's boot clock (what its ``time_boot_ms`` would read now) answers
  TIMESYNC requests (``tc1 == 0``) with ``tc1`` in nanoseconds and ``ts1`` echoed, as
  ArduPilot and PX4 do; ``answer_timesync=False`` makes it an autopilot that does not
  (the daemon then has only the arrival times to go by). ``rogue_timesync=True`` adds a
  ground station (system 255, component 190) on the link that answers each request
  first, with its own clock an hour off, as a router forwarding every endpoint's
  TIMESYNC traffic would deliver it.
* Messages from the daemon are recorded (``received``, ``wait_for``); the autopilot can
  send ``request_message`` (COMMAND_LONG MAV_CMD_REQUEST_MESSAGE) or any message.
* ``latency_ms=(lo, hi)``: a radio's delay, each datagram held for a uniform random
  time in that range (deterministic for a ``seed``), so datagrams also overtake one
  another; the send times recorded (``sent``) stay those of the replay.
* Link faults: ``inject_garbage`` and ``pause``/``resume`` (a dropped radio link:
  nothing is sent or heard, the messages due meanwhile are lost but still use up
  sequence numbers, so the receiver sees the gap a real link drop leaves);
  ``stall``/``unstall`` (a radio retrying, an autopilot busy: the messages due
  meanwhile wait and go out in a burst when it moves on, late but none lost).

Addressing: by default the daemon connects with ``udpout:127.0.0.1:PORT`` and sends
first; the autopilot sends to the address it last heard from (nothing goes out before
it has heard one: those messages are lost). With ``target=(host, port)`` it sends
there from the start (the daemon listens with ``udpin``).
"""

from __future__ import annotations

import copy
import heapq
import math
import select
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, TypeAlias

import numpy as np
import pytest
from pymavlink.dialects.v10 import common as mavlink1_dialect
from pymavlink.dialects.v20 import common as mavlink

MAV_CMD_REQUEST_MESSAGE = mavlink.MAV_CMD_REQUEST_MESSAGE
_WGS84_A = 6378137.0
_WGS84_E2 = 6.69437999014e-3
_POLL_S = 0.05  # longest the I/O thread sleeps: bounds the latency of stop()
_STX_V1 = 0xFE
_STX_V2 = 0xFD

# A pymavlink message (a mavlink.MAVLink_message): pymavlink has no types.
Message: TypeAlias = Any
# payload lengths without the MAVLink 2 extension fields (pymavlink's v1.0 dialect
# is generated from the same XML without them)
_MAVLINK1_LENGTHS = {mid: cls.unpacker.size for mid, cls in mavlink1_dialect.mavlink_map.items()}


@dataclass(frozen=True)
class Noise:
    """Standard deviations of the Gaussian noise added to the replayed telemetry.

    ``attitude_deg`` applies to each ATTITUDE angle and to each axis of the small
    body-frame rotation applied to ATTITUDE_QUATERNION; ``position_m`` to each
    horizontal axis (north, east) and ``altitude_m`` to the altitude of
    GLOBAL_POSITION_INT and GPS_RAW_INT.
    """

    attitude_deg: float = 0.0
    position_m: float = 0.0
    altitude_m: float = 0.0


@dataclass(frozen=True)
class TlogRecord:
    """One tlog record: its unix time in microseconds and the decoded message."""

    unix_us: int
    msg: Message

    @property
    def type(self) -> str:
        return str(self.msg.get_type())


@dataclass(frozen=True)
class SentRecord:
    """A message the autopilot put on the wire, with the local time it was sent."""

    monotonic_ns: int
    unix_us: int | None  # the tlog time of a replayed message, None for the others
    msg: Message

    @property
    def type(self) -> str:
        return str(self.msg.get_type())


def _packet_size(data: bytes, at: int) -> int:
    magic = data[at]
    if magic == _STX_V2:
        signed = data[at + 2] & mavlink.MAVLINK_IFLAG_SIGNED
        return 12 + data[at + 1] + (mavlink.MAVLINK_SIGNATURE_BLOCK_LEN if signed else 0)
    if magic == _STX_V1:
        return 8 + data[at + 1]
    raise ValueError(f"no MAVLink packet start at byte {at} (0x{magic:02x})")


def read_tlog(path: Path) -> list[TlogRecord]:
    """The records of a tlog, in file order. Raises ValueError on a malformed file."""
    data = Path(path).read_bytes()
    parser = mavlink.MAVLink(None)
    records: list[TlogRecord] = []
    at = 0
    while at < len(data):
        if at + 11 > len(data):
            raise ValueError(f"{path}: truncated record at byte {at}")
        (unix_us,) = struct.unpack_from(">Q", data, at)
        size = _packet_size(data, at + 8)
        packet = data[at + 8 : at + 8 + size]
        if len(packet) < size:
            raise ValueError(f"{path}: truncated packet at byte {at + 8}")
        try:
            msg = parser.decode(bytearray(packet))
        except mavlink.MAVError as err:
            raise ValueError(f"{path}: bad packet at byte {at + 8}: {err}") from err
        records.append(TlogRecord(unix_us, msg))
        at += 8 + size
    if not records:
        raise ValueError(f"{path}: no records")
    return records


def _copy(msg: Message) -> Message:
    # A deep copy of the fields as they are now: decoding get_msgbuf() again would
    # bring back the bytes it was read from, without any change made since (the
    # boot offset, before noise is added).
    return copy.deepcopy(msg)


def _quat_mul(a: tuple[float, ...], b: tuple[float, ...]) -> tuple[float, float, float, float]:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def _rotvec_quat(r: np.ndarray) -> tuple[float, float, float, float]:
    angle = float(np.linalg.norm(r))
    if angle < 1e-12:
        return (1.0, 0.0, 0.0, 0.0)
    s = math.sin(angle / 2.0) / angle
    return (math.cos(angle / 2.0), float(r[0]) * s, float(r[1]) * s, float(r[2]) * s)


def _metres_to_degrees(lat_deg: float, north_m: float, east_m: float) -> tuple[float, float]:
    """Degrees of latitude/longitude for a small north/east displacement (WGS84)."""
    s = math.sin(math.radians(lat_deg))
    w = 1.0 - _WGS84_E2 * s * s
    meridian = _WGS84_A * (1.0 - _WGS84_E2) / w**1.5
    normal = _WGS84_A / math.sqrt(w)
    cos_lat = max(math.cos(math.radians(lat_deg)), 1e-9)
    return math.degrees(north_m / meridian), math.degrees(east_m / (normal * cos_lat))


def _shift_position(msg: Message, north: float, east: float, up: float) -> None:
    dlat, dlon = _metres_to_degrees(msg.lat * 1e-7, north, east)
    msg.lat = int(round(msg.lat + dlat * 1e7))
    msg.lon = int(round(msg.lon + dlon * 1e7))
    up_mm = int(round(up * 1000.0))
    for name in ("alt", "relative_alt", "alt_ellipsoid"):
        if hasattr(msg, name):
            setattr(msg, name, getattr(msg, name) + up_mm)


def _add_noise(msg: Message, noise: Noise, rng: np.random.Generator) -> None:
    """Perturb ``msg`` in place. Draws a fixed number of normals per message type."""
    kind = msg.get_type()
    att = math.radians(noise.attitude_deg)
    if kind == "ATTITUDE":
        d = rng.normal(0.0, 1.0, 3) * att
        msg.roll += float(d[0])
        msg.pitch += float(d[1])
        msg.yaw = (msg.yaw + float(d[2]) + math.pi) % (2.0 * math.pi) - math.pi
    elif kind == "ATTITUDE_QUATERNION":
        dq = _rotvec_quat(rng.normal(0.0, 1.0, 3) * att)
        q = _quat_mul((msg.q1, msg.q2, msg.q3, msg.q4), dq)
        norm = math.sqrt(sum(v * v for v in q))
        msg.q1, msg.q2, msg.q3, msg.q4 = (v / norm for v in q)
    elif kind in ("GLOBAL_POSITION_INT", "GPS_RAW_INT"):
        d = rng.normal(0.0, 1.0, 3)
        _shift_position(
            msg,
            float(d[0]) * noise.position_m,
            float(d[1]) * noise.position_m,
            float(d[2]) * noise.altitude_m,
        )


def with_noise(records: list[TlogRecord], noise: Noise, seed: int = 0) -> list[TlogRecord]:
    """Copies of ``records`` with Gaussian ``noise`` on the attitude and position
    messages, deterministic for a ``seed`` (what ``FakeAutopilot(noise=, seed=)``
    replays)."""
    rng = np.random.default_rng(seed)
    out = []
    for rec in records:
        msg = _copy(rec.msg)
        _add_noise(msg, noise, rng)
        out.append(TlogRecord(rec.unix_us, msg))
    return out


def write_tlog(path: Path, records: list[TlogRecord]) -> None:
    """Writes ``records`` as a tlog, each message re-encoded (MAVLink 2) under the
    system/component id and sequence number it came with."""
    encoders: dict[tuple[int, int], mavlink.MAVLink] = {}
    out = bytearray()
    for rec in records:
        header = rec.msg.get_header()
        ids = (int(header.srcSystem), int(header.srcComponent))
        mav = encoders.setdefault(ids, mavlink.MAVLink(None, srcSystem=ids[0], srcComponent=ids[1]))
        mav.seq = rec.msg.get_seq()
        out += struct.pack(">Q", rec.unix_us) + rec.msg.pack(mav)
    Path(path).write_bytes(bytes(out))


class _TimesyncReply(mavlink.MAVLink_timesync_message):
    """TIMESYNC with the target_system/target_component extension fields of newer
    common.xml (pymavlink 2.4.50 generates only tc1/ts1); MAVLink 1 drops them."""

    def __init__(self, tc1: int, ts1: int, target_system: int, target_component: int) -> None:
        super().__init__(tc1, ts1)
        self.target_system = target_system
        self.target_component = target_component

    def pack(self, mav: mavlink.MAVLink, force_mavlink1: bool = False) -> bytes:
        payload = self.unpacker.pack(self.tc1, self.ts1)
        if not force_mavlink1:
            payload += struct.pack("<BB", self.target_system, self.target_component)
        return self._pack(mav, self.crc_extra, payload, force_mavlink1=force_mavlink1)


def timesync_target(msg: Message) -> tuple[int, int] | None:
    """The (target_system, target_component) extension of a received MAVLink 2
    TIMESYNC, or None when the sender left them out."""
    buf = bytes(msg.get_msgbuf())
    if not buf or buf[0] != _STX_V2:
        return None
    payload = buf[10 : 10 + buf[1]].ljust(18, b"\0")
    if buf[1] <= 16:
        return None
    return payload[16], payload[17]


class FakeAutopilot:
    """Replays a tlog over UDP as an autopilot would stream it; see the module doc."""

    def __init__(
        self,
        tlog: Path,
        *,
        port: int = 0,
        target: tuple[str, int] | None = None,
        boot_offset_ms: int = 0,
        noise: Noise | None = None,
        seed: int = 0,
        mavlink1: bool = False,
        speed: float = 1.0,
        start_delay_s: float = 0.0,
        answer_timesync: bool = True,
        rogue_timesync: bool = False,
        latency_ms: tuple[float, float] | None = None,
        from_unix_us: float | None = None,
        wait_for_peer: bool = False,
    ) -> None:
        if speed <= 0.0:
            raise ValueError("speed must be positive")
        if start_delay_s < 0.0 and not wait_for_peer:
            raise ValueError("start_delay_s must be >= 0")
        self.tlog = Path(tlog)
        self.records = read_tlog(self.tlog)
        if from_unix_us is not None:
            # The replay begins at this tlog time (e.g. a video's first frame).
            self.records = [r for r in self.records if r.unix_us >= from_unix_us]
            if not self.records:
                raise ValueError(f"{tlog} has no record at or after unix {from_unix_us / 1e6}")
        # The replay starts when the daemon is first heard (udpout: it sends first),
        # start_delay_s after that: no record is lost to a link not open yet, and the
        # flight begins as the daemon starts listening for it. A negative delay: the
        # records of that many seconds are due already then, and go at once.
        self.wait_for_peer = wait_for_peer
        self.boot_offset_ms = int(boot_offset_ms)
        self.noise = noise
        self.seed = seed
        self.mavlink1 = mavlink1
        self.speed = float(speed)
        self.start_delay_s = float(start_delay_s)
        self.answer_timesync = answer_timesync
        self.rogue_timesync = rogue_timesync
        if latency_ms is not None and not 0.0 <= latency_ms[0] <= latency_ms[1]:
            raise ValueError("latency_ms must be (lo, hi) with 0 <= lo <= hi")
        self.latency_ms = latency_ms
        self._latency_rng = np.random.default_rng([seed, 2])
        # Datagrams held back by the radio's delay: (due monotonic ns, order, bytes).
        self._delayed: list[tuple[int, int, bytes]] = []
        self._delayed_count = 0
        self._radio_cond = threading.Condition()
        self._radio: threading.Thread | None = None
        self.rogue_answers = 0  # TIMESYNC answers the rogue ground station sent
        self.ignored_v2 = 0  # MAVLink 2 frames a MAVLink 1 autopilot could not read
        # MAV_CMD_SET_MESSAGE_INTERVAL asked of it: message id -> interval in us
        # (acknowledged as ArduPilot does; the replay's own rates stay).
        self.message_intervals: dict[int, int] = {}
        self.target = target
        self.t0_unix_us = self.records[0].unix_us
        self.t_end_unix_us = self.records[-1].unix_us
        first = self.records[0].msg.get_header()
        self.system_id = int(first.srcSystem)
        self.component_id = int(first.srcComponent)

        # The boot clock: time_boot_ms = unix_us / 1000 + offset, fitted to the log.
        offsets = [
            r.msg.time_boot_ms - r.unix_us / 1000.0
            for r in self.records
            if hasattr(r.msg, "time_boot_ms")
            and r.msg.get_header().srcComponent == self.component_id
        ]
        self._boot_minus_unix_ms = (
            float(np.median(offsets)) if offsets else -self.t0_unix_us / 1000.0
        )
        self._planned = self._plan()

        self._mav = mavlink.MAVLink(None, srcSystem=self.system_id, srcComponent=self.component_id)
        self._others: dict[int, mavlink.MAVLink] = {}
        self._rogue = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
        # Each record goes out from the component that sent it in the tlog.
        self._components = [int(r.msg.get_header().srcComponent) for r in self.records]
        self._parser = mavlink.MAVLink(None)
        self._parser.robust_parsing = True
        self._garbage_rng = np.random.default_rng([seed, 1])
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self._sock.bind(("127.0.0.1", port))
            self._sock.setblocking(False)
        except OSError:
            self._sock.close()
            raise
        self.port: int = self._sock.getsockname()[1]

        self._send_lock = threading.Lock()
        self._cond = threading.Condition()
        self._received: list[tuple[int, Message]] = []
        self._sent: list[SentRecord] = []
        self._peer: tuple[str, int] | None = target
        self._peer_ids: tuple[int, int] | None = None
        self._paused = threading.Event()
        self._stalled = threading.Event()
        self._stop = threading.Event()
        self.finished = threading.Event()
        self._thread: threading.Thread | None = None
        self._start_ns: int | None = None
        self._closed = False
        self.error: BaseException | None = None
        self.dropped = 0  # replayed messages lost (paused, or no peer yet)
        self.receive_errors = 0  # bad bytes or packets heard from the daemon

    # ------------------------------------------------------------------ planning

    def _plan(self) -> list[TlogRecord]:
        planned = []
        for rec in self.records:
            msg = _copy(rec.msg)
            if hasattr(msg, "time_boot_ms"):
                shifted = msg.time_boot_ms + self.boot_offset_ms
                if not 0 <= shifted < 2**32:
                    raise ValueError(
                        f"boot_offset_ms {self.boot_offset_ms} puts time_boot_ms out of range"
                    )
                msg.time_boot_ms = shifted
            planned.append(TlogRecord(rec.unix_us, msg))
        return planned if self.noise is None else with_noise(planned, self.noise, self.seed)

    def planned(self, msg_type: str | None = None) -> list[TlogRecord]:
        """The replayed messages as they will be sent (offset and noise applied)."""
        return [r for r in self._planned if msg_type is None or r.type == msg_type]

    def tlog_messages(self, msg_type: str | None = None) -> list[TlogRecord]:
        """The tlog's records as they are in the file."""
        return [r for r in self.records if msg_type is None or r.type == msg_type]

    # ------------------------------------------------------------------ clocks

    @property
    def started(self) -> bool:
        return self._start_ns is not None

    @property
    def start_monotonic_ns(self) -> int:
        """time.monotonic_ns() at which the first tlog record is (or was) sent."""
        if self._start_ns is None:
            raise RuntimeError("FakeAutopilot not started")
        return self._start_ns

    @property
    def replay_seconds(self) -> float:
        """Wall-clock length of the replay."""
        return (self.t_end_unix_us - self.t0_unix_us) / 1e6 / self.speed

    def monotonic_ns_for_unix_us(self, unix_us: float) -> int:
        """The local time.monotonic_ns() at which tlog time ``unix_us`` is replayed."""
        return self.start_monotonic_ns + int(
            round((unix_us - self.t0_unix_us) * 1000.0 / self.speed)
        )

    def unix_us_at_monotonic_ns(self, monotonic_ns: int) -> float:
        """The tlog time being replayed at local time ``monotonic_ns``."""
        return self.t0_unix_us + (monotonic_ns - self.start_monotonic_ns) * self.speed / 1000.0

    def boot_ms_at_monotonic_ns(self, monotonic_ns: int | None = None) -> float:
        """The autopilot's boot clock (shifted by boot_offset_ms) at a local instant
        (now by default): what its replayed time_boot_ms reads then, unrounded."""
        mono = time.monotonic_ns() if monotonic_ns is None else monotonic_ns
        unix_us = self.unix_us_at_monotonic_ns(mono)
        return unix_us / 1000.0 + self._boot_minus_unix_ms + self.boot_offset_ms

    def monotonic_ns_for_boot_ms(self, time_boot_ms: float) -> int:
        """The local time.monotonic_ns() at which the autopilot's clock reads
        ``time_boot_ms`` (offset included, as the daemon receives it)."""
        unix_us = (time_boot_ms - self.boot_offset_ms - self._boot_minus_unix_ms) * 1000.0
        return self.monotonic_ns_for_unix_us(unix_us)

    # ------------------------------------------------------------------ life cycle

    def start(self) -> FakeAutopilot:
        """Start the I/O thread; the first record goes out after ``start_delay_s``."""
        if self._closed:
            raise RuntimeError("FakeAutopilot already stopped")
        if self._thread is not None:
            raise RuntimeError("FakeAutopilot already started")
        if not self.wait_for_peer:
            self._start_ns = time.monotonic_ns() + int(self.start_delay_s * 1e9)
        self._thread = threading.Thread(
            target=self._run, name=f"fake-autopilot-{self.port}", daemon=True
        )
        self._thread.start()
        if self.latency_ms is not None:
            self._radio = threading.Thread(
                target=self._deliver_delayed, name=f"fake-radio-{self.port}", daemon=True
            )
            self._radio.start()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the thread and close the socket; idempotent. Re-raises a thread error."""
        self._stop.set()
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout)
        with self._radio_cond:
            self._radio_cond.notify_all()
        if self._radio is not None and self._radio is not threading.current_thread():
            self._radio.join(timeout)
        if not self._closed:
            self._closed = True
            with self._send_lock:
                self._sock.close()
        with self._cond:
            self._cond.notify_all()
        if thread is not None and thread.is_alive():
            raise RuntimeError("fake autopilot thread did not stop")
        if self.error is not None:
            err, self.error = self.error, None
            raise RuntimeError("fake autopilot thread failed") from err

    def __enter__(self) -> FakeAutopilot:
        if self._thread is None:
            self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    @property
    def closed(self) -> bool:
        return self._closed

    # ------------------------------------------------------------------ link faults

    def pause(self) -> None:
        """Drop the link: send nothing, ignore everything heard, until resume()."""
        self._paused.set()

    def resume(self) -> None:
        self._paused.clear()

    @property
    def paused(self) -> bool:
        return self._paused.is_set()

    def stall(self) -> None:
        """Hold the replay: the messages that fall due wait, until unstall() sends
        them at once."""
        self._stalled.set()

    def unstall(self) -> None:
        self._stalled.clear()

    def inject_garbage(self, n_bytes: int, *, with_magic: bool = False) -> bytes:
        """Send ``n_bytes`` of noise to the peer, in datagrams of up to 512 bytes.

        By default the bytes hold no MAVLink start marker (0xFD/0xFE): a parser skips
        them and loses nothing else. ``with_magic=True`` starts with a bogus MAVLink 2
        header and draws from all byte values, so a parser may also lose the packets
        that follow while it resynchronises. Returns the bytes actually sent (empty
        when paused or no peer is known)."""
        if with_magic:
            body = self._garbage_rng.integers(0, 256, max(n_bytes - 3, 0), dtype=np.uint8)
            data = (bytes([_STX_V2, 0xFF, 0x00]) + body.tobytes())[:n_bytes]
        else:
            data = self._garbage_rng.integers(0, _STX_V2, n_bytes, dtype=np.uint8).tobytes()
        with self._send_lock:
            if not self._can_send():
                return b""
            for i in range(0, len(data), 512):
                self._sendto(data[i : i + 512])
        return data

    # ------------------------------------------------------------------ sending

    @property
    def peer(self) -> tuple[str, int] | None:
        """Where the autopilot sends: ``target``, or the address it last heard from."""
        return self._peer

    @property
    def mav(self) -> mavlink.MAVLink:
        """A pymavlink encoder for building messages (``ap.mav.xxx_encode(...)``) to
        pass to ``send``; use it only to build them, not to send."""
        return self._mav

    def _can_send(self) -> bool:
        return not self._closed and not self._paused.is_set() and self._peer is not None

    def _sendto(self, data: bytes) -> None:
        assert self._peer is not None
        if self.latency_ms is not None:
            lo, hi = self.latency_ms
            delay_ns = int(float(self._latency_rng.uniform(lo, hi)) * 1e6)
            with self._radio_cond:
                self._delayed_count += 1
                heapq.heappush(
                    self._delayed, (time.monotonic_ns() + delay_ns, self._delayed_count, data)
                )
                self._radio_cond.notify_all()
            return
        self._send_now(data)

    def _send_now(self, data: bytes) -> None:
        assert self._peer is not None
        try:
            self._sock.sendto(data, self._peer)
        except OSError:
            pass  # nobody listening (ICMP port unreachable): UDP loses it, like a radio

    def _deliver_delayed(self) -> None:
        """The radio: each held datagram goes out when its delay is over."""
        while not self._stop.is_set():
            with self._radio_cond:
                if not self._delayed:
                    self._radio_cond.wait(0.05)
                    continue
                due, _, data = self._delayed[0]
                wait_ns = due - time.monotonic_ns()
                if wait_ns > 0:
                    self._radio_cond.wait(min(wait_ns / 1e9, 0.05))
                    continue
                heapq.heappop(self._delayed)
            with self._send_lock:
                if not self._closed:
                    self._send_now(data)

    def _encoder(self, component: int | None) -> mavlink.MAVLink:
        """The autopilot's encoder, or that of another component of its system (a
        gimbal in the tlog), each with its own sequence numbers."""
        if component is None or component == self.component_id:
            return self._mav
        if component not in self._others:
            self._others[component] = mavlink.MAVLink(
                None, srcSystem=self.system_id, srcComponent=component
            )
        return self._others[component]

    def _pack(self, msg: Message, component: int | None = None) -> bytes:
        mav = self._encoder(component)
        buf = msg.pack(mav, force_mavlink1=self.mavlink1)
        if self.mavlink1:
            # like the C library: a MAVLink 1 payload stops before the extension fields
            base = _MAVLINK1_LENGTHS.get(msg.get_msgId())
            if base is None:
                raise ValueError(f"{msg.get_type()} has no MAVLink 1 form")
            if buf[1] > base:
                payload = buf[6 : 6 + base]
                buf = msg._pack(mav, msg.crc_extra, payload, force_mavlink1=True)
        mav.seq = (mav.seq + 1) % 256
        return buf

    def send(
        self, msg: Message, *, unix_us: int | None = None, component: int | None = None
    ) -> bool:
        """Encode and send ``msg`` with the next sequence number; False if the link is
        down (paused, stopped, or no peer yet), in which case it is lost."""
        with self._send_lock:
            if self._closed:
                return False
            buf = self._pack(msg, component)
            if not self._can_send():
                return False
            with self._cond:  # logged first, so it is there once a receiver has it
                self._sent.append(SentRecord(time.monotonic_ns(), unix_us, msg))
            self._sendto(buf)
        return True

    def command(
        self,
        command: int,
        *params: float,
        target_system: int | None = None,
        target_component: int | None = None,
    ) -> bool:
        """Send COMMAND_LONG ``command`` with up to seven ``params`` to the given ids;
        by default to the system/component last heard from, or broadcast (0/0) when
        none yet."""
        if len(params) > 7:
            raise ValueError("at most 7 params")
        ids = self._peer_ids or (0, 0)
        tsys = ids[0] if target_system is None else target_system
        tcomp = ids[1] if target_component is None else target_component
        p = [float(v) for v in params] + [0.0] * (7 - len(params))
        return self.send(self._mav.command_long_encode(tsys, tcomp, command, 0, *p))

    def request_message(
        self,
        msg_id: int,
        *params: float,
        target_system: int | None = None,
        target_component: int | None = None,
    ) -> bool:
        """Send COMMAND_LONG MAV_CMD_REQUEST_MESSAGE (param1 = ``msg_id``, then up to six
        more ``params``), addressed as ``command`` does."""
        if len(params) > 6:
            raise ValueError("at most 6 extra params")
        return self.command(
            MAV_CMD_REQUEST_MESSAGE,
            float(msg_id),
            *params,
            target_system=target_system,
            target_component=target_component,
        )

    def sent(self, msg_type: str | None = None) -> list[SentRecord]:
        """Everything actually sent, replayed or not, in order."""
        with self._cond:
            return [r for r in self._sent if msg_type is None or r.type == msg_type]

    # ------------------------------------------------------------------ receiving

    def received(self, msg_type: str | None = None) -> list[Message]:
        """The messages heard from the daemon (all, or of one type), in order."""
        with self._cond:
            return [m for _, m in self._received if msg_type is None or m.get_type() == msg_type]

    def received_with_times(self, msg_type: str | None = None) -> list[tuple[int, Message]]:
        """Like ``received``, with the local time.monotonic_ns() each was read."""
        with self._cond:
            return [
                (t, m) for t, m in self._received if msg_type is None or m.get_type() == msg_type
            ]

    def clear_received(self) -> None:
        with self._cond:
            self._received.clear()

    def wait_for(self, msg_type: str, count: int = 1, timeout: float = 5.0) -> list[Message]:
        """Wait until ``count`` messages of ``msg_type`` were heard; returns all of
        them. Raises TimeoutError (or RuntimeError if the thread failed)."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                got = [m for _, m in self._received if m.get_type() == msg_type]
                if len(got) >= count:
                    return got
                if self.error is not None:
                    raise RuntimeError("fake autopilot thread failed") from self.error
                left = deadline - time.monotonic()
                if left <= 0 or self._closed:
                    raise TimeoutError(
                        f"heard {len(got)} of {count} {msg_type} in {timeout} s "
                        f"(heard in all: {sorted({m.get_type() for _, m in self._received})})"
                    )
                self._cond.wait(min(left, _POLL_S))

    def _handle(self, msg: Message, now_ns: int) -> None:
        if msg.get_type() == "BAD_DATA":
            self.receive_errors += 1
            return
        header = msg.get_header()
        self._peer_ids = (int(header.srcSystem), int(header.srcComponent))
        with self._cond:
            self._received.append((now_ns, msg))
            self._cond.notify_all()
        if self.mavlink1 and msg.get_msgbuf()[:1] == b"\xfd":
            # A MAVLink 1 autopilot does not understand MAVLink 2 frames: recorded for
            # the test, not answered.
            self.ignored_v2 += 1
            return
        if (
            msg.get_type() == "COMMAND_LONG"
            and msg.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
            and msg.target_system == self.system_id
            and msg.target_component == self.component_id
        ):
            self.message_intervals[int(msg.param1)] = int(msg.param2)
            self.send(
                self._mav.command_ack_encode(
                    msg.command, mavlink.MAV_RESULT_ACCEPTED, 0, 0, *self._peer_ids
                )
            )
        if msg.get_type() == "TIMESYNC" and msg.tc1 == 0:
            target = timesync_target(msg)
            if target is not None and target[0] not in (0, self.system_id):
                return
            tc1 = int(round(self.boot_ms_at_monotonic_ns(now_ns) * 1e6))
            if self.rogue_timesync:
                self._send_rogue(_TimesyncReply(tc1 + 3_600_000_000_000, msg.ts1, 0, 0))
            if self.answer_timesync:
                self.send(_TimesyncReply(tc1, msg.ts1, *self._peer_ids))

    def _send_rogue(self, msg: Message) -> None:
        with self._send_lock:
            if self._closed or not self._can_send():
                return
            buf = msg.pack(self._rogue, force_mavlink1=self.mavlink1)
            self._rogue.seq = (self._rogue.seq + 1) % 256
            self.rogue_answers += 1
            self._sendto(buf)

    def _drain(self) -> None:
        while not self._stop.is_set():
            try:
                data, addr = self._sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                return
            except ConnectionRefusedError:
                continue  # an ICMP error from an earlier send
            now_ns = time.monotonic_ns()
            if self._paused.is_set():
                continue
            if self.target is None:
                self._peer = (addr[0], addr[1])
            try:
                msgs = self._parser.parse_buffer(data) or []
            except mavlink.MAVError:
                self.receive_errors += 1
                continue
            for msg in msgs:
                self._handle(msg, now_ns)

    # ------------------------------------------------------------------ thread

    def _run(self) -> None:
        try:
            self._loop()
        except BaseException as err:  # noqa: BLE001 - surfaced by stop()/wait_for()
            self.error = err
            with self._cond:
                self._cond.notify_all()

    def _loop(self) -> None:
        if self.wait_for_peer:
            while self._peer is None and not self._stop.is_set():
                if select.select([self._sock], [], [], _POLL_S)[0]:
                    self._drain()
            self._start_ns = time.monotonic_ns() + int(self.start_delay_s * 1e9)
        if self._stop.is_set():
            return
        due = [self.monotonic_ns_for_unix_us(r.unix_us) for r in self._planned]
        nxt = 0
        while not self._stop.is_set():
            wait_s = _POLL_S
            if nxt < len(due):
                wait_s = min(wait_s, max(0.0, (due[nxt] - time.monotonic_ns()) / 1e9))
            readable, _, _ = select.select([self._sock], [], [], wait_s)
            if readable:
                self._drain()
            now = time.monotonic_ns()
            while (
                nxt < len(due)
                and due[nxt] <= now
                and not self._stalled.is_set()
                and not self._stop.is_set()
            ):
                rec = self._planned[nxt]
                component = self._components[nxt]
                if not self.send(rec.msg, unix_us=rec.unix_us, component=component):
                    self.dropped += 1
                nxt += 1
            if nxt >= len(due) and not self.finished.is_set():
                self.finished.set()


def autopilot_fixture(
    name: str = "fake_autopilot",
    scope: Literal["session", "package", "module", "class", "function"] = "function",
) -> Callable[..., Any]:
    """A pytest fixture that gives a factory ``make(tlog, **kwargs) -> FakeAutopilot``
    (not started) and stops every autopilot it made at teardown. In a test module:
    ``fake_autopilot = autopilot_fixture()``."""

    @pytest.fixture(name=name, scope=scope)
    def _fixture() -> Iterator[Callable[..., FakeAutopilot]]:
        made: list[FakeAutopilot] = []

        def make(tlog: Path, **kwargs: Any) -> FakeAutopilot:
            ap = FakeAutopilot(tlog, **kwargs)
            made.append(ap)
            return ap

        try:
            yield make
        finally:
            errors = []
            for ap in made:
                try:
                    ap.stop()
                except RuntimeError as err:
                    errors.append(err)
            if errors:
                raise errors[0]

    return _fixture


def main(argv: list[str] | None = None) -> int:
    """Replays a tlog to a UDP address in real time (tools/demo.sh uses it):
    ``python tests/harness/fake_autopilot.py FLIGHT.tlog --target 127.0.0.1:14550``."""
    import argparse
    import signal
    import sys

    p = argparse.ArgumentParser(description=main.__doc__)
    p.add_argument("tlog", type=Path)
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--target", help="HOST:PORT the daemon listens on (udpin)")
    where.add_argument(
        "--listen",
        type=int,
        help="UDP port on 127.0.0.1 the daemon sends to (udpout); the replay starts when "
        "the daemon is first heard",
    )
    p.add_argument("--start-delay", type=float, default=0.0, help="seconds before the first record")
    p.add_argument(
        "--from-unix",
        type=float,
        help="the tlog time (unix seconds) to replay when the replay starts (--listen: when "
        "the daemon is first heard; the second before it is sent at once, as history)",
    )
    p.add_argument("--ready-file", type=Path, help="created once the socket is bound")
    args = p.parse_args(argv)
    history_s = 1.0 if args.listen is not None and args.from_unix is not None else 0.0
    kwargs: dict[str, Any] = {
        "start_delay_s": args.start_delay - history_s,
        "from_unix_us": None if args.from_unix is None else (args.from_unix - history_s) * 1e6,
    }
    if args.target is not None:
        host, _, port = args.target.rpartition(":")
        ap = FakeAutopilot(args.tlog, target=(host, int(port)), **kwargs)
    else:
        ap = FakeAutopilot(args.tlog, port=args.listen, wait_for_peer=True, **kwargs)
    if args.ready_file is not None:
        args.ready_file.touch()
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    ap.start()
    while not stop.is_set() and not ap.finished.wait(0.2):
        pass
    n = len(ap.received("CAMERA_IMAGE_CAPTURED"))
    ap.stop()
    print(
        f"fake autopilot: replayed {args.tlog.name}; heard {n} CAMERA_IMAGE_CAPTURED",
        file=sys.stderr,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
