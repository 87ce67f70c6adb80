"""Zenoh transport security of `keyframed run`: TLS and user/password authentication,
configured only through the Zenoh JSON5 file named by `zenoh.config`.

A throw-away certificate authority and a server certificate for 127.0.0.1/localhost
are made at test time with the `openssl` command-line tool. The other side is a
Python eclipse-zenoh session (its wheel has Zenoh's default features, TLS and
user/password included). The daemon waits for a first pose from the fake autopilot
before it reads video (`telemetry.start_wait_ms`) but opens Zenoh first, so the test
connects and subscribes before the first keyframe: every keyframe must arrive,
byte-identical to the dataset folder, and a session without the right CA or password
must not get in at all. Zenoh's error does not say why a link failed, so each refused
session differs from the accepted one in that one setting only, tried while the
accepted one is connected. A daemon built without zenoh's `auth_usrpwd` feature ignores
`transport.auth` silently: the user/password tests then fail."""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import socket
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from fake_autopilot import autopilot_fixture
from flights import flight
from ports import free_port

zenoh = pytest.importorskip("zenoh", reason="eclipse-zenoh is installed by tools/setup.sh")

fake_autopilot = autopilot_fixture()

VEHICLE = "sec1"
USER, PASSWORD = "uav", "s3cret-pass"


@pytest.fixture(scope="module")
def short_flight() -> Path:
    return flight("nadir", width=320, height=180, seconds=3)


# ---- a throw-away PKI ----------------------------------------------------------------


@dataclass(frozen=True)
class Pki:
    ca: Path  # the CA certificate that signed the server's
    cert: Path  # server certificate: CN=localhost, SAN IP:127.0.0.1, DNS:localhost
    key: Path  # its private key (PKCS#8 PEM)
    rogue_ca: Path  # a CA that signed nothing here


def openssl(*args: str | Path, cwd: Path) -> None:
    r = subprocess.run(
        ["openssl", *map(str, args)], cwd=cwd, capture_output=True, text=True, timeout=60
    )
    assert r.returncode == 0, r.stderr


def make_ca(d: Path, name: str) -> tuple[Path, Path]:
    key, cert = d / f"{name}.key", d / f"{name}.pem"
    openssl(
        "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1",
        "-nodes", "-keyout", key, "-out", cert, "-days", "2", "-subj", f"/CN={name}",
        "-addext", "basicConstraints=critical,CA:TRUE",
        "-addext", "keyUsage=critical,keyCertSign,cRLSign",
        cwd=d,
    )  # fmt: skip
    return cert, key


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    if shutil.which("openssl") is None:
        pytest.fail("openssl not found (Debian package openssl, installed by tools/setup.sh)")
    d = tmp_path_factory.mktemp("pki")
    ca, ca_key = make_ca(d, "keyframed-test-ca")
    rogue_ca, _ = make_ca(d, "rogue-ca")
    key, csr, cert, ext = d / "server.key", d / "server.csr", d / "server.pem", d / "ext.cnf"
    openssl(
        "req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
        "-keyout", key, "-out", csr, "-subj", "/CN=localhost",
        cwd=d,
    )  # fmt: skip
    ext.write_text(
        "subjectAltName=IP:127.0.0.1,DNS:localhost\n"
        "basicConstraints=critical,CA:FALSE\n"
        "keyUsage=critical,digitalSignature\n"
        "extendedKeyUsage=serverAuth\n"
    )
    openssl(
        "x509", "-req", "-in", csr, "-CA", ca, "-CAkey", ca_key, "-set_serial", "2",
        "-days", "2", "-extfile", ext, "-out", cert,
        cwd=d,
    )  # fmt: skip
    return Pki(ca=ca, cert=cert, key=key, rogue_ca=rogue_ca)


# ---- the daemon and the Python sessions ------------------------------------------------


def start_daemon(
    kf_bin: Path,
    tmp_path: Path,
    fl: Path,
    zenoh_config: dict[str, Any],
    mport: int,
    *extra: str,
) -> subprocess.Popen[str]:
    """`keyframed run` on the flight's video; it opens Zenoh, then waits (up to 30 s)
    for the fake autopilot's first pose before it reads a frame."""
    etc = tmp_path / "etc"
    (etc / "conf.d").mkdir(parents=True)
    zconf = tmp_path / "zenoh.json5"
    zconf.write_text(json.dumps(zenoh_config, indent=2))
    (etc / "keyframed.toml").write_text("")
    sets = [
        f"output.state_dir={tmp_path / 'state'}",
        "camera.source=file",
        f"camera.path={fl / 'video.avi'}",
        f"telemetry.url=udpin:127.0.0.1:{mport}",
        "telemetry.start_wait_ms=30000",
        f"tagging.calibration={fl / 'intrinsics.json'}",
        "zenoh.enabled=true",
        f"zenoh.config={zconf}",
        f"zenoh.vehicle={VEHICLE}",
        *extra,
    ]
    args = [str(kf_bin), "run", "--config-dir", str(etc)]
    for s in sets:
        args += ["--set", s]
    return subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def session_config(
    *,
    mode: str = "peer",
    listen: str | None = None,
    connect: str | None = None,
    tls: dict[str, Any] | None = None,
    usrpwd: dict[str, Any] | None = None,
    timeout_ms: int = 60000,
) -> dict[str, Any]:
    """A Zenoh config: one endpoint, no multicast scouting; a session that connects
    gives up (zenoh.open raises) when the link is not up within `timeout_ms`."""
    conf: dict[str, Any] = {
        "mode": mode,
        "scouting": {"multicast": {"enabled": False}},
        "listen": {"endpoints": [listen] if listen else []},
        "connect": {"endpoints": [connect] if connect else []},
    }
    if connect:
        conf["connect"] |= {"timeout_ms": timeout_ms, "exit_on_failure": True}
    link: dict[str, Any] = {}
    if tls:
        link["tls"] = tls
    conf["transport"] = {"link": link}
    if usrpwd:
        conf["transport"]["auth"] = {"usrpwd": usrpwd}
    return conf


def open_session(conf: dict[str, Any]) -> Any:
    return zenoh.open(zenoh.Config.from_json5(json.dumps(conf)))


def refused(conf: dict[str, Any]) -> str:
    """The error of a session that must not get in (and fails if it does)."""
    try:
        s = open_session(conf)
    except Exception as e:  # zenoh.ZError
        return str(e)
    s.close()
    pytest.fail(f"a session got in with {conf['transport']}")


class Collector:
    """Subscribes to the vehicle's keyframes and status."""

    def __init__(self, session: Any) -> None:
        self.keyframes: list[tuple[dict[str, Any], bytes]] = []
        self.status: list[dict[str, Any]] = []
        self.subs = [
            session.declare_subscriber(
                f"keyframed/{VEHICLE}/keyframe",
                lambda s: self.keyframes.append(
                    (json.loads(s.attachment.to_bytes()), s.payload.to_bytes())
                ),
            ),
            session.declare_subscriber(
                f"keyframed/{VEHICLE}/status",
                lambda s: self.status.append(json.loads(s.payload.to_bytes())),
            ),
        ]

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()


def wait_for_peer(session: Any, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if list(session.info.peers_zid()) or list(session.info.routers_zid()):
            return
        time.sleep(0.05)
    pytest.fail("the session has no peer")


def fly(proc: subprocess.Popen[str], ap: Any, session: Any) -> str:
    """Starts the autopilot (the daemon then reads the video in real time) and waits
    for the daemon to finish; its stderr."""
    # The subscriptions must have reached the daemon before its first keyframe: a
    # query answered by its queryable (on the same link, after the declarations)
    # says they have, however loaded the machine is.
    # (Asked again until the daemon has joined: before that nothing answers at once.
    # The deadline only bounds a failure: a TLS handshake on a loaded 2-core machine,
    # the other test worker busy, has taken more than 20 s.)
    deadline = time.monotonic() + 60.0
    while not list(session.get(f"keyframed/{VEHICLE}/keyframes/0", timeout=5.0)):
        if proc.poll() is not None or time.monotonic() > deadline:
            if proc.poll() is None:
                proc.kill()
            _, stderr = proc.communicate()
            pytest.fail(f"the daemon's queryable did not answer (rc {proc.returncode}):\n{stderr}")
        time.sleep(0.05)
    ap.start()
    try:
        _, stderr = proc.communicate(timeout=90)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, stderr
    time.sleep(0.3)  # the last samples arrive
    return stderr


def check_every_keyframe(tmp_path: Path, got: Collector) -> int:
    fd = (tmp_path / "state" / "latest").resolve()
    with open(fd / "keyframes" / "keyframes.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) >= 2
    assert [m["file"] for m, _ in got.keyframes] == [r["file"] for r in rows]
    for (meta, payload), row in zip(got.keyframes, rows, strict=True):
        assert meta["vehicle"] == VEHICLE
        assert payload == (fd / "keyframes" / row["file"]).read_bytes()
    assert got.status and got.status[-1]["state"] == "done"
    return len(rows)


def tls_listener(pki: Pki) -> dict[str, Any]:
    return {"listen_certificate": str(pki.cert), "listen_private_key": str(pki.key)}


# ---- (a) TLS ----------------------------------------------------------------------------


def test_tls_only_a_client_trusting_the_ca_gets_the_keyframes(
    kf_bin: Path, short_flight: Path, pki: Pki, tmp_path: Path, fake_autopilot: Any
) -> None:
    """The daemon listens on tls/127.0.0.1 with its certificate; a peer that trusts the
    CA receives every keyframe; one trusting another CA, or none, cannot connect."""
    zport, mport = free_port(), free_port(socket.SOCK_DGRAM)
    endpoint = f"tls/127.0.0.1:{zport}"
    proc = start_daemon(
        kf_bin,
        tmp_path,
        short_flight,
        session_config(listen=endpoint, tls=tls_listener(pki)),
        mport,
    )
    ap = fake_autopilot(short_flight / "flight.tlog", target=("127.0.0.1", mport))
    session = None
    try:
        # retries until the daemon listens (it is up before it waits for telemetry)
        session = open_session(
            session_config(connect=endpoint, tls={"root_ca_certificate": str(pki.ca)})
        )
        wait_for_peer(session)
        got = Collector(session)
        for tls in ({"root_ca_certificate": str(pki.rogue_ca)}, {}):
            refused(session_config(connect=endpoint, tls=tls, timeout_ms=1000))
        # plain TCP to the TLS port gets nowhere either
        refused(session_config(connect=f"tcp/127.0.0.1:{zport}", timeout_ms=1000))
        fly(proc, ap, session)
        got.close()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        if session is not None:
            session.close()
    check_every_keyframe(tmp_path, got)


# ---- (b) user/password over TLS ------------------------------------------------------


def test_usrpwd_over_tls_only_the_right_password_gets_the_keyframes(
    kf_bin: Path, short_flight: Path, pki: Pki, tmp_path: Path, fake_autopilot: Any
) -> None:
    """The daemon listens on TLS and checks users against its dictionary file; a peer
    with the right user and password receives every keyframe; a wrong password, an
    unknown user or no credentials at all are refused."""
    dictionary = tmp_path / "users.txt"
    dictionary.write_text(f"{USER}:{PASSWORD}\nground:other-pass\n")
    os.chmod(dictionary, 0o600)
    zport, mport = free_port(), free_port(socket.SOCK_DGRAM)
    endpoint = f"tls/127.0.0.1:{zport}"
    proc = start_daemon(
        kf_bin,
        tmp_path,
        short_flight,
        session_config(
            listen=endpoint,
            tls=tls_listener(pki),
            usrpwd={"dictionary_file": str(dictionary)},
        ),
        mport,
    )
    ap = fake_autopilot(short_flight / "flight.tlog", target=("127.0.0.1", mport))
    ca = {"root_ca_certificate": str(pki.ca)}
    session = None
    try:
        session = open_session(
            session_config(connect=endpoint, tls=ca, usrpwd={"user": USER, "password": PASSWORD})
        )
        wait_for_peer(session)
        got = Collector(session)
        for creds in (
            {"user": USER, "password": "wrong"},
            {"user": "intruder", "password": PASSWORD},
            None,
        ):
            refused(session_config(connect=endpoint, tls=ca, usrpwd=creds, timeout_ms=1000))
        fly(proc, ap, session)
        got.close()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        if session is not None:
            session.close()
    check_every_keyframe(tmp_path, got)


# ---- (c) client of a router over TLS with user/password ------------------------------


def test_client_of_a_tls_router_with_usrpwd(
    kf_bin: Path, short_flight: Path, pki: Pki, tmp_path: Path, fake_autopilot: Any
) -> None:
    """The deployment of docs/deploy.md: the daemon is a Zenoh client of a router
    (a router-mode Python session here, zenohd in the field) reached over TLS with a
    user and password. Right credentials: every keyframe reaches the router's
    subscriber. A wrong password: the daemon does not start, and says why."""
    dictionary = tmp_path / "users.txt"
    dictionary.write_text(f"{USER}:{PASSWORD}\n")
    port = free_port()
    endpoint = f"tls/127.0.0.1:{port}"
    router = open_session(
        session_config(
            mode="router",
            listen=endpoint,
            tls=tls_listener(pki),
            usrpwd={"dictionary_file": str(dictionary)},
        )
    )
    try:
        got = Collector(router)

        def client(password: str) -> dict[str, Any]:
            conf = session_config(
                mode="client",
                connect=endpoint,
                tls={"root_ca_certificate": str(pki.ca)},
                usrpwd={"user": USER, "password": password},
            )
            del conf["connect"]["timeout_ms"], conf["connect"]["exit_on_failure"]
            return conf

        # Told not to go on without a session (zenoh.open_retry_s = 0): it stops.
        bad = tmp_path / "bad"
        mport = free_port(socket.SOCK_DGRAM)
        proc = start_daemon(
            kf_bin, bad, short_flight, client("wrong"), mport, "zenoh.open_retry_s=0"
        )
        try:
            _, stderr = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
        assert proc.returncode != 0
        assert "cannot open zenoh session" in stderr, stderr
        assert "zenoh.config:" in stderr, stderr  # the setting's name in a daemon's terms
        assert "panic" not in stderr, stderr
        # By default it goes on (records, waits for its autopilot), says why, and
        # keeps trying: still refused, nothing reaches the router.
        bad2 = tmp_path / "bad2"
        proc = start_daemon(kf_bin, bad2, short_flight, client("wrong"), mport)
        try:
            time.sleep(2.0)
            assert proc.poll() is None
            proc.send_signal(signal.SIGTERM)
            _, stderr = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
        assert proc.returncode == 0, stderr
        assert "cannot open zenoh session" in stderr, stderr
        assert "trying again every 5 s" in stderr, stderr
        assert "zenoh session open" not in stderr, stderr
        assert "no session opened in this flight" in stderr, stderr
        assert not got.keyframes and not got.status

        good = tmp_path / "good"
        mport = free_port(socket.SOCK_DGRAM)
        proc = start_daemon(kf_bin, good, short_flight, client(PASSWORD), mport)
        ap = fake_autopilot(short_flight / "flight.tlog", target=("127.0.0.1", mport))
        fly(proc, ap, router)
        got.close()
    finally:
        router.close()
    check_every_keyframe(good, got)


# ---- (d) the ground station over TLS with user/password --------------------------------


def test_ground_station_listens_on_tls_with_usrpwd(
    kf_bin: Path, short_flight: Path, pki: Pki, tmp_path: Path, fake_autopilot: Any
) -> None:
    """`keyframed-ground --zenoh-config` as docs/deploy.md sets it up: the ground
    station listens on TLS and checks users; the vehicle connects with the CA and its
    password. The dataset holds every keyframe, byte for byte."""
    import sys

    dictionary = tmp_path / "users.txt"
    dictionary.write_text(f"{USER}:{PASSWORD}\n")
    port = free_port()
    endpoint = f"tls/127.0.0.1:{port}"
    gconf = tmp_path / "ground.json5"
    gconf.write_text(
        json.dumps(
            session_config(
                listen=endpoint,
                tls=tls_listener(pki),
                usrpwd={"dictionary_file": str(dictionary)},
            )
        )
    )
    dataset = tmp_path / "dataset"
    ground = subprocess.Popen(
        [sys.executable, "-m", "keyframed.ground", "--out", str(dataset), "--quiet"]
        + ["--zenoh-config", str(gconf), "--until-done", "--duration", "60"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    vehicle = tmp_path / "vehicle"
    proc = None
    try:
        deadline = time.monotonic() + 20
        while True:  # the ground station's TLS port is open
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
                break
            except OSError:
                assert time.monotonic() < deadline and ground.poll() is None, ground.stderr
                time.sleep(0.05)
        mport = free_port(socket.SOCK_DGRAM)
        # The daemon's session opens once the link is up and the ground station's
        # subscriptions are known: no keyframe can go out before them.
        proc = start_daemon(
            kf_bin,
            vehicle,
            short_flight,
            session_config(
                connect=endpoint,
                tls={"root_ca_certificate": str(pki.ca)},
                usrpwd={"user": USER, "password": PASSWORD},
            ),
            mport,
        )
        ap = fake_autopilot(short_flight / "flight.tlog", target=("127.0.0.1", mport))
        time.sleep(0.3)
        ap.start()
        _, stderr = proc.communicate(timeout=90)
        assert proc.returncode == 0, stderr
        g_out, g_err = ground.communicate(timeout=60)
        assert ground.returncode == 0, g_err
    finally:
        for p in (proc, ground):
            if p is not None and p.poll() is None:
                p.kill()
                p.communicate()
    fd = (vehicle / "state" / "latest").resolve()
    with open(fd / "keyframes" / "keyframes.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) >= 2
    result = json.loads(g_out.strip().splitlines()[-1])
    assert result["vehicle"] == VEHICLE and result["keyframes"] == len(rows)
    for r in rows:
        got = (dataset / VEHICLE / "images" / r["file"]).read_bytes()
        assert got == (fd / "keyframes" / r["file"]).read_bytes()
