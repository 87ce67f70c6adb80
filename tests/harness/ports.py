"""Free loopback ports for the tests' servers (UDP MAVLink, TCP Zenoh)."""

from __future__ import annotations

import json
import os
import random
import socket
from pathlib import Path
from typing import Any

# Ports are picked below Linux's ephemeral range (32768-60999 by default), from which
# the kernel takes the source port of every outgoing connection: a port the kernel
# handed out with bind(0) can be taken again by another test's Zenoh session dialling
# out between our check and the server's bind. Each pytest-xdist worker draws from its
# own slice, and no port is handed out twice in one process.
_LOW, _HIGH = 20000, 32000
_given: set[int] = set()


def _slice() -> tuple[int, int]:
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw")
    count = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1") or 1)
    index = int(worker) if worker.isdigit() else 0
    width = (_HIGH - _LOW) // max(count, 1)
    start = _LOW + index * width
    return start, start + width


def _bindable(port: int) -> bool:
    for kind in (socket.SOCK_STREAM, socket.SOCK_DGRAM):
        with socket.socket(socket.AF_INET, kind) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                return False
    return True


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A port on 127.0.0.1 that nothing listens on right now (TCP or UDP), outside the
    range the kernel takes outgoing connections' ports from. KIND is kept for callers
    that say which protocol they need; the port is free for both."""
    del kind
    low, high = _slice()
    rng = random.Random()
    for _ in range(1000):
        port = rng.randrange(low, high)
        if port not in _given and _bindable(port):
            _given.add(port)
            return port
    raise RuntimeError(f"no free port in {low}-{high}")


def zenoh_listener_config(path: Path, port: int, endpoint_options: str = "") -> Path:
    """A Zenoh peer configuration (JSON5) listening on tcp/127.0.0.1:PORT, no scouting:
    the daemon's side of a loopback link. ENDPOINT_OPTIONS ("so_sndbuf=8192") go after
    the endpoint's #."""
    endpoint = f"tcp/127.0.0.1:{port}" + (f"#{endpoint_options}" if endpoint_options else "")
    conf = {
        "mode": "peer",
        "listen": {"endpoints": [endpoint]},
        "scouting": {"multicast": {"enabled": False}},
    }
    path.write_text(json.dumps(conf))
    return path


def zenoh_connect_config(path: Path, port: int, mode: str = "peer") -> Path:
    """A Zenoh configuration (JSON5) in MODE (peer or client) dialling
    tcp/127.0.0.1:PORT, no scouting: the daemon's side when the other side listens."""
    conf = {
        "mode": mode,
        "connect": {"endpoints": [f"tcp/127.0.0.1:{port}"]},
        "scouting": {"multicast": {"enabled": False}},
    }
    path.write_text(json.dumps(conf))
    return path


def zenoh_dialling(port: int) -> Any:
    """A zenoh.Config for a test's own session dialling tcp/127.0.0.1:PORT, no scouting:
    a watcher of the daemon, or the slow side of a relay."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    # Dialled before the daemon listens, Zenoh tries again after 1, 2, then 4 s: a
    # daemon slow to start on a busy machine would be heard seconds late. Every 0.2 s.
    conf.insert_json5(
        "connect/retry", "{period_init_ms: 200, period_max_ms: 200, period_increase_factor: 1}"
    )
    return conf
