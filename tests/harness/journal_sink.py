"""Stands in for journald: run as root in a private mount namespace (see
``run_under_journal``), it binds journald's native socket, runs a command with stderr
as the "journal stream" (JOURNAL_STREAM names it, as systemd does), and prints the
records that came through the socket as JSON lines.

Usage: journal_sink.py STDERR_FILE COMMAND [ARGS...]
"""

from __future__ import annotations

import json
import os
import socket
import struct
import subprocess
import sys
import time

SOCKET = "/run/systemd/journal/socket"
TIMEOUT_S = 90.0  # the command is killed after this (the test's own timeout is longer)


def parse(datagram: bytes) -> dict[str, str]:
    """One record of journald's native protocol: KEY=VALUE lines, or KEY, a 64-bit
    little-endian length and the value's bytes, for a value with a newline in it."""
    fields: dict[str, str] = {}
    at = 0
    while at < len(datagram):
        end = datagram.index(b"\n", at)
        line = datagram[at:end]
        if b"=" in line:
            key, value = line.split(b"=", 1)
            at = end + 1
        else:
            key = line
            (size,) = struct.unpack_from("<Q", datagram, end + 1)
            value = datagram[end + 9 : end + 9 + size]
            at = end + 9 + size + 1
        fields[key.decode()] = value.decode(errors="replace")
    return fields


def main() -> int:
    stderr_path, command = sys.argv[1], sys.argv[2:]
    os.makedirs(os.path.dirname(SOCKET), exist_ok=True)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(SOCKET)
    sock.settimeout(0.1)
    with open(stderr_path, "wb") as err:
        st = os.fstat(err.fileno())
        env = {**os.environ, "JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"}
        proc = subprocess.Popen(command, stderr=err, stdout=subprocess.DEVNULL, env=env)
        records = []
        deadline = time.monotonic() + TIMEOUT_S
        try:
            while proc.poll() is None:
                if time.monotonic() > deadline:
                    sys.stderr.write(f"journal_sink: {command[0]} still running: killed\n")
                    return 124
                try:
                    records.append(parse(sock.recv(1 << 20)))
                except TimeoutError:
                    pass
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        # What it sent before it exited is queued: all of it.
        sock.setblocking(False)
        while True:
            try:
                records.append(parse(sock.recv(1 << 20)))
            except BlockingIOError:
                break
    for r in records:
        print(json.dumps(r))
    return proc.returncode


if __name__ == "__main__":
    sys.exit(main())
