"""Free loopback ports for the tests' servers (UDP MAVLink, TCP Zenoh)."""

from __future__ import annotations

import json
import socket
from pathlib import Path


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def zenoh_listener_config(path: Path, port: int) -> Path:
    """A Zenoh peer configuration (JSON5) listening on tcp/127.0.0.1:PORT, no scouting:
    the daemon's side of a loopback link."""
    conf = {
        "mode": "peer",
        "listen": {"endpoints": [f"tcp/127.0.0.1:{port}"]},
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
