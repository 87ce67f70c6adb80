"""The ground station (keyframed-ground) against a vehicle on loopback Zenoh.

The vehicle side here is a Python Zenoh session that publishes the keyframes a real
`keyframed select --telemetry` run wrote (tagged JPEGs, keyframes.csv) and answers
queries from that folder, as the daemon does; the daemon end to end is in
test_mcap_zenoh.py. The checks use independent readers: pycolmap for what COLMAP
makes of the dataset, exiftool's values through the JPEG bytes."""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import shutil
import signal
import subprocess
import sys
import sysconfig
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from colmap_check import colmap_cli_import
from flights import flight
from ports import free_port

zenoh = pytest.importorskip("zenoh", reason="eclipse-zenoh is installed by tools/setup.sh")


def select(kf_bin: Path, video: Path, out: Path, *args: str) -> str:
    """`keyframed select VIDEO --out OUT ARGS...`, which must succeed."""
    r = subprocess.run(
        [str(kf_bin), "select", str(video), "--out", str(out), "--quiet", *args],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    return r.stderr


@pytest.fixture(scope="module")
def tagged(kf_bin: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    fl = flight("nadir", width=480, height=270, seconds=8.0)
    out = tmp_path_factory.mktemp("tagged")
    select(
        kf_bin,
        fl / "video.avi",
        out,
        *["--telemetry", str(fl / "flight.tlog"), "--video-start", "2026-06-01T10:00:00Z"],
        *["--calibration", str(fl / "intrinsics.json")],
    )
    return out


def rows(out: Path) -> list[dict[str, str]]:
    with open(out / "keyframes.csv") as f:
        return list(csv.DictReader(f))


class Vehicle:
    """Publishes keyframes and serves keyframed/<name>/keyframes/<seq> and the range
    form keyframes/*?range=A..B from a folder, as the daemon does; once given a flight
    id, lists its flights on keyframed/<name>/flights as `keyframed run` does."""

    def __init__(self, name: str, folder: Path, port: int) -> None:
        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        self.session = zenoh.open(conf)
        self.name = name
        self.folder = folder
        self.rows = rows(folder)
        self.queries: list[tuple[int, int]] = []  # (first, last) asked for
        self.flight_queries: list[tuple[str, int, int]] = []  # naming a flight
        self.spans: list[tuple[float, float]] = []  # when each was being answered
        self.reply_delay = 0.0  # seconds before each keyframe's reply: a slow link
        self.catalogue_queries = 0
        self.stopped = threading.Event()
        self.unavailable: set[int] = set()
        self.garbled: set[int] = set()  # answered with an attachment that is no JSON
        # The daemon's flight id (none: an offline run), and the earlier ones it serves
        # on request (flight=ID), as after a restart: the same folder here.
        self.flight = ""
        self.earlier_flights: set[str] = set()
        self.published: dict[str, int] = {}  # keyframes published so far, by flight
        self.unlisted: set[str] = set()  # earlier flights its list leaves out (state lost)
        self.status_thread: threading.Thread | None = None
        self.pub = self.session.declare_publisher(
            f"keyframed/{name}/keyframe", congestion_control=zenoh.CongestionControl.BLOCK
        )
        self.queryable = self.session.declare_queryable(
            f"keyframed/{name}/keyframes/*", self._serve
        )
        self.catalogue = self.session.declare_queryable(
            f"keyframed/{name}/flights", self._serve_flights
        )

    def meta(self, row: dict[str, str]) -> dict[str, Any]:
        return {
            "flight": self.flight or None,
            "sequence": int(row["sequence"]),
            "frame_index": int(row["index"]),
            "file": row["file"],
            "lat": row["lat"],
            "lon": row["lon"],
            "alt_rel": row["alt_rel"],
            # Pix4D yaw, pitch, roll in degrees, null when unknown (as the daemon's)
            **{k: float(row[k]) if row[k] else None for k in ("yaw", "pitch", "roll")},
        }

    def _serve(self, query: Any) -> None:
        last = str(query.key_expr).rsplit("/", 1)[1]
        params = dict(p.split("=", 1) for p in str(query.parameters).split(";") if "=" in p)
        if last != "*":
            first = final = int(last)
        elif "range" in params:
            a, b = params["range"].split("..")
            first, final = int(a), int(b)
        else:
            first, final = 0, len(self.rows) - 1
        flight = params.get("flight", self.flight)
        if flight != self.flight and flight not in self.earlier_flights:
            query.reply_err(f"no flight '{flight}' here".encode())
            return
        if "flight" in params:
            self.flight_queries.append((flight, first, final))
        else:
            self.queries.append((first, final))
        start = time.monotonic()
        for seq in range(first, min(final, len(self.rows) - 1) + 1):
            if self.stopped.wait(self.reply_delay):
                return  # closed while a slow link was still answering
            if seq in self.unavailable:
                query.reply_err(b"not in the store")
                continue
            row = self.rows[seq]
            meta = json.dumps(self.meta(row) | {"flight": flight or None}).encode()
            query.reply(
                f"keyframed/{self.name}/keyframes/{seq}",
                (self.folder / row["file"]).read_bytes(),
                attachment=b"\xff{not json" if seq in self.garbled else meta,
            )
        self.spans.append((start, time.monotonic()))

    def _serve_flights(self, query: Any) -> None:
        """The earlier flights, whole, and the current one as far as it was published
        (`keyframed run` counts what it wrote); nothing without a flight id. Counted
        once answered: a test may change the flights then without changing the answer."""
        if self.flight:
            self._reply_flights(query)
        self.catalogue_queries += 1

    def _reply_flights(self, query: Any) -> None:
        flights = [
            {"flight": f, "keyframes": len(self.rows), "age_s": 1.0, "current": False}
            for f in sorted(self.earlier_flights - self.unlisted)
        ]
        flights.append(
            {
                "flight": self.flight,
                "keyframes": self.published.get(self.flight, 0),
                "age_s": 0.0,
                "current": True,
            }
        )
        query.reply(f"keyframed/{self.name}/flights", json.dumps({"flights": flights}).encode())

    def publish(self, seq: int, payload: bytes | None = None) -> None:
        row = self.rows[seq]
        data = (self.folder / row["file"]).read_bytes() if payload is None else payload
        self.published[self.flight] = max(self.published.get(self.flight, 0), seq + 1)
        self.pub.put(data, attachment=json.dumps(self.meta(row)).encode())

    def status(self) -> None:
        """Like the daemon: status over and over (it says how many keyframes exist)."""

        def loop() -> None:
            while not self.stopped.wait(0.2):
                self.session.put(
                    f"keyframed/{self.name}/status",
                    json.dumps({"keyframes": len(self.rows)}).encode(),
                )

        self.status_thread = threading.Thread(target=loop, daemon=True)
        self.status_thread.start()

    def close(self) -> None:
        self.stopped.set()
        if self.status_thread is not None:
            self.status_thread.join()
        self.queryable.undeclare()
        self.catalogue.undeclare()
        self.pub.undeclare()
        self.session.close()


def ground(out: Path, port: int, *extra: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "keyframed.ground", "--out", str(out), "--quiet"]
        + ["--connect", f"tcp/127.0.0.1:{port}", "--until-idle", "2", *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def wait_until(what: Any, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while not what():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.05)


def wait_connected(vehicle: Vehicle, timeout: float = 10.0) -> None:
    """Until the ground station's subscriber is known to the vehicle's publisher."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if vehicle.pub.matching_status.matching:
            time.sleep(0.2)  # the status subscriber is declared just after
            return
        time.sleep(0.05)
    raise AssertionError("the ground station never subscribed")


def test_gaps_are_filled_by_query_and_the_dataset_loads_in_colmap(
    tagged: Path, tmp_path: Path
) -> None:
    port = free_port()
    vehicle = Vehicle("uav1", tagged, port)
    out = tmp_path / "dataset"
    proc = ground(out, port, "--sift")
    try:
        wait_connected(vehicle)
        n = len(vehicle.rows)
        assert n >= 5
        lost = {1, 2, n - 1}  # a dropped link: two in the middle and the last one
        for seq in range(n):
            if seq not in lost:
                vehicle.publish(seq)
        vehicle.publish(0)  # a repeat must not be stored twice
        vehicle.status()  # "I have written n": the missing tail is fetched too
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
        vehicle.close()
    assert proc.returncode == 0, stderr
    summary = json.loads(stdout.strip().splitlines()[-1])
    assert summary["keyframes"] == n
    assert summary["fetched_by_query"] == len(lost)
    assert summary["duplicates_ignored"] == 1
    # one query per gap: 1..2 in the middle, n-1 at the end
    assert sorted(vehicle.queries) == [(1, 2), (n - 1, n - 1)], vehicle.queries
    assert summary["gap_queries"] == 2
    assert summary["calibrated"] is True

    ds = out / "uav1"
    for row in vehicle.rows:
        assert (ds / "images" / row["file"]).read_bytes() == (tagged / row["file"]).read_bytes()
    seqs = [json.loads(line)["sequence"] for line in (ds / "keyframes.jsonl").open()]
    assert seqs == list(range(n))

    # cameras.txt: the calibration, recovered from the JPEG tags alone
    fl = flight("nadir", width=480, height=270, seconds=8.0)
    intr = json.loads((fl / "intrinsics.json").read_text())
    cam = (ds / "cameras.txt").read_text().splitlines()[-1].split()
    assert cam[1] == "OPENCV" and int(cam[2]) == 480 and int(cam[3]) == 270
    fx, fy, cx, cy = (float(v) for v in cam[4:8])
    assert fx == pytest.approx(intr["fx"], rel=1e-4)
    assert fy == pytest.approx(intr["fy"], rel=1e-4)
    # COLMAP's principal point: from the image corner, OpenCV's + 0.5
    assert cx == pytest.approx(intr["cx"] + 0.5, abs=0.01)
    assert cy == pytest.approx(intr["cy"] + 0.5, abs=0.01)

    # cameras.json for OpenDroneMap: keyed as ODM's Photo.camera_id() names the camera
    # of these images (read here by exiftool), the same intrinsics normalised by the
    # longer side
    exif = {
        t["FileName"]: t
        for t in json.loads(
            subprocess.run(
                ["exiftool", "-j", "-n", str(ds / "images")],
                capture_output=True,
                text=True,
                check=True,
            ).stdout
        )
    }
    tags = exif[vehicle.rows[0]["file"]]
    # the sample's intrinsics.json names no camera: no Make or Model (ODM: empty)
    make, model = str(tags.get("Make", "")), str(tags.get("Model", ""))
    ratio = str(tags["FocalLengthIn35mmFormat"] / 36.0)[:6]
    size = f"{tags['ImageWidth']} {tags['ImageHeight']}"
    camera_id = f"{make.strip()} {model.strip()} {size} brown {ratio}".lower()
    odm = json.loads((ds / "cameras.json").read_text())
    # ODM's id with --camera-lens brown, then as its default "auto" makes it from the
    # XMP ModelType: the same camera under both
    auto_id = camera_id.replace(" brown ", " perspective ")
    assert list(odm) == [camera_id, auto_id] and summary["odm_camera"] == camera_id
    assert odm[auto_id] == odm[camera_id]
    brown = odm[camera_id]
    assert brown["projection_type"] == "brown" and (brown["width"], brown["height"]) == (480, 270)
    assert brown["focal_x"] * 480 == pytest.approx(fx, rel=1e-9)
    assert brown["focal_y"] * 480 == pytest.approx(fy, rel=1e-9)
    assert 240 + brown["c_x"] * 480 == pytest.approx(cx, rel=1e-9)
    assert 135 + brown["c_y"] * 480 == pytest.approx(cy, rel=1e-9)
    assert [brown[k] for k in ("k1", "k2", "p1", "p2")] == pytest.approx(
        [float(v) for v in cam[8:12]], abs=1e-12
    )

    pairs = [tuple(line.split()) for line in (ds / "pairs.txt").read_text().splitlines()]
    files = [r["file"] for r in vehicle.rows]
    for a, b in zip(files, files[1:], strict=False):
        assert (a, b) in pairs
    assert len(pairs) < n * (n - 1) / 2 or n < 6, "pairs are not exhaustive"

    # geo.txt: position, the camera's yaw pitch roll and the accuracies, as the
    # keyframe's metadata and its XMP (read by exiftool) have them: no made-up 0 0 0
    geo = (ds / "geo.txt").read_text().splitlines()
    assert geo[0] == "EPSG:4326" and len(geo) == n + 1
    by_file = {r["file"]: r for r in vehicle.rows}
    for line in geo[1:]:
        name, *values = line.split()
        assert len(values) == 8, line
        lon, lat, _, yaw, pitch, roll, xy, z = (float(v) for v in values)
        t, row = exif[name], by_file[name]
        assert (lat, lon) == pytest.approx((float(row["lat"]), float(row["lon"])), abs=1e-7)
        assert [yaw, pitch, roll] == pytest.approx([t["Yaw"], t["Pitch"], t["Roll"]], abs=1e-6)
        assert [yaw, pitch, roll] == pytest.approx(
            [float(row["yaw"]), float(row["pitch"]), float(row["roll"])], abs=1e-4
        )  # the metadata's, to its 4 decimals
        assert (xy, z) == pytest.approx((t["GPSXYAccuracy"], t["GPSZAccuracy"]), abs=1e-3)
    assert any(abs(float(line.split()[4])) > 1.0 for line in geo[1:]), "a yaw other than 0"

    # SIFT in COLMAP's import format
    for f in files:
        lines = (ds / "features" / (f + ".txt")).read_text().splitlines()
        count, dim = (int(v) for v in lines[0].split())
        assert dim == 128 and count == len(lines) - 1 and count > 50
        first = lines[1].split()
        assert len(first) == 4 + 128 and all(0 <= int(v) <= 255 for v in first[4:])

    # COLMAP: cameras.txt read by COLMAP's own text reader (a model folder with no
    # images or points yet), so that its format, not only our parsing of it, is checked
    pycolmap = pytest.importorskip("pycolmap", reason="pycolmap is installed by tools/setup.sh")
    model_dir = tmp_path / "colmap_model"
    model_dir.mkdir()
    shutil.copy(ds / "cameras.txt", model_dir / "cameras.txt")
    (model_dir / "images.txt").write_text("# no images\n")
    (model_dir / "points3D.txt").write_text("# no points\n")
    rec = pycolmap.Reconstruction(str(model_dir))
    assert len(rec.cameras) == 1
    read = next(iter(rec.cameras.values()))
    assert str(read.model).endswith("OPENCV") and (read.width, read.height) == (480, 270)
    assert read.focal_length_x == pytest.approx(intr["fx"], rel=1e-4)
    assert read.focal_length_y == pytest.approx(intr["fy"], rel=1e-4)
    assert read.principal_point_x == pytest.approx(intr["cx"] + 0.5, abs=0.01)
    assert read.principal_point_y == pytest.approx(intr["cy"] + 0.5, abs=0.01)
    # OPENCV: fx, fy, cx, cy, then k1, k2, p1, p2 as OpenCV orders them
    assert list(read.params[4:8]) == pytest.approx(intr["distortion"][:4], abs=1e-6)

    # COLMAP: the camera as given, and a GPS prior per image from the EXIF tags
    db_path = tmp_path / "colmap.db"
    opts = pycolmap.ImageReaderOptions()
    opts.camera_model = "OPENCV"
    opts.camera_params = ",".join(cam[4:])
    pycolmap.Database.open(db_path).close()  # creates the schema
    pycolmap.import_images(db_path, ds / "images", pycolmap.CameraMode.SINGLE, options=opts)
    db = pycolmap.Database.open(db_path)
    try:
        cams = db.read_all_cameras()
        assert len(cams) == 1
        assert cams[0].params[0] == pytest.approx(intr["fx"], rel=1e-4)
        images = db.read_all_images()
        assert len(images) == n
        priors = db.read_all_pose_priors()
        assert len(priors) == n, "COLMAP read a GPS prior from every keyframe"
        by_name = {r["file"]: r for r in vehicle.rows}
        lat_lon = np.array(
            [[float(by_name[i.name]["lat"]), float(by_name[i.name]["lon"])] for i in images]
        )
        got = np.array([[p.position[0], p.position[1]] for p in priors])
        # COLMAP's WGS84 prior is (lat, lon, alt); its order follows image ids
        assert np.allclose(np.sort(got[:, 0]), np.sort(lat_lon[:, 0]), atol=1e-7)
        assert np.allclose(np.sort(got[:, 1]), np.sort(lat_lon[:, 1]), atol=1e-7)
    finally:
        db.close()

    # COLMAP's own command line (Debian's 3.8, installed by tools/setup.sh), as
    # docs/deploy.md gives it: the camera of cameras.txt, the SIFT files as they are
    # (every keypoint), the listed pairs matched; consecutive keyframes (60-85 %
    # overlap) verify
    assert shutil.which("colmap"), "COLMAP is installed by tools/setup.sh"
    cli = colmap_cli_import(ds, tmp_path / "colmap-cli")
    counts = {
        f: int((ds / "features" / (f + ".txt")).read_text().split(maxsplit=1)[0]) for f in files
    }
    assert cli.keypoints == counts
    assert cli.camera_model == 4  # OPENCV
    assert cli.camera_params == pytest.approx([float(v) for v in cam[4:]], rel=1e-9)
    assert cli.pairs_matched >= len(files) - 1
    assert cli.pairs_verified >= len(files) - 1, cli
    print(f"COLMAP 3.8 CLI: {len(pairs)} pairs listed, {cli.pairs_verified} verified")


def test_a_signal_while_closing_stops_waiting_for_a_vehicle_that_does_not_answer(
    tagged: Path, tmp_path: Path
) -> None:
    """The station ends (idle) with a gap whose query the vehicle never answers (a
    link that carries nothing back): closing would wait out the query's timeout, 45 s
    a chunk. SIGINT then stops the waiting at once: the dataset is written with what
    arrived, the gap is reported missing, exit status 3."""
    port = free_port()
    vehicle = Vehicle("uav9", tagged, port)
    vehicle.reply_delay = 120.0
    out = tmp_path / "dataset"
    proc = ground(out, port)
    try:
        wait_connected(vehicle)
        n = len(vehicle.rows)
        for seq in range(n):
            if seq != 2:
                vehicle.publish(seq)
        vehicle.status()
        wait_until(lambda: vehicle.queries, timeout=30)
        time.sleep(3.0)  # idle by now: closing, waiting for the answer
        assert proc.poll() is None
        t0 = time.monotonic()
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=20)
        took = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
        vehicle.close()
    assert took < 5.0, took
    assert proc.returncode == 3, stderr
    assert "stopped without waiting for missing keyframes" in stderr
    summary = json.loads(stdout.strip().splitlines()[-1])
    assert summary["keyframes"] == n - 1 and summary["missing"], summary
    assert len((out / "uav9" / "geo.txt").read_text().splitlines()) == n  # header + n - 1


def test_a_restarted_vehicle_keeps_both_flights_apart(tagged: Path, tmp_path: Path) -> None:
    """The daemon restarts mid-survey (the watchdog, a power blip): its new flight
    counts sequence numbers from 0 again and writes the same file names. Both flights
    end up in the dataset, none overwritten or dropped as a duplicate; a gap in the
    earlier flight is fetched by a query that names it."""
    port = free_port()
    vehicle = Vehicle("uav3", tagged, port)
    out = tmp_path / "dataset"
    proc = ground(out, port)
    n = len(vehicle.rows)
    try:
        wait_connected(vehicle)
        vehicle.flight = "20261202T101500Z"
        for seq in range(n):
            if seq != 2:  # lost on the link, and the daemon then restarted
                vehicle.publish(seq)
        vehicle.earlier_flights = {vehicle.flight}
        vehicle.flight = "20261202T102000Z"
        for seq in range(n):
            vehicle.publish(seq)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
        vehicle.close()
    assert proc.returncode == 0, stderr
    summary = json.loads(stdout.strip().splitlines()[-1])
    assert summary["keyframes"] == 2 * n and not summary["missing"], summary
    assert summary["duplicates_ignored"] == 0 and summary["fetched_by_query"] == 1
    assert vehicle.flight_queries == [("20261202T101500Z", 2, 2)], vehicle.flight_queries
    ds = out / "uav3"
    metas = [json.loads(line) for line in (ds / "keyframes.jsonl").open()]
    assert [(m["flight"], m["sequence"]) for m in metas] == [
        (f, s) for f in ("20261202T101500Z", "20261202T102000Z") for s in range(n)
    ]
    names = sorted(p.name for p in (ds / "images").glob("*.jpg"))
    files = [r["file"] for r in vehicle.rows]
    assert names == sorted(files + [f"20261202T102000Z_{f}" for f in files])
    for m in metas:
        source = tagged / m["file"].removeprefix("20261202T102000Z_")
        assert (ds / "images" / m["file"]).read_bytes() == source.read_bytes()
    assert len((ds / "geo.txt").read_text().splitlines()) == 2 * n + 1


@pytest.mark.parametrize("listed", [True, False], ids=["listed", "state-lost"])
def test_the_end_of_a_flight_the_link_lost_is_fetched_or_reported(
    tagged: Path, tmp_path: Path, listed: bool
) -> None:
    """The link drops at the end of a flight: its last two keyframes and its final
    status never reach the station, which knows only the count of the last status it
    heard, and had asked for the vehicle's flights while it flew. The daemon restarts:
    hearing of a flight it had not known, the station asks for the list again, learns
    the first flight's final count and fetches its end by query. A vehicle whose list
    no longer has the first flight (its state directory lost) cannot tell how many
    keyframes it ended with: the summary names the flight and the exit status is 3."""
    port = free_port()
    vehicle = Vehicle("uav5", tagged, port)
    out = tmp_path / "dataset"
    images = out / "uav5" / "images"
    proc = ground(out, port)
    n = len(vehicle.rows)
    first, second = "20261202T101500Z", "20261202T102000Z"

    def status(state: str, kept: int) -> None:
        body = {"state": state, "frames": 100, "kept": kept, "flight": vehicle.flight}
        vehicle.session.put(  # sent once, so never dropped under congestion
            "keyframed/uav5/status",
            json.dumps(body).encode(),
            congestion_control=zenoh.CongestionControl.BLOCK,
        )

    try:
        wait_connected(vehicle)
        vehicle.flight = first
        for seq in range(n - 2):
            vehicle.publish(seq)
        status("running", n - 2)
        wait_until(lambda: vehicle.catalogue_queries >= 1)
        wait_until(lambda: len(list(images.glob("*.jpg"))) == n - 2)
        vehicle.earlier_flights = {first}
        vehicle.unlisted = set() if listed else {first}
        vehicle.flight = second
        for seq in range(n):
            vehicle.publish(seq)
        status("done", n)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
        vehicle.close()
    summary = json.loads(stdout.strip().splitlines()[-1])
    assert summary["duplicates_ignored"] == 0 and not summary["missing"], summary
    names = sorted(p.name for p in images.glob("*.jpg"))
    files = [r["file"] for r in vehicle.rows]
    if listed:
        assert proc.returncode == 0, stderr
        assert summary["keyframes"] == 2 * n and not summary["flights_end_unknown"], summary
        assert vehicle.flight_queries == [(first, n - 2, n - 1)], vehicle.flight_queries
        assert names == sorted(files + [f"{second}_{f}" for f in files])
    else:
        assert proc.returncode == 3 and "still missing" in stderr, (stderr, json.dumps(summary))
        assert summary["keyframes"] == 2 * n - 2, summary
        assert summary["flights_end_unknown"] == [first], summary
        assert names == sorted(files[: n - 2] + [f"{second}_{f}" for f in files])


def test_a_flight_list_decides_what_is_fetched_and_a_resumed_dataset_keeps_its_names(
    tmp_path: Path,
) -> None:
    """What the station makes of a vehicle's list of flights (keyframed/<v>/flights):
    the running flight, a recent earlier one and one it already holds are fetched, an
    old one is not, and entries that are no flight are passed over. A dataset resumed
    after its index was rewritten in flight-id order keeps giving plain names to the
    flight that had them."""
    from keyframed.ground import VehicleDataset

    ds = VehicleDataset(tmp_path, "uav9", None)
    ds.add({"flight": "B", "sequence": 0, "file": "000000.jpg"}, b"b0")
    ds.note_catalogue(
        [
            {"flight": "0-old", "keyframes": 4, "age_s": 90000.0, "current": False},
            {"flight": "A", "keyframes": 2, "age_s": 600.0, "current": False},
            {"flight": "B", "keyframes": 3, "age_s": 0.5, "current": True},
            {"flight": "C", "keyframes": 1e400, "age_s": 1.0},
            {"flight": "D", "keyframes": 10**9, "age_s": 1.0},
            {"flight": "E", "keyframes": 1, "age_s": None},
            "not a flight",
            {"keyframes": 5},
        ],
        max_age_s=3600.0,
    )
    assert sorted(ds.missing()) == [("A", 0), ("A", 1), ("B", 1), ("B", 2)]
    assert ds.skipped_flights == ["0-old", "E"]
    ds.add({"flight": "A", "sequence": 0, "file": "000000.jpg"}, b"a0")
    assert (ds.images / "A_000000.jpg").read_bytes() == b"a0"
    ds.finish()  # the index now lists A before B
    again = VehicleDataset(tmp_path, "uav9", None)
    again.add({"flight": "B", "sequence": 1, "file": "000001.jpg"}, b"b1")
    again.add({"flight": "A", "sequence": 1, "file": "000001.jpg"}, b"a1")
    assert (again.images / "000001.jpg").read_bytes() == b"b1"
    assert (again.images / "A_000001.jpg").read_bytes() == b"a1"
    assert (again.images / "000000.jpg").read_bytes() == b"b0"


def test_a_damaged_index_line_costs_that_line_not_the_dataset(tmp_path: Path) -> None:
    """keyframes.jsonl garbled by a power cut or a hand edit (bytes that are no UTF-8,
    JSON that is no object, a name that is no string or not one the station gives):
    the dataset still opens with every good line, and takes new keyframes. A flight id
    with a path in it is kept as the station keys it, so a resume keys it the same."""
    from keyframed.ground import VehicleDataset

    ds = VehicleDataset(tmp_path, "uav5", None)
    assert ds.add({"flight": "x/F1", "sequence": 0, "file": "000000.jpg"}, b"f0")
    ds.add({"flight": "x/F1", "sequence": 1, "file": "000001.jpg"}, b"f1")
    (ds.images / "other.jpg").write_bytes(b"?")
    index = ds.dir / "keyframes.jsonl"
    with open(index, "ab") as f:
        f.write(b'{"flight": "F1", "sequence": 2, "file": "00\xff\xfe2.jpg"}\n')
        f.write(b"\xff\xfe garbage\n")
        for bad in ("null", "[1, 2]", '"text"', '{"file": 5, "sequence": 3}'):
            f.write(bad.encode() + b"\n")
        f.write(b'{"file": "../uav5/images/other.jpg", "sequence": 4}\n')
        f.write(b'{"file": "other.jpg", "sequence": "four"}\n')
    again = VehicleDataset(tmp_path, "uav5", None)
    assert sorted(again.meta) == [("F1", 0), ("F1", 1)]
    assert again.missing() == []
    assert not again.add({"flight": "x/F1", "sequence": 1, "file": "000001.jpg"}, b"f1")
    assert again.add({"flight": "F1", "sequence": 2, "file": "000002.jpg"}, b"f2")
    assert again.add({"flight": "G", "sequence": 0, "file": "other.jpg"}, b"o")
    assert (again.images / "other.jpg").read_bytes() == b"?"
    assert again.duplicates == 1
    summary = again.finish()
    assert summary["keyframes"] == 4 and summary["missing"] == [], summary
    lines = [json.loads(line) for line in index.read_text().splitlines()]
    assert [(m["flight"], m["sequence"], m["file"]) for m in lines] == [
        ("F1", 0, "000000.jpg"),
        ("F1", 1, "000001.jpg"),
        ("F1", 2, "000002.jpg"),
        ("G", 0, "G_other.jpg"),
    ]


def test_a_keyframe_the_disk_did_not_take_keeps_its_name_for_its_return(tmp_path: Path) -> None:
    """A write that fails (a full disk; here a folder in the image's place) leaves no
    partial copy behind, and the keyframe, fetched again, gets its own name, not a
    name made up because the failed write had taken it."""
    from keyframed.ground import VehicleDataset

    ds = VehicleDataset(tmp_path, "uav8", None)
    meta = {"flight": "F1", "sequence": 0, "frame_index": 0}
    (ds.images / "000000.jpg").mkdir()
    with pytest.raises(OSError):
        ds.add(meta, b"jpeg bytes")
    assert sorted(p.name for p in ds.images.iterdir()) == ["000000.jpg"]  # no .tmp left
    assert ds.missing() == [] and ds.count() == 0
    (ds.images / "000000.jpg").rmdir()
    assert ds.add(meta, b"jpeg bytes")
    assert sorted(p.name for p in ds.images.iterdir()) == ["000000.jpg"]
    assert (ds.images / "000000.jpg").read_bytes() == b"jpeg bytes"
    assert ds.finish()["keyframes"] == 1


def test_a_keyframe_whose_index_line_the_disk_did_not_take_is_kept(tmp_path: Path) -> None:
    """The image is written but keyframes.jsonl's append fails (a full disk; here the
    index is /dev/full): the keyframe counts as stored, is not asked for again, and
    the index rewritten whole holds its line."""
    from keyframed.ground import VehicleDataset

    ds = VehicleDataset(tmp_path, "uav8", None)
    index = ds.dir / "keyframes.jsonl"
    index.unlink(missing_ok=True)
    index.symlink_to("/dev/full")
    assert ds.add({"flight": "F1", "sequence": 0, "frame_index": 7}, b"jpeg bytes")
    assert (ds.images / "000007.jpg").read_bytes() == b"jpeg bytes"
    assert ds.missing() == [] and ds.count() == 1
    assert ds.finish()["keyframes"] == 1
    assert not index.is_symlink()
    lines = [json.loads(line) for line in index.read_text().splitlines()]
    assert [(m["flight"], m["sequence"], m["file"]) for m in lines] == [("F1", 0, "000007.jpg")]


def test_nothing_is_stored_once_the_datasets_files_are_written(tmp_path: Path) -> None:
    """A gap query's reply that arrives after finish() wrote pairs.txt and geo.txt (a
    second Ctrl-C stopped the waiting) is not stored where those files would not name
    it: it stays missing for a later run on the folder."""
    from keyframed.ground import VehicleDataset

    ds = VehicleDataset(tmp_path, "uav8", None)
    assert ds.add({"flight": "F1", "sequence": 0, "frame_index": 0}, b"a")
    ds.note_end("F1")
    with ds.lock:
        ds.announced["F1"] = 1
    summary = ds.finish()
    assert summary["missing"] == [1], summary
    assert not ds.add({"flight": "F1", "sequence": 1, "frame_index": 5}, b"b")
    assert sorted(p.name for p in ds.images.iterdir()) == ["000000.jpg"]
    assert len((ds.dir / "keyframes.jsonl").read_text().splitlines()) == 1


def test_a_vehicle_whose_folder_cannot_be_made_is_said_once(tagged: Path, tmp_path: Path) -> None:
    """The vehicle is heard but its folder cannot be made (a file in its place, a
    folder of another user's): one line that says so, the vehicle in the summary with
    that error, exit 3, and --until-idle ends, rather than a line for each message
    and "heard no vehicle" (exit 4) at the end."""
    port = free_port()
    vehicle = Vehicle("uav6", tagged, port)
    out = tmp_path / "dataset"
    out.mkdir()
    (out / "uav6").write_text("a file where the vehicle's folder goes")
    proc = ground(out, port)
    try:
        wait_connected(vehicle)
        vehicle.status()
        for seq in range(len(vehicle.rows)):
            vehicle.publish(seq)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
        vehicle.close()
    assert proc.returncode == 3, (proc.returncode, stderr)
    said = [ln for ln in stderr.splitlines() if "cannot make its dataset folder" in ln]
    assert said == [f"keyframed-ground: uav6: cannot make its dataset folder {out}/uav6: "
                    "Not a directory"], stderr  # fmt: skip
    assert "bad keyframe message" not in stderr and "bad status message" not in stderr, stderr
    assert "heard no vehicle" not in stderr, stderr
    summary = json.loads(stdout.strip().splitlines()[-1])
    assert summary == {"vehicle": "uav6", "keyframes": 0, "error": said[0].split(": ", 2)[2]}


def test_progress_shows_the_newest_keyframes_position(tmp_path: Path) -> None:
    """The progress line's position is the newest keyframe's that has one (the latest
    flight, its highest sequence), not that of the last one to arrive: a gap filled
    later, or an earlier flight fetched, is an older keyframe."""
    from keyframed.ground import VehicleDataset

    ds = VehicleDataset(tmp_path, "uav7", None)
    assert ds.progress().startswith("uav7: 0 keyframes, ") and " at " not in ds.progress()
    flight = "20261204T101500Z"
    ds.add({"flight": flight, "sequence": 3, "lat": 51.3, "lon": 7.3}, b"3")
    ds.add({"flight": flight, "sequence": 4, "lat": "", "lon": ""}, b"4")  # not geotagged
    ds.add({"flight": flight, "sequence": 1, "lat": 51.1, "lon": 7.1}, b"1", fetched=True)
    ds.add({"flight": "20261204T090000Z", "sequence": 9, "lat": 50.9, "lon": 6.9}, b"e")
    line = ds.progress()
    assert line.startswith("uav7: 4 keyframes, ") and line.endswith(" at 51.300000,7.300000"), line


def test_which_flights_ended_with_their_count_unknown(tmp_path: Path) -> None:
    """The flights the station saw followed by another, and whether it learned how
    many keyframes they ended with: from a final status (which may overtake the next
    flight's first keyframes) or from the vehicle's list naming them as not running.
    A flight the last list did not name makes the station ask for the list again."""
    from keyframed.ground import VehicleDataset

    ds = VehicleDataset(tmp_path, "uav9", None)
    ds.note_running("A")
    ds.note_end("B")  # B's final status before any of its keyframes
    ds.note_running("B")
    assert ds.end_unknown() == ["A"]
    ds.note_running("C")
    ds.note_running("A")  # a late message of A's: A stays behind C
    assert ds.current == "C" and ds.end_unknown() == ["A"]
    ds.catalogue_due = False
    ds.note_catalogue(
        [
            {"flight": "A", "keyframes": 3, "age_s": 50.0, "current": False},
            {"flight": "C", "keyframes": 1, "age_s": 0.5, "current": True},
        ],
        max_age_s=3600.0,
    )
    assert ds.end_unknown() == [] and not ds.catalogue_due
    ds.note_running("C")
    assert not ds.catalogue_due
    ds.note_running("D")  # a restart the list did not name
    assert ds.catalogue_due and ds.end_unknown() == ["C"]


def test_a_keyframe_that_is_no_image_costs_only_itself(tagged: Path, tmp_path: Path) -> None:
    """Bytes that are no JPEG arrive for one keyframe: stored as received, their SIFT
    fails and is counted, and the dataset's files are still written for the rest."""
    port = free_port()
    vehicle = Vehicle("uav4", tagged, port)
    out = tmp_path / "dataset"
    proc = ground(out, port, "--sift")
    n = len(vehicle.rows)
    try:
        wait_connected(vehicle)
        for seq in range(n):
            vehicle.publish(seq, b"garbage, not a JPEG" if seq == 1 else None)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
        vehicle.close()
    assert proc.returncode == 0, stderr
    assert "SIFT failed" in stderr and "Traceback" not in stderr, stderr
    summary = json.loads(stdout.strip().splitlines()[-1])
    assert summary["keyframes"] == n and summary["sift_failed"] == 1, summary
    ds = out / "uav4"
    assert (ds / "cameras.txt").read_text().splitlines()[-1].split()[1] == "OPENCV"
    assert len((ds / "geo.txt").read_text().splitlines()) == n  # header + n - 1 geotagged
    assert len(list((ds / "features").glob("*.txt"))) == n - 1


def test_hostile_metadata_costs_only_itself(tagged: Path, tmp_path: Path) -> None:
    """Keyframe metadata no daemon sends (a sequence number or count past any flight,
    a camera quaternion that is no quaternion) is refused or left out, and the
    dataset's files are still written for the rest."""
    from keyframed.ground import VehicleDataset

    ds = VehicleDataset(tmp_path, "uav8", None)
    jpegs = sorted(tagged.glob("*.jpg"))[:4]
    bad_q: list[Any] = ["not a quaternion", [1.0, 2.0], [float("nan"), 0.0, 0.0, 1.0]]
    for seq, (jpeg, q) in enumerate(zip(jpegs, [*bad_q, [1.0, 0.0, 0.0, 0.0]], strict=True)):
        assert ds.add({"sequence": seq, "file": jpeg.name, "cam_q": q}, jpeg.read_bytes())
    with pytest.raises(ValueError, match="not believed"):  # would make missing() endless
        ds.add({"sequence": 10**12, "file": "x.jpg"}, jpegs[0].read_bytes())
    # A number too large for a float where a position goes: no position, no crash.
    assert ds.add(
        {"sequence": 4, "file": "big.jpg", "lat": 10**400, "lon": 7.0, "alt": 10**400},
        jpegs[0].read_bytes(),
    )
    assert ds.progress().startswith("uav8: 5 keyframes")
    # Names another keyframe holds, or that are no JPEG's (a .tmp is thrown away on
    # resume, the index is the dataset's own): each image kept under a name of its
    # own, none overwritten.
    for seq, name in (
        (5, jpegs[1].name),
        (6, "x.jpg.tmp"),
        (7, "keyframes.jsonl"),
        (8, "seq000009.jpg"),
        (9, ""),
    ):
        assert ds.add({"sequence": seq, "file": name}, jpegs[seq % 4].read_bytes())
    names = {m["file"] for m in ds.meta.values()}
    assert len(names) == 10 and all(n.endswith(".jpg") for n in names), names
    assert (ds.images / jpegs[1].name).read_bytes() == jpegs[1].read_bytes()
    for m in ds.meta.values():
        assert (ds.images / m["file"]).read_bytes() == jpegs[m["sequence"] % 4].read_bytes()
    summary = ds.finish()
    assert summary["keyframes"] == 10 and summary["missing"] == [], summary
    assert summary["pairs"] >= 3 and (ds.dir / "geo.txt").read_text().count("\n") == 11
    # Resumed, the names are known: a new keyframe takes none of them.
    again = VehicleDataset(tmp_path, "uav8", None)
    assert len(again.meta) == 10
    assert again.add({"sequence": 10, "file": jpegs[2].name}, jpegs[2].read_bytes())
    assert (again.images / jpegs[2].name).read_bytes() == jpegs[2].read_bytes()
    assert again.meta[("", 10)]["file"] == "seq000010.jpg"


def test_sift_features_land_where_colmap_puts_them(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A blob centred on OpenCV's pixel (60, 50) is COLMAP's (60.5, 50.5): the feature
    file has it there (OpenCV's SIFT alone finds it 0.25 px off, its first octave's
    upscaling), with the descriptors as COLMAP's extractor normalises them by default
    (L1-root: the square root of the L1-normalised histogram, times 512)."""
    import cv2
    import numpy as np
    from keyframed.ground import sift_to_colmap

    yy, xx = np.mgrid[0:100, 0:120].astype(np.float64)
    blob = 40.0 + 180.0 * np.exp(-((xx - 60.0) ** 2 + (yy - 50.0) ** 2) / (2 * 4.0**2))
    image = tmp_path / "blob.png"
    cv2.imwrite(str(image), blob.round().astype(np.uint8))
    out = tmp_path / "blob.txt"
    n = sift_to_colmap(str(image), str(out))
    lines = out.read_text().splitlines()
    assert lines[0] == f"{n} 128" and n >= 1 and len(lines) == n + 1
    rows = [[float(v) for v in line.split()] for line in lines[1:]]
    x, y, *_ = min(rows, key=lambda r: math.hypot(r[0] - 60.5, r[1] - 50.5))
    assert (x, y) == pytest.approx((60.5, 50.5), abs=0.06)

    # An OpenCV without precise upscaling (before 4.8: cv2.error for the keyword):
    # its 0.25 px is taken out instead.
    real = cv2.SIFT

    class OldSift:
        @staticmethod
        def create(**kwargs: Any) -> Any:
            if "enable_precise_upscale" in kwargs:
                raise cv2.error("unknown keyword")
            return real.create(**kwargs)

    monkeypatch.setattr(cv2, "SIFT", OldSift)
    sift_to_colmap(str(image), str(tmp_path / "old.txt"))
    monkeypatch.undo()
    old = [
        [float(v) for v in ln.split()[:2]]
        for ln in (tmp_path / "old.txt").read_text().splitlines()[1:]
    ]
    ox, oy = min(old, key=lambda r: math.hypot(r[0] - 60.5, r[1] - 50.5))
    assert (ox, oy) == pytest.approx((60.5, 50.5), abs=0.06)

    # The descriptors: OpenCV's, L1-root normalised (not L2 as OpenCV leaves them).
    img = cv2.imread(str(image), cv2.IMREAD_GRAYSCALE)
    sift = cv2.SIFT.create(nfeatures=4000, enable_precise_upscale=True)
    _, desc = sift.detectAndCompute(img, None)  # type: ignore[call-overload]
    root = np.sqrt(desc / desc.sum(axis=1, keepdims=True))
    expected = np.clip(np.round(root * 512.0), 0, 255)
    written = np.array([r[4:] for r in rows])
    assert written.shape == expected.shape
    assert np.abs(written - expected).max() <= 1  # float rounding at a .5


def test_the_sift_worker_leaves_ctrl_c_to_the_station() -> None:
    """Ctrl-C reaches the whole process group; a SIFT worker that died of it would
    break the pool for every keyframe after it and the station's close."""
    from concurrent.futures import ProcessPoolExecutor

    from keyframed.ground import _sift_worker_init

    with ProcessPoolExecutor(1, initializer=_sift_worker_init) as pool:
        assert pool.submit(signal.getsignal, signal.SIGINT).result() == signal.SIG_IGN


def test_a_station_that_hears_no_vehicle_says_so(tmp_path: Path) -> None:
    """Nobody on the link (a vehicle in peer mode on a port of its own, a wrong
    address): not a clean exit with an empty dataset, but a line saying what to check
    and status 4."""
    r = subprocess.run(
        [sys.executable, "-m", "keyframed.ground", "--out", str(tmp_path / "ds"), "--quiet"]
        + ["--listen", f"tcp/127.0.0.1:{free_port()}", "--duration", "1.5"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 4, (r.returncode, r.stderr)
    assert "heard no vehicle" in r.stderr and "endpoints" in r.stderr, r.stderr
    assert r.stdout.strip() == ""


def test_bad_command_lines(tmp_path: Path) -> None:
    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "keyframed.ground", *args],
            capture_output=True,
            text=True,
            timeout=30,
        )

    r = run("--out", str(tmp_path), "--zenoh-config", str(tmp_path / "nope.json5"))
    assert r.returncode == 2 and "no such file" in r.stderr
    for not_a_file in (str(tmp_path), "/dev/null"):
        r = run("--out", str(tmp_path), "--zenoh-config", not_a_file)
        assert r.returncode == 2 and f"{not_a_file}: not a file" in r.stderr, r.stderr
    # the daemon's rule for zenoh.vehicle; '*' and '?' would be Zenoh wildcards
    for name in ("a/b", "..", "a*b", "uav?x", "a b", "x" * 65):
        r = run("--out", str(tmp_path), "--vehicle", name)
        assert r.returncode == 2 and "bad vehicle" in r.stderr, (name, r.stderr)
        assert "Traceback" not in r.stderr
    for flag, value in (("--duration", "nan"), ("--duration", "-5"), ("--until-idle", "-1")):
        r = run("--out", str(tmp_path), flag, value)
        assert r.returncode == 2 and f"{flag} must be" in r.stderr, (flag, value, r.stderr)
    r = run("--out", str(tmp_path), "--earlier-flights", "-1")
    assert r.returncode == 2 and "--earlier-flights" in r.stderr
    bad = tmp_path / "bad.json5"
    bad.write_text("{ mode: 12 ")
    r = run("--out", str(tmp_path / "d"), "--zenoh-config", str(bad))
    assert r.returncode == 1 and "Zenoh" in r.stderr
    assert "Traceback" not in r.stderr
    # One line, where in the file and what is wrong; not where in Zenoh's Rust sources.
    assert r.stderr.startswith("keyframed-ground: cannot open the Zenoh session: line 1, ")
    assert len(r.stderr.splitlines()) == 1 and ".rs:" not in r.stderr, r.stderr
    r = run("--out", "/proc/keyframed-cannot-write")
    assert r.returncode == 1 and "cannot create" in r.stderr
    # A folder that exists but takes no file: said at start, not when a vehicle is heard
    r = run("--out", "/proc/self", "--duration", "1")
    assert r.returncode == 1 and "cannot write in /proc/self" in r.stderr, r.stderr
    # Endpoints that cannot exist: said at once, not retried by Zenoh for ever.
    for flag, endpoint in (
        ("--connect", "tcp/127.0.0.1:74470"),
        ("--connect", "tcp/127.0.0.1"),
        ("--listen", "udp/0.0.0.0:port"),
    ):
        r = run("--out", str(tmp_path / "e"), flag, endpoint, "--duration", "1")
        assert r.returncode == 2 and f"{flag} {endpoint}: not HOST:PORT" in r.stderr, r.stderr
    for flag, endpoint in (("--connect", "garbage"), ("--listen", "tcp/"), ("--connect", "/x")):
        r = run("--out", str(tmp_path / "e"), flag, endpoint, "--duration", "1")
        assert r.returncode == 2, (endpoint, r.returncode, r.stderr)
        assert r.stderr == f"keyframed-ground: {flag} {endpoint}: not PROTOCOL/ADDRESS " + (
            "(e.g. tcp/192.168.1.10:7447)\n"
        )


@pytest.mark.parametrize(
    "lens",
    ["focal_length_mm: 4.4\n", "sensor_width_mm: 6.17\nsensor_height_mm: 3.47\n"],
    ids=["focal-mm", "sensor-size"],
)
def test_a_calibration_survives_the_tags_into_colmap_and_odm(
    kf_bin: Path, tmp_path: Path, lens: str
) -> None:
    """calibrateCamera's output (pixels only, fx != fy, k1 k2 p1 p2 k3) plus the lens's
    focal length in mm, or the sensor's datasheet size (whose height says square
    pixels, which fx != fy does not): what the ground station makes of the keyframes'
    tags alone is that calibration, in COLMAP's and OpenSfM's conventions."""
    from keyframed.ground import colmap_camera, odm_cameras, read_tags

    fl = flight("nadir", width=320, height=180, seconds=3.0)
    calib = {"fx": 231.5, "fy": 232.25, "cx": 161.25, "cy": 88.75}
    k = [-0.12, 0.034, 0.0011, -0.0007, 0.0052]
    matrix = [calib["fx"], 0, calib["cx"], 0, calib["fy"], calib["cy"], 0, 0, 1]
    (tmp_path / "calib.yaml").write_text(
        "%YAML:1.0\n---\nimage_width: 320\nimage_height: 180\n"
        "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
        f"   data: {matrix}\n"
        "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n"
        f"   data: {k}\n"
        f'{lens}make: "Acme"\nmodel: "Acme Cam 2"\n'
    )
    out = tmp_path / "tagged"
    stderr = select(kf_bin, fl / "video.avi", out, "--calibration", str(tmp_path / "calib.yaml"))
    assert "sensor_width_mm" not in stderr  # the focal length in mm was enough
    jpeg = next(out.glob("*.jpg")).read_bytes()
    tags = read_tags(jpeg)
    line = colmap_camera(tags)
    assert line is not None
    model, w, h, *params = line.split()[1:]
    assert (model, w, h) == ("FULL_OPENCV", "320", "180")
    expected = [calib["fx"], calib["fy"], calib["cx"] + 0.5, calib["cy"] + 0.5, k[0], k[1]]
    expected += [k[2], k[3], k[4], 0.0, 0.0, 0.0]
    assert [float(v) for v in params] == pytest.approx(expected, rel=1e-5, abs=1e-7)

    odm = odm_cameras(tags)
    assert odm is not None
    # ODM's id keeps the make in the model ("v2 acme acme cam 2 ..." in OpenDroneMap,
    # the file's keys go without "v2 "); f35 = round(fx * 36 / 320) = 26. Again as
    # ODM's --camera-lens auto names it: the XMP ModelType.
    ratio = str(26 / 36)[:6]
    assert list(odm) == [
        f"acme acme cam 2 320 180 brown {ratio}",
        f"acme acme cam 2 320 180 perspective {ratio}",
    ]
    brown = odm[f"acme acme cam 2 320 180 brown {ratio}"]
    assert odm[f"acme acme cam 2 320 180 perspective {ratio}"] == brown
    assert brown["focal_x"] * 320 == pytest.approx(calib["fx"], rel=1e-5)
    assert brown["focal_y"] * 320 == pytest.approx(calib["fy"], rel=1e-5)
    assert 160 + brown["c_x"] * 320 == pytest.approx(calib["cx"] + 0.5, rel=1e-5)
    assert 90 + brown["c_y"] * 320 == pytest.approx(calib["cy"] + 0.5, rel=1e-5)
    got = [brown[n] for n in ("k1", "k2", "p1", "p2", "k3")]
    assert got == pytest.approx(k, rel=1e-6)


def test_a_fisheye_calibration_reaches_colmap_and_odm_as_fisheye(
    kf_bin: Path, tmp_path: Path
) -> None:
    """cv::fisheye::calibrate's output as OpenCV's calibration sample writes it
    (fisheye_model: 1, k1..k4): the keyframes say fisheye, COLMAP gets OPENCV_FISHEYE
    and ODM fisheye_opencv with the same numbers, and a point COLMAP's camera projects
    lands where OpenCV's fisheye model puts it; the ground footprint inverts the lens."""
    import cv2
    import numpy as np
    import pycolmap
    from keyframed.ground import (
        _area,
        _fisheye_ray,
        colmap_camera,
        footprint,
        odm_cameras,
        read_tags,
    )

    fl = flight("nadir", width=320, height=180, seconds=2.0)
    fx, fy, cx, cy = 101.5, 102.25, 158.75, 91.25
    d = [0.043, -0.0121, 0.0034, -0.00052]
    matrix = [fx, 0, cx, 0, fy, cy, 0, 0, 1]
    (tmp_path / "fisheye.yaml").write_text(
        "%YAML:1.0\n---\nimage_width: 320\nimage_height: 180\nfisheye_model: 1\n"
        "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
        f"   data: {matrix}\n"
        "distortion_coefficients: !!opencv-matrix\n   rows: 4\n   cols: 1\n   dt: d\n"
        f"   data: {d}\n"
        'focal_length_mm: 1.8\nmake: "Acme"\nmodel: "Fish 1"\n'
    )
    out = tmp_path / "tagged"
    select(kf_bin, fl / "video.avi", out, "--calibration", str(tmp_path / "fisheye.yaml"))
    tags = read_tags(next(out.glob("*.jpg")).read_bytes())
    assert tags.lens == "fisheye" and tags.calibrated
    line = colmap_camera(tags)
    assert line is not None
    model, w, h, *params = line.split()[1:]
    assert (model, w, h) == ("OPENCV_FISHEYE", "320", "180")
    expected = [fx, fy, cx + 0.5, cy + 0.5, *d]
    assert [float(v) for v in params] == pytest.approx(expected, rel=1e-5, abs=1e-8)

    # COLMAP's camera and OpenCV's fisheye model agree on where points land, out to
    # 75 degrees off the axis (COLMAP counts from the corner, OpenCV from the first
    # pixel's centre: half a pixel apart).
    cam = pycolmap.Camera(model=model, width=320, height=180, params=[float(v) for v in params])
    rng = np.random.default_rng(7)
    theta = rng.uniform(0.0, np.radians(75), 50)
    phi = rng.uniform(-np.pi, np.pi, 50)
    rays = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], 1)
    colmap_px = cam.img_from_cam(rays)
    k = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    opencv_px, _ = cv2.fisheye.projectPoints(
        rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), k, np.array(d)
    )
    assert np.abs(colmap_px - (opencv_px.reshape(-1, 2) + 0.5)).max() < 1e-3

    # The footprint's ray for a pixel is the direction OpenCV projects there.
    for ray, px in zip(rays[:10], opencv_px.reshape(-1, 2)[:10], strict=True):
        ray_back = _fisheye_ray((px[0] - cx) / fx, (px[1] - cy) / fy, d)
        assert ray_back is not None
        back = np.array(ray_back) / np.linalg.norm(ray_back)
        assert np.degrees(np.arccos(np.clip(back @ ray, -1, 1))) < 0.01, (back, ray)

    # A nadir footprint 30 m up has the area of the image's outline on the ground,
    # traced densely through OpenCV's model. This lens sees past the horizon at its
    # corners (104 degrees off the axis): no footprint. At twice the focal length
    # (corners 52 degrees off) the footprint's area is the outline's.
    nadir = [np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5)]
    assert footprint((0.0, 0.0), 30.0, nadir, tags) is None
    assert tags.focal_mm is not None
    long_lens = dataclasses.replace(tags, focal_mm=2 * tags.focal_mm)
    k2 = np.array([[2 * fx, 0, cx], [0, 2 * fy, cy], [0, 0, 1]])
    edge = np.linspace(0.0, 1.0, 200, endpoint=False)
    zero = 0 * edge
    outline = np.concatenate(
        [
            np.stack([edge * 320, zero], 1),
            np.stack([320 + zero, edge * 180], 1),
            np.stack([320 - edge * 320, 180 + zero], 1),
            np.stack([zero, 180 - edge * 180], 1),
        ]
    )
    rays = cv2.fisheye.undistortPoints((outline - 0.5).reshape(-1, 1, 2), k2, np.array(d))
    truth = 30.0**2 * _area([(float(x), float(y)) for x, y in rays.reshape(-1, 2)])
    poly = footprint((0.0, 0.0), 30.0, nadir, long_lens)
    assert poly is not None
    assert _area(poly) == pytest.approx(truth, rel=0.03)
    # Its four corners alone would take in much more ground than the lens shows.
    corners = [poly[0], poly[8], poly[16], poly[24]]
    assert _area(corners) > 1.2 * truth

    odm = odm_cameras(tags)
    assert odm is not None
    ratio = str(round(fx * 36 / 320) / 36)[:6]
    # One key: ODM's --camera-lens auto calls the XMP ModelType "fisheye" fisheye_opencv.
    assert list(odm) == [f"acme fish 1 320 180 fisheye_opencv {ratio}"]
    cam_json = odm[f"acme fish 1 320 180 fisheye_opencv {ratio}"]
    assert cam_json["projection_type"] == "fisheye_opencv"
    assert cam_json["focal_x"] * 320 == pytest.approx(fx, rel=1e-5)
    assert 160 + cam_json["c_x"] * 320 == pytest.approx(cx + 0.5, rel=1e-5)
    assert [cam_json[f"k{i}"] for i in range(1, 5)] == pytest.approx(d, rel=1e-6)
    assert "p1" not in cam_json


def test_a_calibration_of_another_aspect_ratio_tags_no_intrinsics(
    kf_bin: Path, tmp_path: Path
) -> None:
    """A 4:3 calibration on 16:9 frames is another sensor mode (a crop): scaled to the
    frames it would give an anisotropic camera that COLMAP and ODM take for a
    calibration. The warning says so, and the keyframes carry the camera's identity
    and lens focal length but no intrinsics, so the station makes no camera of them."""
    from keyframed.ground import colmap_camera, odm_cameras, read_tags

    fl = flight("nadir", width=320, height=180, seconds=3.0)
    matrix = [250.0, 0, 159.5, 0, 250.0, 119.5, 0, 0, 1]
    (tmp_path / "calib43.yaml").write_text(
        "%YAML:1.0\n---\nimage_width: 320\nimage_height: 240\n"
        "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
        f"   data: {matrix}\n"
        "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n"
        "   data: [-0.1, 0.02, 0.0, 0.0, 0.0]\n"
        'sensor_width_mm: 6.4\nfocal_length_mm: 5.0\nmake: "Acme"\nmodel: "Four Three"\n'
    )
    out = tmp_path / "tagged"
    stderr = select(kf_bin, fl / "video.avi", out, "--calibration", str(tmp_path / "calib43.yaml"))
    assert "crops rather than scales" in stderr and "without them" in stderr, stderr
    tags = read_tags(next(out.glob("*.jpg")).read_bytes())
    assert (tags.make, tags.model) == ("Acme", "Four Three")
    assert tags.focal_mm == pytest.approx(5.0)
    assert colmap_camera(tags) is None and odm_cameras(tags) is None


def test_an_uncalibrated_camera_gets_no_cameras_file(kf_bin: Path, tmp_path: Path) -> None:
    """A camera known by its lens and sensor only (no calibration): the keyframes have
    EXIF's focal length and focal plane resolution but no XMP calibration. The ground
    station makes no camera of them (a centred principal point and zero distortion
    would be taken for a calibration), removes the one an earlier run left, and its
    summary says there is none; the other files are written as ever."""
    from keyframed.ground import VehicleDataset, colmap_camera, odm_cameras, read_tags

    fl = flight("nadir", width=320, height=180, seconds=3.0)
    (tmp_path / "camera.toml").write_text(
        '[camera]\nmake = "Acme"\nmodel = "Acme Cam 2"\nwidth = 320\nheight = 180\n'
        "sensor_width_mm = 6.4\nfocal_length_mm = 4.4\n"
    )
    out = tmp_path / "tagged"
    select(kf_bin, fl / "video.avi", out, "--calibration", str(tmp_path / "camera.toml"))
    jpegs = sorted(out.glob("*.jpg"))
    assert len(jpegs) >= 2
    tags = read_tags(jpegs[0].read_bytes())
    assert tags.focal_mm == pytest.approx(4.4) and tags.pixels_per_mm == pytest.approx(50.0)
    assert tags.focal_35mm and not tags.calibrated
    assert colmap_camera(tags) is None and odm_cameras(tags) is None

    ds = VehicleDataset(tmp_path / "dataset", "uav5", None)
    (ds.dir / "cameras.txt").write_text("1 OPENCV 320 180 220 220 160 90 0 0 0 0\n")
    (ds.dir / "cameras.json").write_text("{}\n")
    for seq, jpeg in enumerate(jpegs):
        ds.add({"sequence": seq, "file": jpeg.name}, jpeg.read_bytes())
    summary = ds.finish()
    assert summary["calibrated"] is False and summary["camera"] is None
    assert summary["odm_camera"] is None
    assert not (ds.dir / "cameras.txt").exists() and not (ds.dir / "cameras.json").exists()
    assert (ds.dir / "pairs.txt").read_text() and (ds.dir / "geo.txt").exists()


def test_geo_txt_rows_never_make_up_angles() -> None:
    """geo.txt's columns are positional and OpenDroneMap takes a row's yaw pitch roll
    over the image's, and its accuracies, none if the row has none: the angles are the
    keyframe's (its XMP, else its metadata), never 0 0 0; an image whose accuracies a
    row cannot carry gets none (ODM then reads its own tags); no position, no row."""
    from keyframed.ground import ImageTags, geo_row

    def tags(**kw: Any) -> ImageTags:
        return ImageTags(lat=51.5, lon=-0.25, alt=70.0, **kw)

    acc: dict[str, Any] = {"xy_accuracy": 0.8, "z_accuracy": 1.2}
    xmp: dict[str, Any] = {"attitude": (90.0, 1.5, 0.5)}
    meta = {"yaw": "271.5", "pitch": 12.25, "roll": -3.0}  # a number, or as CSV has it
    lla = "a.jpg -0.250000000 51.500000000 70.000"
    assert geo_row("a.jpg", tags(**acc, **xmp), meta) == (
        f"{lla} 90.000000 1.500000 0.500000 0.800 1.200"
    )
    assert geo_row("a.jpg", tags(**acc), meta) == (
        f"{lla} 271.500000 12.250000 -3.000000 0.800 1.200"
    )
    assert geo_row("a.jpg", tags(**xmp), {}) == f"{lla} 90.000000 1.500000 0.500000"
    assert geo_row("a.jpg", tags(), {"yaw": 10.0, "pitch": None, "roll": 0.0}) == lla
    assert geo_row("a.jpg", tags(**acc), {"yaw": float("nan"), "pitch": 0, "roll": 0}) is None
    assert geo_row("a.jpg", tags(xy_accuracy=0.8, **xmp), meta) is None
    assert geo_row("a.jpg", ImageTags(**acc, **xmp), meta) is None
    # a position without an altitude: no row, rather than one at 0 m
    assert geo_row("a.jpg", ImageTags(lat=51.5, lon=-0.25), meta) is None


def test_a_gap_the_vehicle_cannot_fill_is_reported(tagged: Path, tmp_path: Path) -> None:
    """One keyframe the vehicle no longer has, one it answers with garbage: both are
    reported missing, the rest is stored and the dataset's files are written."""
    port = free_port()
    vehicle = Vehicle("uav2", tagged, port)
    vehicle.unavailable = {1}
    vehicle.garbled = {3}
    out = tmp_path / "dataset"
    proc = ground(out, port)
    try:
        wait_connected(vehicle)
        for seq in (0, 2, 4):
            vehicle.publish(seq)
        # a publisher whose vehicle name would put its folder outside --out
        row = vehicle.rows[0]
        vehicle.session.put(
            "keyframed/../keyframe",
            (tagged / row["file"]).read_bytes(),
            attachment=json.dumps(vehicle.meta(row)).encode(),
            # put's default is to drop under congestion: the keyframes just sent may
            # still fill the queue on a loaded machine
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
        vehicle.close()
    assert proc.returncode == 3, stderr
    assert "still missing" in stderr and "bad reply" in stderr
    assert "Traceback" not in stderr
    summary = json.loads(stdout.strip().splitlines()[-1])
    assert summary["keyframes"] == 3 and summary["missing"] == [1, 3]
    assert (1, 1) in vehicle.queries and (3, 3) in vehicle.queries
    for name in ("cameras.txt", "pairs.txt", "geo.txt", "keyframes.jsonl"):
        assert (out / "uav2" / name).stat().st_size > 0, name
    assert "bad vehicle name '..'" in stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dataset"]
    assert sorted(p.name for p in out.iterdir()) == ["uav2"]


def test_resume_after_a_kill_mid_write(tagged: Path, tmp_path: Path) -> None:
    """The station was killed while writing: a half-written image (``.tmp``) and a
    half-written metadata line. Started again on the same folder, it throws both away,
    keeps what was complete, and fetches the rest in one range query."""
    port = free_port()
    vehicle = Vehicle("uav3", tagged, port)
    n = len(vehicle.rows)
    ds = tmp_path / "dataset" / "uav3"
    (ds / "images").mkdir(parents=True)
    first, second = vehicle.rows[0], vehicle.rows[1]
    (ds / "images" / first["file"]).write_bytes((tagged / first["file"]).read_bytes())
    (ds / "images" / (second["file"] + ".tmp")).write_bytes(b"\xff\xd8 half a jpeg")
    line = json.dumps(vehicle.meta(first), sort_keys=True) + "\n"
    (ds / "keyframes.jsonl").write_text(line + line[: len(line) // 2])
    proc = ground(tmp_path / "dataset", port)
    try:
        wait_connected(vehicle)
        vehicle.status()  # "I have written n"
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
        vehicle.close()
    assert proc.returncode == 0, stderr
    summary = json.loads(stdout.strip().splitlines()[-1])
    assert summary["keyframes"] == n and summary["fetched_by_query"] == n - 1
    assert vehicle.queries == [(1, n - 1)]
    assert not list(ds.rglob("*.tmp"))
    for row in vehicle.rows:
        assert (ds / "images" / row["file"]).read_bytes() == (tagged / row["file"]).read_bytes()
    seqs = [json.loads(x)["sequence"] for x in (ds / "keyframes.jsonl").read_text().splitlines()]
    assert seqs == list(range(n))


def test_a_line_cut_short_by_a_kill_costs_no_later_keyframe(tagged: Path, tmp_path: Path) -> None:
    """Killed mid-line, resumed, killed again before the index was rewritten: the line
    the second run appended does not run on from the cut one, so a third run still
    knows every keyframe stored."""
    from keyframed.ground import VehicleDataset

    rows_ = rows(tagged)
    jpeg = [(tagged / r["file"]).read_bytes() for r in rows_[:3]]
    meta = [{"sequence": i, "file": r["file"]} for i, r in enumerate(rows_[:3])]
    ds = VehicleDataset(tmp_path / "dataset", "uav6", None)
    ds.add(meta[0], jpeg[0])
    ds.add(meta[1], jpeg[1])
    index = ds.dir / "keyframes.jsonl"
    text = index.read_text()
    index.write_text(text[: len(text) - 10])  # the kill: keyframe 1's line cut short
    again = VehicleDataset(tmp_path / "dataset", "uav6", None)  # resumed
    assert sorted(again.meta) == [("", 0)]
    assert index.read_text().endswith("\n")
    again.add(meta[2], jpeg[2])  # appended; killed again before finish()
    third = VehicleDataset(tmp_path / "dataset", "uav6", None)
    assert sorted(third.meta) == [("", 0), ("", 2)]  # 1 is fetched again by query


def test_resume_computes_the_sift_features_an_earlier_run_did_not(
    tagged: Path, tmp_path: Path
) -> None:
    """The station was killed with SIFT jobs pending: of three stored images one has
    its features, one none (its job never ran), one half-written ones (``.tmp``).
    Started again with --sift, it computes the two missing, keeps the one there, and
    computes those of the keyframes it fetches: every image ends with its features."""
    port = free_port()
    vehicle = Vehicle("uav6", tagged, port)
    n = len(vehicle.rows)
    assert n >= 4
    ds = tmp_path / "dataset" / "uav6"
    (ds / "images").mkdir(parents=True)
    (ds / "features").mkdir()
    stored = vehicle.rows[:3]
    for row in stored:
        (ds / "images" / row["file"]).write_bytes((tagged / row["file"]).read_bytes())
    index = "".join(json.dumps(vehicle.meta(row), sort_keys=True) + "\n" for row in stored)
    (ds / "keyframes.jsonl").write_text(index)
    kept = ds / "features" / (stored[0]["file"] + ".txt")
    kept.write_text("0 128\n")  # complete, if empty: not computed again
    (ds / "features" / (stored[2]["file"] + ".txt.tmp")).write_text("4000 128\n1.5 2")
    proc = ground(tmp_path / "dataset", port, "--sift")
    try:
        wait_connected(vehicle)
        vehicle.status()  # "I have written n"
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
        vehicle.close()
    assert proc.returncode == 0, stderr
    summary = json.loads(stdout.strip().splitlines()[-1])
    assert summary["keyframes"] == n and summary["fetched_by_query"] == n - 3
    assert summary["sift_failed"] == 0, stderr
    assert vehicle.queries == [(3, n - 1)]
    assert not list(ds.rglob("*.tmp"))
    assert kept.read_text() == "0 128\n"
    for row in vehicle.rows[1:]:
        lines = (ds / "features" / (row["file"] + ".txt")).read_text().splitlines()
        count, dim = (int(v) for v in lines[0].split())
        assert dim == 128 and count == len(lines) - 1 and count > 50, row["file"]


def test_a_stop_writes_the_dataset_without_waiting_for_a_sift_backlog(
    tagged: Path, tmp_path: Path
) -> None:
    """A station resumed with --sift on a folder of 1080p images without features (a
    backlog of a second or so each) and stopped at once by two SIGINTs: it writes the
    dataset's files, leaves the features it has not got to (the summary says how many)
    and exits, rather than computing them all first."""
    import cv2

    n = 24
    ds = tmp_path / "dataset" / "uav9"
    (ds / "images").mkdir(parents=True)
    rng = np.random.default_rng(3)
    texture = cv2.GaussianBlur(rng.integers(0, 256, (1080, 1920), dtype=np.uint8), (0, 0), 1.5)
    ok, jpeg = cv2.imencode(".jpg", texture)
    assert ok
    # Sequences 1..n of the flight stored earlier; the vehicle then sends 0 live.
    with open(ds / "keyframes.jsonl", "w") as f:
        for seq in range(1, n + 1):
            (ds / "images" / f"old{seq:06d}.jpg").write_bytes(jpeg.tobytes())
            meta = {"flight": "F1", "sequence": seq, "file": f"old{seq:06d}.jpg"}
            f.write(json.dumps(meta) + "\n")
    port = free_port()
    vehicle = Vehicle("uav9", tagged, port)
    vehicle.flight = "F1"
    live = vehicle.rows[0]["file"]
    proc = ground(tmp_path / "dataset", port, "--sift")
    try:
        wait_connected(vehicle)
        vehicle.publish(0)
        wait_until(lambda: (ds / "images" / live).exists())
        proc.send_signal(signal.SIGINT)
        time.sleep(0.5)
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
        vehicle.close()
    assert proc.returncode == 0, stderr
    summary = json.loads(stdout.strip().splitlines()[-1])
    assert summary["keyframes"] == n + 1 and summary["sift_failed"] == 0, summary
    features = list((ds / "features").glob("*.txt"))
    assert summary["sift_left"] > n // 2, (summary, len(features))
    assert len(features) + summary["sift_left"] >= n + 1, (summary, len(features))
    assert f"{summary['sift_left']} keyframes left without SIFT features" in stderr
    geo = (ds / "geo.txt").read_text().splitlines()
    assert geo[0] == "EPSG:4326" and geo[1].split()[0] == live, geo
    index = [json.loads(line) for line in (ds / "keyframes.jsonl").read_text().splitlines()]
    assert [m["sequence"] for m in index] == list(range(n + 1))


def test_a_station_killed_leaves_dataset_files_for_the_images_it_holds(
    tagged: Path, tmp_path: Path
) -> None:
    """The dataset's files are written while the station runs, not only when it stops:
    killed (SIGKILL, no shutdown), it leaves keyframes.jsonl, cameras.txt,
    cameras.json, pairs.txt and geo.txt that parse and name exactly the images it
    holds, as they were after each batch of keyframes."""
    port = free_port()
    vehicle = Vehicle("uav7", tagged, port)
    out = tmp_path / "dataset"
    ds = out / "uav7"
    proc = subprocess.Popen(
        [sys.executable, "-m", "keyframed.ground", "--out", str(out), "--quiet"]
        + ["--connect", f"tcp/127.0.0.1:{port}"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    n = len(vehicle.rows)
    files = [r["file"] for r in vehicle.rows]

    def geo_names() -> list[str]:
        try:
            return [line.split()[0] for line in (ds / "geo.txt").read_text().splitlines()[1:]]
        except FileNotFoundError:
            return []

    try:
        wait_connected(vehicle)
        for seq in range(n // 2):
            vehicle.publish(seq)
        wait_until(lambda: geo_names() == files[: n // 2])
        for seq in range(n // 2, n):
            vehicle.publish(seq)
        wait_until(lambda: geo_names() == files)
        proc.send_signal(signal.SIGKILL)
        proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
        vehicle.close()
    assert proc.returncode == -signal.SIGKILL
    held = sorted(p.name for p in (ds / "images").glob("*.jpg"))
    assert held == sorted(files) and not list(ds.rglob("*.tmp"))

    metas = [json.loads(line) for line in (ds / "keyframes.jsonl").read_text().splitlines()]
    assert [(m["sequence"], m["file"]) for m in metas] == list(enumerate(files))

    fl = flight("nadir", width=480, height=270, seconds=8.0)
    intr = json.loads((fl / "intrinsics.json").read_text())
    cam = (ds / "cameras.txt").read_text().splitlines()[-1].split()
    assert cam[:4] == ["1", "OPENCV", "480", "270"]
    assert float(cam[4]) == pytest.approx(intr["fx"], rel=1e-4)
    odm = json.loads((ds / "cameras.json").read_text())
    assert odm and all(c["projection_type"] == "brown" for c in odm.values())
    assert all(c["focal_x"] * 480 == pytest.approx(float(cam[4]), rel=1e-9) for c in odm.values())

    pairs = [tuple(line.split()) for line in (ds / "pairs.txt").read_text().splitlines()]
    assert {name for pair in pairs for name in pair} == set(files)
    assert all((a, b) in pairs for a, b in zip(files, files[1:], strict=False))

    geo = (ds / "geo.txt").read_text().splitlines()
    assert geo[0] == "EPSG:4326" and len(geo) == n + 1
    for line, row in zip(geo[1:], vehicle.rows, strict=True):
        lon, lat = (float(v) for v in line.split()[1:3])
        assert (lat, lon) == pytest.approx((float(row["lat"]), float(row["lon"])), abs=1e-7)


def test_a_long_gap_on_a_slow_link_is_asked_for_in_chunks_once_each(
    tagged: Path, tmp_path: Path
) -> None:
    """A vehicle slow to answer (0.7 s a keyframe, as large keyframes over a slow
    radio link) and a gap of 11 keyframes: the station asks for at most 8 in one
    query, sends the next query only when the last has been answered, and asks for
    none again while its answer is on the way, though the first chunk takes longer
    than the 5 s a query used to be given. Each answer is stored as it arrives, not
    when the chunk ends: a station stopped mid-chunk keeps what crossed the link."""
    folder = tmp_path / "long"
    folder.mkdir()
    base = rows(tagged)
    long_rows = []
    for seq in range(12):
        row = dict(base[seq % len(base)], sequence=str(seq), index=str(seq))
        row["file"] = f"{seq:06d}.jpg"
        shutil.copyfile(tagged / base[seq % len(base)]["file"], folder / row["file"])
        long_rows.append(row)
    with open(folder / "keyframes.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(base[0]))
        writer.writeheader()
        writer.writerows(long_rows)
    port = free_port()
    vehicle = Vehicle("uav8", folder, port)
    vehicle.reply_delay = 0.7
    out = tmp_path / "dataset"
    proc = ground(out, port)
    images = out / "uav8" / "images"
    second_on_disk: list[float] = []  # when the chunk's second keyframe was stored

    def watch() -> None:
        while proc.poll() is None and not second_on_disk:
            if images.is_dir() and len(list(images.glob("*.jpg"))) >= 3:  # 0, 1 and 2
                second_on_disk.append(time.monotonic())
            time.sleep(0.05)

    watcher = threading.Thread(target=watch, daemon=True)
    try:
        wait_connected(vehicle)
        vehicle.publish(0)
        vehicle.status()  # "I have written 12"
        watcher.start()
        stdout, stderr = proc.communicate(timeout=90)
    finally:
        if proc.poll() is None:
            proc.kill()
        vehicle.close()
    watcher.join()
    assert proc.returncode == 0, stderr
    summary = json.loads(stdout.strip().splitlines()[-1])
    assert summary["keyframes"] == 12 and summary["fetched_by_query"] == 11, summary
    assert vehicle.queries == [(1, 8), (9, 11)], vehicle.queries
    assert summary["gap_queries"] == 2 and summary["duplicates_ignored"] == 0, summary
    (a_start, a_end), (b_start, _) = vehicle.spans
    assert a_end - a_start > 5.0 and b_start >= a_end, vehicle.spans
    # Sent 1.4 s into a 5.6 s chunk: on disk seconds before the chunk's last reply
    assert second_on_disk and second_on_disk[0] < a_end - 2.5, (second_on_disk, vehicle.spans)
    for row in long_rows:
        assert (out / "uav8" / "images" / row["file"]).read_bytes() == (
            folder / row["file"]
        ).read_bytes()


@pytest.mark.parametrize("name", ["nadir", "orbit"])
def test_pairs_follow_the_ground_truth_overlap_graph(name: str) -> None:
    """pairs.txt's graph against the generator's exact overlap between frames: on the
    nadir survey (a lawn-mower with turns, a hover and yaw) and the oblique orbit,
    every two keyframes that share a quarter of their view are paired, and frames that
    share nothing are not (beyond the sequential neighbours)."""
    from keyframed import ground, synth

    fl = synth.load_flight(flight(name, width=480, height=270))
    intr = fl.intrinsics
    frames = list(range(0, len(fl), 12))
    ned_from_enu = np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, -1]])
    tags, quats, heights = [], [], []
    for i in frames:
        lat, lon, _ = fl.geodetic[i]
        tags.append(
            ground.ImageTags(
                width=fl.width,
                height=fl.height,
                lat=float(lat),
                lon=float(lon),
                focal_mm=intr["focal_length_mm"],
                pixels_per_mm=fl.width / intr["sensor_width_mm"],
                principal_mm=(
                    (intr["cx"] + 0.5) * intr["sensor_width_mm"] / fl.width,
                    (intr["cy"] + 0.5) * intr["sensor_width_mm"] / fl.width,
                ),
            )
        )
        r_ned_cam = ned_from_enu @ fl.rotations[i]
        quats.append([float(v) for v in synth._rotmat_to_quat(r_ned_cam[None])[0]])
        heights.append(float(fl.positions[i][2]))  # the ground is the plane z = 0
    names = [f"{i:06d}.jpg" for i in frames]
    pairs = set(ground.image_pairs(names, tags, alt_above_ground=heights, cam_q=quats))
    sequential = {(names[k], names[k + d]) for d in (1, 2, 3) for k in range(len(names) - d)}
    missed, extra, overlapping = [], [], 0
    for a in range(len(frames)):
        for b in range(a + 1, len(frames)):
            i, j = frames[a], frames[b]
            truth = max(fl.overlap(i, j), fl.overlap(j, i))
            pair = (names[a], names[b])
            if truth >= 0.25 and pair not in pairs:
                missed.append((pair, round(truth, 2)))
            if truth == 0.0 and pair in pairs and pair not in sequential:
                extra.append(pair)
            overlapping += truth > 0.0
    assert not missed, missed
    assert not extra, extra
    total = len(frames) * (len(frames) - 1) // 2
    print(f"{len(pairs)} pairs of {total}; {overlapping} overlap in truth")
    assert len(pairs) < total, "not exhaustive"
    # sideways neighbours (the next survey line) are in it, not only the sequence
    assert len(pairs - sequential) > 0


def test_one_vehicle_of_two_with_live_progress(tagged: Path, tmp_path: Path) -> None:
    """--vehicle NAME takes that vehicle's keyframes only, though another publishes on
    the same network; without --quiet a progress line (count, rate, last position)
    goes to stderr."""
    ports = free_port(), free_port()
    vehicles = [Vehicle("uav1", tagged, ports[0]), Vehicle("uav2", tagged, ports[1])]
    out = tmp_path / "dataset"
    # the console script as installed (the other tests run the module)
    script = Path(sysconfig.get_path("scripts")) / "keyframed-ground"
    assert script.is_file(), f"{script}: the package's console script is not installed"
    proc = subprocess.Popen(
        [str(script), "--out", str(out), "--vehicle", "uav2"]
        + [arg for p in ports for arg in ("--connect", f"tcp/127.0.0.1:{p}")]
        + ["--until-idle", "2.5"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        wait_connected(vehicles[1])
        n = len(vehicles[1].rows)
        for seq in range(n):
            for v in vehicles:
                v.publish(seq)
            time.sleep(0.4)  # long enough for a progress line or two
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
        for v in vehicles:
            v.close()
    assert proc.returncode == 0, stderr
    assert sorted(p.name for p in out.iterdir()) == ["uav2"]
    assert len(list((out / "uav2" / "images").glob("*.jpg"))) == n
    summaries = [json.loads(line) for line in stdout.strip().splitlines()]
    assert [s["vehicle"] for s in summaries] == ["uav2"] and summaries[0]["keyframes"] == n
    # No final status was heard: said, though nothing is known to be missing.
    assert summaries[0]["last_flight_ended"] is False and summaries[0]["missing"] == []
    assert "has not ended as far as the station knows" in stderr, stderr
    # (each update starts with a carriage return; text mode reads it as a newline)
    lines = [seg.strip() for seg in stderr.replace("\r", "\n").splitlines() if seg.strip()]
    assert any(line.startswith(f"uav2: {n} keyframes") for line in lines), lines
    assert any(" at 51." in line and "/min" in line for line in lines), lines
    assert not any("uav1" in line for line in lines), lines
