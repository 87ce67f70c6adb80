"""Keyframe latency on loopback, for `keyframed run` on a sample flight played in
real time, publishing to two Zenoh peers: a bare subscriber, which stamps receipt
in its callback, and a ground station (keyframed-ground's GroundStation, in this
process on a session of its own), stamped once it has stored the keyframe (the JPEG
written into its dataset, its metadata appended). Both share this process (and
Python's lock): the station's storing can delay the bare subscriber's stamp by a
little. All on this machine's CLOCK_MONOTONIC; the keyframe's metadata carries two
stamps of the daemon's:

- ``decided_ns``, when the selector kept the frame: decision to receipt is the
  issue's measure (JPEG encoding, tagging, the file write, Zenoh), for every
  keyframe, gap fills included (their decision is the promotion);
- ``time_ns``, the frame's arrival: capture to receipt adds the capture queue and
  the selection, for the keyframes kept on their own decision (a gap fill is by
  design an earlier frame kept later).

Also prints the MCAP file's size and the keyframes' sizes.

With ``--telemetry``, the flight's telemetry streams from the tests' fake autopilot
over UDP as in flight: each keyframe then also waits for a position sample newer
than its frame (``telemetry.wait_ms``), at the autopilot's rate (the sample flights'
tlogs hold GLOBAL_POSITION_INT at 10 Hz; the daemon asks a real autopilot for 20 Hz).

    .venv/bin/python tools/bench/latency_bench.py [--flight nadir] [--width 1920 --height 1080]
        [--runs 8] [--telemetry]

A 20 s flight gives 10-13 keyframes, so the flight is flown ``--runs`` times and the
keyframes of all runs pooled: the p99 is then a percentile, not the maximum.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import zenoh

ROOT = Path(__file__).resolve().parents[2]


def fly(fl: Path, ports: list[int], telemetry: bool, daemon: Path) -> tuple[dict, float]:
    """One `keyframed run` of the flight, publishing to the peers on ``ports``."""
    from fake_autopilot import FakeAutopilot  # the tests' (tests/harness)

    autopilot = FakeAutopilot(fl / "flight.tlog", boot_offset_ms=1_234_567) if telemetry else None
    with tempfile.TemporaryDirectory() as tmp:
        zconf = Path(tmp) / "zenoh.json5"
        zconf.write_text(
            json.dumps(
                {
                    "mode": "peer",
                    "connect": {"endpoints": [f"tcp/127.0.0.1:{p}" for p in ports]},
                    "scouting": {"multicast": {"enabled": False}},
                }
            )
        )
        (Path(tmp) / "etc").mkdir()
        sets = [
            "camera.source=file",
            f"camera.path={fl / 'video.avi'}",
            f"output.state_dir={tmp}/state",
            f"telemetry.url=udpout:127.0.0.1:{autopilot.port}" if autopilot else "telemetry.url=",
            f"zenoh.config={zconf}",
            "zenoh.vehicle=bench",
        ]
        cmd = [str(daemon), "run", "--config-dir", f"{tmp}/etc"]
        for s in sets:
            cmd += ["--set", s]
        if autopilot is not None:
            autopilot.start()
        try:
            subprocess.run(cmd, check=True, stderr=subprocess.DEVNULL)
        finally:
            if autopilot is not None:
                autopilot.stop()
        time.sleep(0.5)
        state = Path(tmp) / "state" / "latest"
        summary = json.loads((state / "summary.json").read_text())
        mcap_mb = (state / "flight.mcap").stat().st_size / 1e6
    return summary, mcap_mb


def stats(ms: list[float]) -> str:
    """Median, p99 and max of sorted latencies in ms."""
    p99 = ms[min(len(ms) - 1, round(0.99 * (len(ms) - 1)))]
    return (
        f"median {statistics.median(ms):.1f} ms, p99 {p99:.1f}, max {ms[-1]:.1f} "
        f"over {len(ms)} keyframes"
    )


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--flight", default="nadir")
    p.add_argument("--width", type=int, default=1920)
    p.add_argument("--height", type=int, default=1080)
    p.add_argument("--seconds", type=float, default=20.0)
    p.add_argument("--runs", type=int, default=8, help="flights flown, keyframes pooled")
    p.add_argument(
        "--telemetry", action="store_true", help="the flight's telemetry from a fake autopilot"
    )
    p.add_argument(
        "--bin",
        type=Path,
        default=Path(os.environ.get("KEYFRAMED_BIN", ROOT / "build/release/daemon/keyframed")),
        help="the daemon (default: $KEYFRAMED_BIN, else build/release/daemon/keyframed)",
    )
    args = p.parse_args()
    sys.path.insert(0, str(ROOT / "tests" / "harness"))
    from flights import flight  # the tests' cached sample flights
    from keyframed.ground import GroundStation

    fl = flight(args.flight, width=args.width, height=args.height, seconds=args.seconds)
    with socket.socket() as s1, socket.socket() as s2:  # two ports, both free at once
        s1.bind(("127.0.0.1", 0))
        s2.bind(("127.0.0.1", 0))
        ports = [s1.getsockname()[1], s2.getsockname()[1]]
    arrivals: list[tuple[int, dict, int]] = []
    stored: list[tuple[int, dict]] = []

    def on_keyframe(sample: zenoh.Sample) -> None:
        now = time.monotonic_ns()
        meta = json.loads(sample.attachment.to_bytes())
        arrivals.append((now, meta, len(sample.payload.to_bytes())))

    class TimedStation(GroundStation):
        """keyframed-ground's station, each keyframe stamped once it is stored (one
        that was not, a duplicate or a failed write, is not stamped)."""

        def _stored(self) -> int:
            return sum(d.count() for d in list(self.datasets.values()))

        def _on_keyframe(self, sample: zenoh.Sample) -> None:
            before = self._stored()
            super()._on_keyframe(sample)
            if self._stored() > before:
                stored.append((time.monotonic_ns(), json.loads(sample.attachment.to_bytes())))

    def listener(port: int) -> zenoh.Session:
        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        return zenoh.open(conf)

    session, ground_session = listener(ports[0]), listener(ports[1])
    sub = session.declare_subscriber("keyframed/*/keyframe", on_keyframe)
    written = frames = geotagged = 0
    mcap_mb = 0.0
    with tempfile.TemporaryDirectory() as dataset:
        station = TimedStation(ground_session, Path(dataset), "*", sift=False, quiet=True)
        for _ in range(args.runs):
            summary, size = fly(fl, ports, args.telemetry, args.bin)
            written += summary["written"]
            geotagged += (summary.get("telemetry") or {}).get("geotagged", 0)
            frames += summary["frames_read"]
            mcap_mb = size
        sub.undeclare()
        results = station.close()
    session.close()
    ground_session.close()
    in_dataset = sum(int(r.get("keyframes", 0)) for r in results)
    own = sorted(
        (now - int(m["time_ns"])) / 1e6
        for now, m, _ in arrivals
        # kept on their own decision; a promoted candidate carries its earlier
        # "redundant"/"blurry" reason and was kept later by design
        if (m.get("scores") or {}).get("reason") in ("first", "overlap_target", "paper_distance")
    )
    decided = sorted((now - int(m["decided_ns"])) / 1e6 for now, m, _ in arrivals)
    to_station = sorted((now - int(m["decided_ns"])) / 1e6 for now, m in stored)
    if not own or not decided or not to_station:
        print("no keyframes received", file=sys.stderr)
        return 1
    print(
        f"keyframed run, {args.width}x{args.height} {args.flight} flight, {args.seconds:.0f} s, "
        f"{args.runs} runs" + (", telemetry from the fake autopilot" if args.telemetry else "")
    )
    print(f"  keyframes received      {len(arrivals)} of {written} written")
    print(f"  in the station's dataset {in_dataset} of {written} written")
    if args.telemetry:
        print(f"  geotagged               {geotagged} of {written}")
    print(f"  decision to receipt     {stats(decided)}, every keyframe")
    print(f"  decision to stored      {stats(to_station)}, at keyframed-ground")
    print(f"  capture to receipt      {stats(own)}, gap fills excluded")
    print(f"  keyframe size           {statistics.mean(n for _, _, n in arrivals) / 1e3:.0f} KB")
    print(f"  MCAP file               {mcap_mb:.1f} MB a run ({frames // args.runs} frames)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
