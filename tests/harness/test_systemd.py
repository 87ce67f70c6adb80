"""The systemd unit, sysusers entry and sd_notify protocol, checked with systemd's tools.

`systemd-analyze verify` insists that every Exec*= binary exists and is executable,
so it runs on a copy of the unit whose /usr/bin/keyframed is the binary under test
(the installed unit differs only in that path; CMake writes the same substitution
for other prefixes).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from conftest import ROOT
from fake_autopilot import autopilot_fixture
from flights import flight
from ports import free_port, zenoh_connect_config, zenoh_listener_config
from sandbox import sandboxed

UNIT = ROOT / "systemd/keyframed.service"
SYSUSERS = ROOT / "systemd/keyframed.sysusers"

# Only the tests that run systemd-analyze need it; the unit's text and the notify
# protocol are checked everywhere.
needs_analyze = pytest.mark.skipif(
    shutil.which("systemd-analyze") is None,
    reason="systemd-analyze not installed (tools/setup.sh installs systemd)",
)


@pytest.fixture()
def unit_copy(kf_bin: Path, tmp_path: Path) -> Path:
    text = UNIT.read_text()
    assert "ExecStart=/usr/bin/keyframed run" in text
    path = tmp_path / "keyframed.service"
    path.write_text(text.replace("/usr/bin/keyframed", str(kf_bin)))
    return path


@needs_analyze
def test_unit_verifies(unit_copy: Path):
    p = subprocess.run(
        ["systemd-analyze", "verify", str(unit_copy)], capture_output=True, text=True, timeout=60
    )
    # verify exits 0 on some warnings (unknown keys): require silence too.
    assert p.returncode == 0, p.stderr
    assert p.stderr.strip() == "", p.stderr


def test_unit_has_the_agreed_settings():
    settings: dict[str, list[str]] = {}
    for line in UNIT.read_text().splitlines():
        if "=" in line and not line.startswith("#"):
            key, value = line.split("=", 1)
            settings.setdefault(key, []).append(value)
    one = {k: v[-1] for k, v in settings.items()}
    assert one["Type"] == "notify"
    assert one["ExecStart"] == "/usr/bin/keyframed run"
    assert one["ExecReload"] == "/bin/kill -HUP $MAINPID"
    assert one["WatchdogSec"] == "10"
    # A watchdog stop flushes the outputs (SIGTERM), not a core dump (SIGABRT); systemd
    # counts it a failure all the same, so Restart=on-failure restarts the daemon.
    assert one["WatchdogSignal"] == "SIGTERM"
    assert one["Restart"] == "on-failure"
    assert one["StartLimitIntervalSec"] == "0", "a long camera outage must not fail the unit"
    # ... but a bad configuration (keyframed run exits 78) or command line (2) does.
    assert one["RestartPreventExitStatus"].split() == ["2", "78"]
    assert one["User"] == "keyframed" and one["DynamicUser"] == "no"
    assert one["SupplementaryGroups"] == "video dialout"
    assert one["DevicePolicy"] == "closed"
    assert "char-video4linux rw" in settings["DeviceAllow"]
    for tty in ("ttyS", "ttyAMA", "ttyUSB", "ttyACM"):
        assert f"char-{tty} rw" in settings["DeviceAllow"]
    assert one["CapabilityBoundingSet"] == ""
    assert one["UMask"] == "0027"
    # Writable: its own state and log directories only.
    assert one["StateDirectory"] == "keyframed" and one["LogsDirectory"] == "keyframed"
    # The sandbox the issue asks for, each directive pinned (the exposure rating below
    # hardly moves without several of them: 1.6 to 3.6 with five removed).
    hardening = {
        "ProtectSystem": "strict",
        "ProtectHome": "yes",
        "PrivateTmp": "yes",
        "NoNewPrivileges": "yes",
        "MemoryDenyWriteExecute": "yes",
        "AmbientCapabilities": "",
        "SystemCallArchitectures": "native",
        "RestrictNamespaces": "yes",
        "ProtectKernelTunables": "yes",
        "ProtectKernelModules": "yes",
        "ProtectControlGroups": "yes",
    }
    assert {k: one.get(k) for k in hardening} == hardening
    assert one["RestrictAddressFamilies"].split() == [
        "AF_UNIX",
        "AF_INET",
        "AF_INET6",
        "AF_NETLINK",
    ]
    assert settings["SystemCallFilter"] == ["@system-service", "~@privileged"]


@needs_analyze
def test_security_exposure_is_ok(unit_copy: Path):
    p = subprocess.run(
        ["systemd-analyze", "security", "--offline=yes", "--no-pager", str(unit_copy)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert p.returncode == 0, p.stderr
    m = re.search(r"Overall exposure level for \S+: (\d+\.\d) (\w+)", p.stdout)
    assert m, p.stdout[-500:]
    exposure, rating = float(m.group(1)), m.group(2)
    # systemd 252 (analyze-security.c) rates exposure x10 >= 50 MEDIUM, >= 10 OK,
    # >= 1 SAFE, 0 PERFECT: "OK or better" is an exposure under 5.0.
    print(f"systemd-analyze security: exposure {exposure} {rating}")
    assert rating in ("OK", "SAFE", "PERFECT"), p.stdout[-2000:]
    # 1.6 as shipped; what raises it (a directive dropped) is a decision to make here.
    assert exposure <= 2.0


def test_sysusers_creates_the_user_in_a_scratch_root(tmp_path: Path):
    if shutil.which("systemd-sysusers") is None:
        pytest.skip("systemd-sysusers not installed")
    root = tmp_path / "root"
    (root / "etc").mkdir(parents=True)
    p = subprocess.run(
        ["systemd-sysusers", f"--root={root}", str(SYSUSERS)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert p.returncode == 0, p.stderr
    passwd = (root / "etc/passwd").read_text()
    assert re.search(r"^keyframed:x:\d+:\d+:keyframed daemon:/var/lib/keyframed:", passwd, re.M)
    groups = {line.split(":")[0]: line for line in (root / "etc/group").read_text().splitlines()}
    assert groups["video"].endswith(":keyframed")
    assert groups["dialout"].endswith(":keyframed")


def run_selftest(kf_bin: Path, tmp_path: Path, **env: str):
    """Runs `keyframed notify-selftest` with us as the service manager."""
    path = tmp_path / "notify.sock"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(str(path))
        sock.settimeout(10)
        full_env = {k: v for k, v in os.environ.items() if not k.startswith("WATCHDOG_")}
        full_env.update(NOTIFY_SOCKET=str(path), **env)
        p = subprocess.run(
            [str(kf_bin), "notify-selftest"],
            capture_output=True,
            text=True,
            timeout=30,
            env=full_env,
        )
        datagrams = []
        sock.setblocking(False)
        while True:
            try:
                datagrams.append(sock.recv(4096).decode())
            except BlockingIOError:
                break
    return p, datagrams


def test_notifier_sends_the_exact_datagrams(kf_bin: Path, tmp_path: Path):
    p, datagrams = run_selftest(kf_bin, tmp_path, WATCHDOG_USEC="4000000")
    assert p.returncode == 0, p.stderr
    assert "notify_socket=yes" in p.stdout
    assert "watchdog_usec=4000000" in p.stdout
    assert "ping_usec=2000000" in p.stdout
    assert len(datagrams) == 7, datagrams
    assert datagrams[0] == "STATUS=starting"
    assert datagrams[1] == "READY=1\nSTATUS=selecting keyframes"  # newline flattened
    assert datagrams[2] == "WATCHDOG=1"
    assert re.fullmatch(r"RELOADING=1\nMONOTONIC_USEC=\d+", datagrams[3]), datagrams[3]
    assert datagrams[4] == "READY=1"
    assert datagrams[5] == "STOPPING=1\nSTATUS=bye"
    assert datagrams[6] == "EXTEND_TIMEOUT_USEC=40000000"


def test_watchdog_meant_for_another_process_is_ignored(kf_bin: Path, tmp_path: Path):
    p, datagrams = run_selftest(kf_bin, tmp_path, WATCHDOG_USEC="4000000", WATCHDOG_PID="1")
    assert p.returncode == 0, p.stderr
    assert "watchdog_usec=0" in p.stdout
    assert len(datagrams) == 7


def test_without_notify_socket_nothing_is_sent(kf_bin: Path):
    env = {k: v for k, v in os.environ.items() if k != "NOTIFY_SOCKET"}
    p = subprocess.run(
        [str(kf_bin), "notify-selftest"], capture_output=True, text=True, timeout=30, env=env
    )
    assert p.returncode == 1  # every send reports "nobody listens"
    assert "notify_socket=no" in p.stdout


fake_autopilot = autopilot_fixture()


@needs_analyze
def test_the_sandbox_of_the_unit_refuses_what_it_should(tmp_path: Path) -> None:
    """The sandbox as tests/harness/sandbox.py builds it from the unit is in force:
    chroot (@privileged) fails, a raw packet socket's family is refused, and what the
    unit allows still works."""
    probe = (
        "import os, socket, sys\n"
        "try:\n    os.chroot('/')\nexcept PermissionError:\n    print('chroot refused')\n"
        "try:\n    socket.socket(socket.AF_PACKET, socket.SOCK_RAW)\n"
        "except OSError as e:\n    print('packet', e.errno)\n"
        "socket.socket(socket.AF_INET, socket.SOCK_DGRAM).close()\n"
        "print('inet ok')\n"
        "status = dict(ln.split(':', 1) for ln in open('/proc/self/status'))\n"
        "print(status['NoNewPrivs'].strip(), status['Seccomp'].strip())\n"
    )
    p = subprocess.run(
        sandboxed(UNIT, [sys.executable, "-c", probe]), capture_output=True, text=True, timeout=60
    )
    assert p.returncode == 0, p.stderr
    lines = p.stdout.split("\n")[:4]
    assert lines == ["chroot refused", "packet 97", "inet ok", "1 2"], p.stdout  # 2: filter


@needs_analyze
def test_the_daemon_runs_inside_the_units_system_call_sandbox(
    kf_bin: Path, tmp_path: Path, fake_autopilot: Any
) -> None:
    """`keyframed run` under the unit's SystemCallFilter=, RestrictAddressFamilies=,
    NoNewPrivileges= and MemoryDenyWriteExecute= (seccomp, as systemd applies them):
    a flight with telemetry over UDP, geotagged keyframes published over Zenoh, the
    MCAP record with its H.264 video, sd_notify: all of it works inside, so no system
    call the daemon (or OpenCV, libx264, exiv2, Zenoh) makes is one the unit forbids."""
    import zenoh

    fl = flight("nadir", width=320, height=180, seconds=3.0)
    # The replay starts when the daemon is first heard: the sandbox's seccomp filter,
    # compiled first, does not eat into the tlog's few seconds past the video.
    ap = fake_autopilot(fl / "flight.tlog", wait_for_peer=True)
    port = free_port()
    zconf = zenoh_connect_config(tmp_path / "zenoh.json5", port)
    cfg = tmp_path / "etc"
    (cfg / "conf.d").mkdir(parents=True)
    (cfg / "keyframed.toml").write_text("")
    notify = tmp_path / "notify.sock"
    ns = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    ns.bind(str(notify))
    ns.settimeout(0.1)
    cmd = [str(kf_bin), "run", "--config-dir", str(cfg)]
    for s in (
        f"output.state_dir={tmp_path / 'state'}",
        "camera.source=file",
        f"camera.path={fl / 'video.avi'}",
        f"tagging.calibration={fl / 'intrinsics.json'}",
        "output.preview_format=h264",
        f"telemetry.url=udpout:127.0.0.1:{ap.port}",
        f"zenoh.config={zconf}",
        "zenoh.vehicle=boxed",
    ):
        cmd += ["--set", s]
    received: list[bytes] = []
    listen = zenoh_listener_config(tmp_path / "ground.json5", port)
    session = zenoh.open(zenoh.Config.from_file(str(listen)))
    try:
        sub = session.declare_subscriber(
            "keyframed/boxed/keyframe", lambda s: received.append(s.payload.to_bytes())
        )
        ap.start()
        proc = subprocess.Popen(
            sandboxed(UNIT, cmd),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, "NOTIFY_SOCKET": str(notify)},
        )
        try:
            _, stderr = proc.communicate(timeout=120)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
        time.sleep(0.3)
        sub.undeclare()
    finally:
        session.close()
    messages = []
    with contextlib.suppress(TimeoutError):
        while True:
            messages.append(ns.recv(4096).decode())
    ns.close()
    assert proc.returncode == 0, stderr
    for refused in ("Operation not permitted", "Bad system call", "Address family not"):
        assert refused not in stderr, stderr
    assert any(m.startswith("READY=1") for m in messages), messages
    state = (tmp_path / "state" / "latest").resolve()
    summary = json.loads((state / "summary.json").read_text())
    assert summary["state"] == "done" and summary["written"] == summary["kept"] >= 2, summary
    assert summary["telemetry"]["geotagged"] == summary["written"], summary
    assert len(received) == summary["written"], (len(received), summary)
    assert (state / "flight.mcap").stat().st_size > 0
    assert "/camera/video" in (state / "flight.mcap").read_bytes().decode("latin-1")
