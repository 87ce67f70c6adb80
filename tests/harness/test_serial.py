"""A serial link to the autopilot that goes away mid-flight and comes back: a USB
telemetry radio pulled out and plugged in again. The flight's telemetry is written in
real time into a pseudo-terminal behind a stable device name, as /dev/serial/by-id/...
points at /dev/ttyUSB0."""

from __future__ import annotations

import json
import os
import select
import subprocess
import threading
import time
import tty
from pathlib import Path
from typing import Any

from fake_autopilot import read_tlog
from pymavlink.dialects.v20 import common as mav2
from test_geotag import (
    Truth,
    exif,
    keyframes,
    needs_exiftool,
    run_select,
    short_nadir,  # noqa: F401 - the module fixture
    tag_errors,
)

INT32_MAX = 2**31 - 1


class PtyAutopilot:
    """Writes a tlog's packets into a pseudo-terminal at their recorded pace and reads
    what the other end (keyframed) sends.

    ``device`` is a symlink to the pty's slave end. Like a UART, the pty delivers only
    while someone has it open: packets due while nobody does are lost, not buffered.
    The replay starts ``start_delay_s`` after the daemon first opens the device.
    Between ``unplug_s`` and ``plug_s`` (seconds into the replay) the device is gone:
    the pty is closed (the daemon's end sees a hang-up) and the name removed; at
    ``plug_s`` a new pty appears under the same name. Each pty is an "epoch": ``heard``
    lists the daemon's messages with the epoch (0 before, 1 after) and local time.
    With ``damage_every`` = N, every N-th packet loses 3 bytes from its middle on the
    way (a UART overrun): ``written`` counts the packets written whole, ``damaged``
    the others."""

    def __init__(
        self,
        tlog: Path,
        device: Path,
        *,
        unplug_s: float | None = None,
        plug_s: float | None = None,
        start_delay_s: float = 0.1,
        damage_every: int | None = None,
    ) -> None:
        self.records = read_tlog(tlog)
        self._damage_every = damage_every
        self.written = 0
        self.damaged = 0
        self.device = device
        self.t0_unix_us = self.records[0].unix_us
        self.start_ns: int | None = None
        self._start_delay_ns = int(start_delay_s * 1e9)
        self._unplug_s, self._plug_s = unplug_s, plug_s
        self.unplug_ns: int | None = None
        self.plug_ns: int | None = None
        self.heard: list[tuple[int, int, Any]] = []  # (epoch, monotonic ns, message)
        self.lost = 0  # packets due while the device was gone or not open
        self.epoch = 0
        self.error: BaseException | None = None
        self._master: int | None = None
        self._parser = mav2.MAVLink(None)
        self._stop = threading.Event()
        self._plug()
        self._thread = threading.Thread(target=self._run, name="pty-autopilot")
        self._thread.start()

    def flight_us_at(self, monotonic_ns: int) -> float:
        """The tlog time replayed at a local time.monotonic_ns()."""
        assert self.start_ns is not None
        return self.t0_unix_us + (monotonic_ns - self.start_ns) / 1000.0

    def _plug(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)  # a UART: no echo, no line editing
        name = os.ttyname(slave)
        os.close(slave)  # the pty stays while its master is open; the daemon opens it
        os.set_blocking(master, False)
        self._master = master
        tmp = self.device.with_name(self.device.name + ".new")
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(name)
        tmp.replace(self.device)
        self._parser = mav2.MAVLink(None)
        self._parser.robust_parsing = True

    def _unplug(self) -> None:
        assert self._master is not None
        self.device.unlink()
        os.close(self._master)
        self._master = None

    def _poll(self, timeout_s: float) -> tuple[bool, bool]:
        """(someone has the device open, there are bytes from them)."""
        if self._master is None:
            time.sleep(timeout_s)
            return False, False
        p = select.poll()
        p.register(self._master, select.POLLIN)
        events = p.poll(timeout_s * 1000)
        flags = events[0][1] if events else 0
        if flags & select.POLLHUP:
            time.sleep(timeout_s)  # poll() does not wait while nobody has it open
        return not flags & select.POLLHUP, bool(flags & select.POLLIN)

    def _read(self, now_ns: int) -> None:
        assert self._master is not None
        try:
            data = os.read(self._master, 4096)
        except OSError:  # EIO: the daemon closed it meanwhile
            return
        for msg in self._parser.parse_buffer(data) or []:
            if msg.get_type() != "BAD_DATA":
                self.heard.append((self.epoch, now_ns, msg))

    def _run(self) -> None:
        try:
            self._loop()
        except BaseException as err:  # noqa: BLE001 - re-raised by stop()
            self.error = err

    def _loop(self) -> None:
        nxt = 0
        while not self._stop.is_set():
            wait_s = 0.005
            if self.start_ns is not None and nxt < len(self.records):
                due = self.start_ns + (self.records[nxt].unix_us - self.t0_unix_us) * 1000
                wait_s = min(wait_s, max(0.0, (due - time.monotonic_ns()) / 1e9))
            # on time to well under a millisecond: the daemon's clock comes from arrivals
            is_open, readable = self._poll(wait_s)
            now = time.monotonic_ns()
            if readable:
                self._read(now)
            if self.start_ns is None:
                if not is_open:
                    continue
                self.start_ns = now + self._start_delay_ns
                if self._unplug_s is not None and self._plug_s is not None:
                    self.unplug_ns = self.start_ns + int(self._unplug_s * 1e9)
                    self.plug_ns = self.start_ns + int(self._plug_s * 1e9)
            if self.unplug_ns is not None and self._master is not None and now >= self.unplug_ns:
                self.unplug_ns = None
                self._unplug()
                is_open = False
            if self.plug_ns is not None and self._master is None and now >= self.plug_ns:
                self.plug_ns = None
                self.epoch += 1
                self._plug()
            while nxt < len(self.records):
                rec = self.records[nxt]
                if self.start_ns + (rec.unix_us - self.t0_unix_us) * 1000 > now:
                    break
                nxt += 1
                if self._master is None or not is_open:
                    self.lost += 1
                    continue
                buf = bytes(rec.msg.get_msgbuf())
                damage = self._damage_every is not None and nxt % self._damage_every == 0
                if damage:
                    buf = buf[: len(buf) // 2] + buf[len(buf) // 2 + 3 :]
                try:
                    n = os.write(self._master, buf)
                except OSError:
                    self.lost += 1  # the UART's buffer is full: nobody is reading
                    continue
                if damage or n < len(buf):  # or only its start fitted in the buffer
                    self.damaged += 1
                else:
                    self.written += 1

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()
        if self._master is not None:
            self._unplug()
        if self.error is not None:
            raise RuntimeError("pty autopilot failed") from self.error

    def received(self, msg_type: str, epoch: int | None = None) -> list[tuple[int, int, Any]]:
        return [h for h in self.heard if h[2].get_type() == msg_type and epoch in (None, h[0])]


def select_over_serial(
    kf_bin: Path, fl: Path, out: Path, ap: PtyAutopilot, baud: int, *extra: str, **kw: Any
) -> Any:
    """`keyframed select` on flight FL with its telemetry from AP's serial device (and
    its calibration); AP stopped after."""
    try:
        return run_select(
            kf_bin,
            fl,
            out,
            "--telemetry",
            f"serial:{ap.device}:{baud}",
            "--calibration",
            str(fl / "intrinsics.json"),
            *extra,
            **kw,
        )
    finally:
        ap.stop()


def check_tags(fl: Path, out: Path, ap: PtyAutopilot, kfs: list[dict[str, str]]) -> None:
    """Each keyframe's tags against the truth at the instant the pty replayed then."""
    truth = Truth(fl)
    tags = exif([out / k["file"] for k in kfs])
    for k in kfs:
        assert k["geotag"] == "ok", k
        flight_t = (ap.flight_us_at(int(k["time_ns"])) - truth.epoch_us) / 1e6
        e = tag_errors(tags[k["file"]], truth.at(flight_t))
        assert e[0] < 0.1 and e[1] < 0.1 and e[2] < 0.2, (k["index"], e)


@needs_exiftool
def test_serial_link_over_a_pty(
    kf_bin: Path,
    short_nadir: Path,  # noqa: F811 - the fixture imported above
    tmp_path: Path,
) -> None:
    """A serial link (telemetry radio, flight controller UART) at 921600 baud."""
    ap = PtyAutopilot(short_nadir / "flight.tlog", tmp_path / "ttyFC")
    out = tmp_path / "serial"
    r = select_over_serial(kf_bin, short_nadir, out, ap, 921600)
    assert r.returncode == 0, r.stderr
    kfs = keyframes(out)
    assert len(kfs) >= 5
    check_tags(short_nadir, out, ap, kfs)
    # keyframed spoke on the serial line too: a camera's HEARTBEAT, one capture each
    hb = ap.received("HEARTBEAT")
    assert hb and hb[0][2].type == mav2.MAV_TYPE_CAMERA
    caps = [m for _, _, m in ap.received("CAMERA_IMAGE_CAPTURED")]
    assert [c.image_index for c in caps] == list(range(len(kfs)))


@needs_exiftool
def test_a_serial_line_losing_bytes_loses_only_the_packets_hit(
    kf_bin: Path,
    short_nadir: Path,  # noqa: F811 - the fixture imported above
    tmp_path: Path,
) -> None:
    """One packet in ten loses 3 bytes on the line (a UART overrun, a radio glitch):
    it runs into the packet after it and fails its checksum. That one is rejected;
    the packet it ran into is still read (its bytes are parsed again), so every
    packet that arrived whole counts, and the tags are as accurate as on a clean line."""
    ap = PtyAutopilot(short_nadir / "flight.tlog", tmp_path / "ttyFC", damage_every=10)
    out = tmp_path / "lossy"
    r = select_over_serial(kf_bin, short_nadir, out, ap, 921600)
    assert r.returncode == 0, r.stderr
    tel = json.loads((out / "summary.json").read_text())["telemetry"]
    assert ap.damaged >= 50, (ap.damaged, ap.written)
    # Each damaged packet rejected once; the last may have been cut by the end of the
    # run instead. Packets written after the daemon stopped reading are not counted.
    assert ap.damaged - 1 <= tel["rejected_frames"] <= ap.damaged, (tel, ap.damaged)
    assert ap.written - 20 <= tel["messages"] <= ap.written, (tel, ap.written)
    assert tel["skipped_bytes"] == 0, tel
    print(
        f"serial line losing bytes: {ap.damaged} packets damaged, {tel['rejected_frames']} "
        f"rejected; {tel['messages']} of {ap.written} whole packets read"
    )
    kfs = keyframes(out)
    assert len(kfs) >= 5
    check_tags(short_nadir, out, ap, kfs)


@needs_exiftool
def test_serial_device_unplugged_and_back(
    kf_bin: Path,
    short_nadir: Path,  # noqa: F811 - the fixture imported above
    tmp_path: Path,
) -> None:
    """The radio is pulled out 3.5 s into the flight and plugged back 2 s later: the
    daemon keeps running, says it lost and reopened the port, tags the keyframes before
    and after, tags none in between with a made-up position, and the autopilot still
    gets one CAMERA_IMAGE_CAPTURED per keyframe (those made while the port was gone are
    queued and sent once it is back)."""
    unplug_s, plug_s = 3.5, 5.5
    ap = PtyAutopilot(
        short_nadir / "flight.tlog", tmp_path / "ttyFC", unplug_s=unplug_s, plug_s=plug_s
    )
    out = tmp_path / "out"
    # keyframes closer together than the default 0.70: several on each side
    r = select_over_serial(
        kf_bin, short_nadir, out, ap, 57600, "--target", "0.9", "--band", "0.8,0.95", timeout=60
    )
    assert r.returncode == 0, r.stderr
    log = r.stderr
    assert f"MAVLink link serial:{ap.device}:57600: serial port" in log, log
    assert f"MAVLink link serial:{ap.device}:57600 reopened" in log, log
    assert ap.lost > 50, "packets were due while the device was gone"

    tel = json.loads((out / "summary.json").read_text())["telemetry"]
    assert tel["reconnects"] >= 1, tel
    assert tel["link_errors"] >= 1, tel

    kfs = keyframes(out)
    tags = exif([out / k["file"] for k in kfs])
    # The daemon retries once a second; it reopened when it first spoke on the new pty.
    assert ap.start_ns is not None
    unplug_ns = ap.start_ns + int(unplug_s * 1e9)
    reopen_ns = min(t for epoch, t, _ in ap.heard if epoch == 1)
    assert reopen_ns - unplug_ns < (plug_s - unplug_s + 1.5) * 1e9
    before, after, between = [], [], []
    for k in kfs:
        t_ns = int(k["time_ns"])
        if t_ns < unplug_ns - 200_000_000:
            before.append(k)
        elif t_ns > reopen_ns + 300_000_000:
            after.append(k)
        else:
            between.append(k)
    print(
        f"serial unplugged for {(reopen_ns - unplug_ns) / 1e9:.2f} s: keyframes "
        f"{len(before)} before, {len(between)} around, {len(after)} after"
    )
    assert len(before) >= 2 and len(after) >= 2, (len(before), len(between), len(after))
    check_tags(short_nadir, out, ap, before + after)
    gone = [k for k in between if k["geotag"] != "ok"]
    assert gone, "a keyframe taken while the device was gone"
    for k in gone:
        assert k["lat"] == "" and "GPS:GPSLatitude" not in tags[k["file"]], k

    # Every keyframe reported over the serial line, once, in order, across the two ptys.
    caps = [m for _, _, m in ap.received("CAMERA_IMAGE_CAPTURED")]
    assert [c.image_index for c in caps] == list(range(len(kfs)))
    for c, k in zip(caps, kfs, strict=True):
        # the CSV's 9 decimals can end in 5: a tie that C++ and Python round apart
        if k["lat"]:
            assert abs(c.lat - float(k["lat"]) * 1e7) <= 0.5 + 1e-6, k
        else:
            assert c.lat == INT32_MAX, k
    late = {m.image_index for _, _, m in ap.received("CAMERA_IMAGE_CAPTURED", epoch=1)}
    assert {int(k["sequence"]) for k in gone} <= late, "queued while gone, sent once back"
    assert tel["captures_sent"] == len(kfs) and tel["captures_pending"] == 0, tel
    # and the daemon speaks on the new device: HEARTBEAT as a camera
    hb = ap.received("HEARTBEAT", epoch=1)
    assert hb and hb[0][2].type == mav2.MAV_TYPE_CAMERA


def test_daemon_run_over_serial_reports_its_captures(
    kf_bin: Path,
    short_nadir: Path,  # noqa: F811 - the fixture imported above
    tmp_path: Path,
) -> None:
    """`keyframed run` with telemetry.url on a serial device: its summary.json counts
    the capture reports (all sent, none pending, dropped or resent) and the link's
    errors and reopens (none)."""
    ap = PtyAutopilot(short_nadir / "flight.tlog", tmp_path / "ttyFC")
    etc = tmp_path / "etc"
    (etc / "conf.d").mkdir(parents=True)
    (etc / "keyframed.toml").write_text("")
    sets = [
        f"output.state_dir={tmp_path / 'state'}",
        "zenoh.enabled=false",
        "output.mcap=false",
        "camera.source=file",
        f"camera.path={short_nadir / 'video.avi'}",
        f"telemetry.url=serial:{ap.device}:115200",
        f"tagging.calibration={short_nadir / 'intrinsics.json'}",
    ]
    args = [str(kf_bin), "run", "--config-dir", str(etc)]
    for s in sets:
        args += ["--set", s]
    try:
        r = subprocess.run(args, capture_output=True, text=True, timeout=60)
    finally:
        ap.stop()
    assert r.returncode == 0, r.stderr
    fd = (tmp_path / "state" / "latest").resolve()
    summary = json.loads((fd / "summary.json").read_text())
    tel = summary["telemetry"]
    kfs = keyframes(fd / "keyframes")
    assert len(kfs) == summary["kept"] >= 5
    assert tel["geotagged"] == len(kfs), tel
    assert tel["captures_sent"] == len(kfs), tel
    assert tel["captures_pending"] == tel["captures_dropped"] == tel["captures_resent"] == 0
    assert tel["link_errors"] == tel["reconnects"] == 0, tel
    caps = [m for _, _, m in ap.received("CAMERA_IMAGE_CAPTURED")]
    assert [c.image_index for c in caps] == list(range(len(kfs)))
