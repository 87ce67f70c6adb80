"""keyframed-ground: the ground station. Receives keyframes over Zenoh and writes a
dataset per vehicle that COLMAP and OpenDroneMap take as it is.

    keyframed-ground --out DATASET [--vehicle NAME] [--connect tcp/HOST:PORT] ...

Subscribes to ``keyframed/<vehicle>/keyframe`` (``*``: every vehicle). Each keyframe
arrives as the tagged JPEG with its metadata (JSON) in the attachment; a gap in the
sequence numbers, or a vehicle whose status says it has written more than we hold,
is filled by query, ``keyframed/<vehicle>/keyframes/*?range=A..B``, which the vehicle
answers from its on-disk store: at most 8 keyframes a query, one query at a time per
vehicle, each waited for up to 5 s plus 5 s a keyframe; what it did not bring is asked
for again 5 s later. Nothing is written twice; every file is written to a temporary
name and renamed.

When it first hears of a vehicle, when a flight it had not listed appears (its daemon
restarted) and once more at the end, the station asks it which flights it holds
(``keyframed/<vehicle>/flights``: each run of the daemon is one flight) and fetches
the keyframes of any earlier flight it lacks, e.g. one flown while the station was
down before the daemon restarted, or the last keyframes of a flight whose end the
link lost; those older than ``--earlier-flights`` seconds (default an hour) are left
alone and listed in the summary. A flight that was followed by another without the
station learning how many keyframes it ended with is listed in the summary's
``flights_end_unknown`` and makes the exit status 3, as missing keyframes do. The
latest flight's end not heard (``last_flight_ended``: false) is said on stderr only:
the station may be stopped while the vehicle flies. A station that heard no vehicle at
all (the link, most likely) says so and exits with status 4.

The files below other than the images are rewritten while the station runs (at most
every 5 s when keyframes arrived) and at the end, so a station that is killed leaves a
dataset whose files describe the images it held at their last writing.

``DATASET/<vehicle>/`` holds:

- ``images/NNNNNN.jpg``: the keyframes, byte for byte as the vehicle wrote them
  (EXIF GPS and XMP Pix4D tags: ODM, OpenSfM and Pix4D read these directly);
- ``keyframes.jsonl``: the metadata of each, by flight (the time it started) and
  sequence number;
- ``cameras.txt``: the camera in COLMAP's text format (OPENCV or FULL_OPENCV, or
  OPENCV_FISHEYE for a fisheye lens, from the calibration in the JPEG's XMP tags);
  absent when the keyframes carry no calibration
  (the summary says ``"calibrated": false``): EXIF's nominal focal length is no
  calibration, and a camera with zero distortion made of it would be held as one;
- ``cameras.json``: the same camera for OpenDroneMap (``--camera-lens brown --cameras
  cameras.json``, or ``fisheye_opencv`` for a fisheye), keyed by the camera id
  OpenDroneMap gives these images, with that lens or with the one their XMP ModelType
  says (ODM's ``auto``); absent with ``cameras.txt``;
- ``pairs.txt``: image pairs for ``colmap matches_importer --match_type pairs``, the
  edges of the overlap graph: each keyframe with its neighbours along the flight and
  with those whose ground footprints (projected from position, camera attitude and
  intrinsics) overlap its own (the next survey line), so matching need not be
  exhaustive;
- ``geo.txt``: positions for OpenDroneMap (EPSG:4326; lon lat alt, the camera's yaw
  pitch roll, accuracies);
- with ``--sift``: ``features/<image>.txt``, SIFT keypoints and descriptors in the
  text format ``colmap feature_importer`` reads, computed by a low-priority worker
  (on a resumed dataset, also for the images stored before that have none yet).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import multiprocessing
import os
import re
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

KEY_PREFIX = "keyframed"
FINAL_STATES = ("done", "stopped", "failed", "interrupted", "capture_failed")
GAP_GRACE_S = 1.0  # how long a gap may last before it is filled by query
MAX_FLIGHT_KEYFRAMES = 1_000_000  # a flight list claiming more is not believed
# A gap is asked for in chunks of at most this many keyframes, one chunk at a time per
# vehicle: on a slow link a chunk of 500 KB keyframes takes a while, and a query still
# being answered is not sent again.
GAP_CHUNK = 8
# A chunk's query waits this long, plus this long per keyframe (500 KB keyframes need
# a link of 800 kbit/s or more to arrive in time), before its answer counts as ended.
GAP_QUERY_S = 5.0
GAP_QUERY_PER_KEYFRAME_S = 5.0
# What a query that ended did not bring is asked for again after this long.
GAP_RETRY_S = 5.0
# While the station runs, the dataset's files are rewritten at most this often, and at
# least ten times as long apart as writing them took (pairs.txt grows faster than the
# number of keyframes).
FILES_EVERY_S = 5.0


def keyframe_key(vehicle: str) -> str:
    return f"{KEY_PREFIX}/{vehicle}/keyframe"


def status_key(vehicle: str) -> str:
    return f"{KEY_PREFIX}/{vehicle}/status"


def store_key(vehicle: str, seq: int | str) -> str:
    return f"{KEY_PREFIX}/{vehicle}/keyframes/{seq}"


def flights_key(vehicle: str) -> str:
    return f"{KEY_PREFIX}/{vehicle}/flights"


def range_selector(vehicle: str, first: int, last: int, flight: str = "") -> str:
    """The query for keyframes ``first`` to ``last`` (both included) in one go; of an
    earlier ``flight`` of the vehicle (a run of its daemon before a restart) if given."""
    selector = f"{store_key(vehicle, '*')}?range={first}..{last}"
    return f"{selector};flight={flight}" if flight else selector


def runs(seqs: list[int]) -> list[tuple[int, int]]:
    """Sorted sequence numbers as (first, last) runs of consecutive numbers."""
    out: list[tuple[int, int]] = []
    for s in sorted(seqs):
        if out and s == out[-1][1] + 1:
            out[-1] = (out[-1][0], s)
        else:
            out.append((s, s))
    return out


# ----------------------------------------------------------------------------- tags


@dataclass
class ImageTags:
    """What the dataset files need from one keyframe's EXIF/XMP tags."""

    width: int = 0
    height: int = 0
    lat: float | None = None
    lon: float | None = None
    alt: float | None = None
    xy_accuracy: float | None = None
    z_accuracy: float | None = None
    focal_mm: float | None = None
    pixels_per_mm: float | None = None  # from FocalPlaneXResolution
    pixels_per_mm_y: float | None = None  # from FocalPlaneYResolution (fy may differ)
    principal_mm: tuple[float, float] | None = None
    # Pix4D R1,R2,R3,T1,T2 (perspective), or OpenCV's fisheye k1..k4
    distortion: list[float] = field(default_factory=list)
    lens: str = "perspective"  # XMP ModelType: "perspective" or "fisheye"
    # XMP PrincipalPoint with the lens's focal length and distortion (Pix4D's
    # Perspective* or keyframed's Fisheye*) all given: the camera was calibrated (the
    # daemon writes them only then), so focal_mm is the calibrated one, not EXIF's
    # nominal lens
    calibrated: bool = False
    attitude: tuple[float, float, float] | None = None  # XMP Yaw, Pitch, Roll (Pix4D)
    make: str = ""
    model: str = ""
    focal_35mm: float | None = None  # FocalLengthIn35mmFilm


def _xmp_value(xmp: str, name: str, prefix: str = "Camera") -> str | None:
    m = re.search(rf'{prefix}:{name}="([^"]*)"', xmp) or re.search(
        rf"<{prefix}:{name}>([^<]*)</{prefix}:{name}>", xmp
    )
    return m.group(1) if m else None


def read_tags(jpeg: bytes) -> ImageTags:
    """EXIF (Pillow) and the Pix4D XMP fields of a keyframe JPEG; nothing (width 0)
    for bytes that are no image."""
    from PIL import UnidentifiedImageError

    try:
        return _read_tags(jpeg)
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError):
        return ImageTags()
    except Exception:  # tags of unexpected types (a GPS field that is no triple)
        return ImageTags()


def _read_tags(jpeg: bytes) -> ImageTags:
    from PIL import Image

    tags = ImageTags()
    with Image.open(io.BytesIO(jpeg)) as im:
        tags.width, tags.height = im.size
        exif = im.getexif()
        tags.make = str(exif.get(0x010F, "")).strip("\x00 ")
        tags.model = str(exif.get(0x0110, "")).strip("\x00 ")
        sub = exif.get_ifd(0x8769)
        if sub.get(0xA405):
            tags.focal_35mm = float(sub[0xA405])
        if 0x920A in sub:
            tags.focal_mm = float(sub[0x920A])
        if 0xA20E in sub and 0xA210 in sub:
            per_unit = float(sub[0xA20E])
            unit_mm = {2: 25.4, 3: 10.0, 4: 1.0}.get(int(sub[0xA210]))
            if unit_mm and per_unit > 0:
                tags.pixels_per_mm = per_unit / unit_mm
                per_unit_y = float(sub.get(0xA20F, 0) or 0)
                if per_unit_y > 0:
                    tags.pixels_per_mm_y = per_unit_y / unit_mm
        gps = exif.get_ifd(0x8825)
        if 2 in gps and 4 in gps:

            def deg(v: Any) -> float:
                return float(v[0]) + float(v[1]) / 60.0 + float(v[2]) / 3600.0

            tags.lat = deg(gps[2]) * (-1.0 if gps.get(1) == "S" else 1.0)
            tags.lon = deg(gps[4]) * (-1.0 if gps.get(3) == "W" else 1.0)
            if 6 in gps:
                tags.alt = float(gps[6]) * (-1.0 if gps.get(5) in (1, b"\x01") else 1.0)
    start = jpeg.find(b"<x:xmpmeta")
    end = jpeg.find(b"</x:xmpmeta>")
    if start >= 0 and end > start:
        xmp = jpeg[start:end].decode("utf-8", "replace")
        for name, attr in (("GPSXYAccuracy", "xy_accuracy"), ("GPSZAccuracy", "z_accuracy")):
            v = _xmp_value(xmp, name)
            if v:
                setattr(tags, attr, float(v))
        pp = _xmp_value(xmp, "PrincipalPoint")
        if pp:
            x, y = (float(s) for s in pp.split(","))
            tags.principal_mm = (x, y)
        if (_xmp_value(xmp, "ModelType") or "").lower() == "fisheye":
            tags.lens = "fisheye"
            fl = _xmp_value(xmp, "FisheyeFocalLength", "Keyframed")
            dist = _xmp_value(xmp, "FisheyeDistortion", "Keyframed")
        else:
            fl = _xmp_value(xmp, "PerspectiveFocalLength")
            dist = _xmp_value(xmp, "PerspectiveDistortion")
        if fl:
            tags.focal_mm = float(fl)
        if dist:
            tags.distortion = [float(s) for s in dist.split(",")]
        tags.calibrated = bool(pp and fl and dist)
        yaw, pitch, roll = (_xmp_value(xmp, name) for name in ("Yaw", "Pitch", "Roll"))
        if yaw and pitch and roll:
            tags.attitude = (float(yaw), float(pitch), float(roll))
    return tags


@dataclass
class Intrinsics:
    """A calibrated camera in pixels, with the principal point measured from the image
    corner (COLMAP's and OpenSfM's convention: the first pixel's centre is at 0.5)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    k: tuple[float, float, float]  # radial k1 k2 k3
    p: tuple[float, float]  # tangential p1 p2 (OpenCV's)
    # OpenCV's fisheye model (cv::fisheye) k1..k4 instead of k and p when a fisheye
    fisheye: tuple[float, float, float, float] | None = None


def intrinsics(tags: ImageTags) -> Intrinsics | None:
    """The calibration the tags give in pixels, or None when they do not: the XMP
    calibration (focal length and principal point in mm, distortion) and the focal
    plane resolution (pixels per mm) to turn it into pixels. EXIF's focal length alone
    is no calibration: the principal point at the centre and zero distortion would be
    made up, and a tool told to hold the camera fixed would hold them."""
    if not (tags.calibrated and tags.focal_mm and tags.pixels_per_mm and tags.width):
        return None
    per_mm_y = tags.pixels_per_mm_y or tags.pixels_per_mm
    if tags.principal_mm:
        cx, cy = tags.principal_mm[0] * tags.pixels_per_mm, tags.principal_mm[1] * per_mm_y
    else:
        cx, cy = tags.width / 2.0, tags.height / 2.0
    r = (tags.distortion + [0.0] * 5)[:5]  # Pix4D R1 R2 R3 T1 T2 = k1 k2 k3 p1 p2
    if tags.lens == "fisheye":
        k = (tags.distortion + [0.0] * 4)[:4]
        fx, fy = tags.focal_mm * tags.pixels_per_mm, tags.focal_mm * per_mm_y
        no_k, no_p = (0.0, 0.0, 0.0), (0.0, 0.0)
        return Intrinsics(
            tags.width, tags.height, fx, fy, cx, cy, no_k, no_p, (k[0], k[1], k[2], k[3])
        )
    return Intrinsics(
        tags.width,
        tags.height,
        tags.focal_mm * tags.pixels_per_mm,
        tags.focal_mm * per_mm_y,
        cx,
        cy,
        (r[0], r[1], r[2]),
        (r[3], r[4]),
    )


def colmap_camera(tags: ImageTags) -> str | None:
    """One COLMAP camera line, or None when the tags do not give the intrinsics in
    pixels: OPENCV (fx fy cx cy k1 k2 p1 p2), or FULL_OPENCV (k3 to k6 after p2) when
    the calibration has a k3, or OPENCV_FISHEYE (fx fy cx cy k1 k2 k3 k4, OpenCV's
    fisheye model) for a fisheye lens. COLMAP puts the image's top-left corner at (0, 0), the
    first pixel's centre at (0.5, 0.5): the principal point is the tags' distance from
    that corner (OpenCV's cx + 0.5), and the SIFT export counts the same way."""
    cam = intrinsics(tags)
    if cam is None:
        return None
    model, params = "OPENCV", [cam.fx, cam.fy, cam.cx, cam.cy, cam.k[0], cam.k[1], *cam.p]
    if cam.fisheye is not None:
        model, params = "OPENCV_FISHEYE", [cam.fx, cam.fy, cam.cx, cam.cy, *cam.fisheye]
    elif cam.k[2] != 0.0:
        model, params = "FULL_OPENCV", params + [cam.k[2], 0.0, 0.0, 0.0]
    # 12 significant digits: the same intrinsics as cameras.json's to 1e-11, not to the
    # rounding of a shorter form
    return f"1 {model} {cam.width} {cam.height} " + " ".join(f"{p:.12g}" for p in params)


def odm_camera_id(tags: ImageTags, projection: str = "brown") -> str | None:
    """The camera id OpenDroneMap gives images with these tags (its Photo.camera_id())
    as its ``--cameras`` file is keyed, without the "v2 " it puts in front: make and
    model as they are (empty when absent), the image's size in pixels, the projection
    (its --camera-lens) and the focal ratio FocalLengthIn35mmFilm / 36 as its first 6
    characters, lowercase. None without the 35 mm focal length, which ODM would
    replace by another estimate."""
    if not tags.focal_35mm:
        return None
    ratio = str(tags.focal_35mm / 36.0)[:6]
    parts = [tags.make.strip(), tags.model.strip(), str(tags.width), str(tags.height)]
    return " ".join(parts + [projection, ratio]).lower()


def odm_cameras(tags: ImageTags) -> dict[str, Any] | None:
    """OpenDroneMap's cameras.json (``--camera-lens brown --cameras cameras.json``):
    the calibration as OpenSfM's Brown-Conrady model (``fisheye_opencv``, OpenCV's
    fisheye model, for a fisheye lens: ``--camera-lens fisheye_opencv``), normalised by
    the image's longer side with the principal point as an offset from the centre; the
    distortion coefficients are OpenCV's (the same polynomials). Keyed by the camera id
    ODM looks the images' camera up by, with that projection, and again with the one
    ODM's default ``--camera-lens auto`` puts in the id: the XMP ModelType
    ("perspective"; a "fisheye" is ODM's "fisheye_opencv"). ODM ignores a key no image
    has. (Plain OpenSfM's ids, "v2 " and a make repeated in the model dropped, are not
    keys here: ODM never looks them up.) None without the calibration or the tags the
    id is made of."""
    cam = intrinsics(tags)
    if cam is None or odm_camera_id(tags) is None:
        return None
    size = float(max(cam.width, cam.height))
    model: dict[str, Any] = {
        "projection_type": "brown" if cam.fisheye is None else "fisheye_opencv",
        "width": cam.width,
        "height": cam.height,
        "focal_x": cam.fx / size,
        "focal_y": cam.fy / size,
        "c_x": (cam.cx - cam.width / 2.0) / size,
        "c_y": (cam.cy - cam.height / 2.0) / size,
    }
    if cam.fisheye is None:
        model |= {"k1": cam.k[0], "k2": cam.k[1], "p1": cam.p[0], "p2": cam.p[1], "k3": cam.k[2]}
    else:
        model |= {f"k{i + 1}": v for i, v in enumerate(cam.fisheye)}
    out: dict[str, Any] = {}
    auto = "fisheye_opencv" if tags.lens == "fisheye" else tags.lens
    for projection in (model["projection_type"], auto):
        camera_id = odm_camera_id(tags, projection)
        if camera_id is not None and camera_id not in out:
            out[camera_id] = dict(model)
    return out


# ------------------------------------------------------------------------ pairs


def _local_xy(lat: float, lon: float, lat0: float, lon0: float) -> tuple[float, float]:
    r = 6378137.0
    return (
        math.radians(lon - lon0) * r * math.cos(math.radians(lat0)),
        math.radians(lat - lat0) * r,
    )


def _rotate(q: list[float], v: tuple[float, float, float]) -> tuple[float, float, float]:
    """v rotated by the unit quaternion q = [w, x, y, z]."""
    w, x, y, z = q
    vx, vy, vz = v
    # t = 2 q_vec x v; v' = v + w t + q_vec x t
    tx, ty, tz = 2 * (y * vz - z * vy), 2 * (z * vx - x * vz), 2 * (x * vy - y * vx)
    return (
        vx + w * tx + (y * tz - z * ty),
        vy + w * ty + (z * tx - x * tz),
        vz + w * tz + (x * ty - y * tx),
    )


def footprint(
    north_east: tuple[float, float], height: float, cam_q: list[float], tags: ImageTags
) -> list[tuple[float, float]] | None:
    """The image's outline on flat ground ``height`` metres below the camera, as a
    polygon of (north, east) metres: each corner's ray (OpenCV camera axes, turned to
    NED by ``cam_q``) meets the ground. A fisheye's straight image edges are curved
    lines on the ground: 8 points along each edge, through the lens. None when a
    corner looks at or above the horizon (no bounded footprint) or the intrinsics are
    unknown."""
    if not (tags.focal_mm and tags.pixels_per_mm and tags.width and tags.height) or height <= 0:
        return None
    per_mm_y = tags.pixels_per_mm_y or tags.pixels_per_mm
    fx, fy = tags.focal_mm * tags.pixels_per_mm, tags.focal_mm * per_mm_y
    cx, cy = tags.width / 2, tags.height / 2
    if tags.principal_mm:
        cx, cy = tags.principal_mm[0] * tags.pixels_per_mm, tags.principal_mm[1] * per_mm_y
    w, h = tags.width, tags.height
    corners = [(0.0, 0.0), (w, 0.0), (w, h), (0.0, h)]
    outline = corners
    if tags.lens == "fisheye":
        steps = 8
        outline = [
            (a[0] + (b[0] - a[0]) * t / steps, a[1] + (b[1] - a[1]) * t / steps)
            for a, b in zip(corners, corners[1:] + corners[:1], strict=True)
            for t in range(steps)
        ]
    out = []
    for u, v in outline:
        ray: tuple[float, float, float] | None = ((u - cx) / fx, (v - cy) / fy, 1.0)
        if tags.lens == "fisheye":
            ray = _fisheye_ray((u - cx) / fx, (v - cy) / fy, tags.distortion)
        if ray is None:
            return None
        dn, de, dd = _rotate(cam_q, ray)
        if dd < 0.05 * math.hypot(dn, de, dd):  # within ~3 degrees of the horizon
            return None
        out.append((north_east[0] + dn * height / dd, north_east[1] + de * height / dd))
    return out


def _fisheye_ray(x: float, y: float, k: list[float]) -> tuple[float, float, float] | None:
    """The direction (OpenCV camera axes) of a fisheye pixel at (x, y) focal lengths
    from the principal point: OpenCV's model puts it at distorted angle
    theta_d = theta (1 + k1 theta^2 + ... + k4 theta^8) from the axis; theta by Newton.
    None where the polynomial has no such angle."""
    theta_d = math.hypot(x, y)
    if theta_d == 0.0:
        return (0.0, 0.0, 1.0)
    c = (k + [0.0] * 4)[:4]
    theta = theta_d
    for _ in range(20):
        t2 = theta * theta
        poly = 1 + t2 * (c[0] + t2 * (c[1] + t2 * (c[2] + t2 * c[3])))
        slope = 1 + t2 * (3 * c[0] + t2 * (5 * c[1] + t2 * (7 * c[2] + t2 * 9 * c[3])))
        if slope <= 1e-9:
            return None
        step = (theta * poly - theta_d) / slope
        theta -= step
        if abs(step) < 1e-12:
            break
    t2 = theta * theta
    if abs(theta * (1 + t2 * (c[0] + t2 * (c[1] + t2 * (c[2] + t2 * c[3])))) - theta_d) > 1e-9:
        return None
    s = math.sin(theta) / theta_d
    return (x * s, y * s, math.cos(theta))


def _hull(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """Convex hull (Andrew's monotone chain), counter-clockwise."""
    pts = sorted(set(points))
    if len(pts) < 3:
        return pts

    def cross(o: tuple[float, float], a: tuple[float, float], b: tuple[float, float]) -> float:
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: list[tuple[float, float]] = []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    upper: list[tuple[float, float]] = []
    for p in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    return lower[:-1] + upper[:-1]


def _area(poly: list[tuple[float, float]]) -> float:
    return 0.5 * abs(
        sum(a[0] * b[1] - b[0] * a[1] for a, b in zip(poly, poly[1:] + poly[:1], strict=True))
    )


def _clip(
    subject: list[tuple[float, float]], clip: list[tuple[float, float]]
) -> list[tuple[float, float]]:
    """Sutherland-Hodgman: subject polygon clipped by a convex polygon."""

    def side(a: tuple[float, float], b: tuple[float, float], p: tuple[float, float]) -> float:
        return (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0])

    orient = 1.0 if side(clip[0], clip[1], clip[2]) > 0 else -1.0
    out = subject
    for a, b in zip(clip, clip[1:] + clip[:1], strict=True):
        if not out:
            break
        pts, out = out, []
        for p, q in zip(pts, pts[1:] + pts[:1], strict=True):
            sp, sq = orient * side(a, b, p), orient * side(a, b, q)
            if sp >= 0:
                out.append(p)
            if (sp >= 0) != (sq >= 0):
                t = sp / (sp - sq)
                out.append((p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1])))
    return out


def footprint_overlap(a: list[tuple[float, float]], b: list[tuple[float, float]]) -> float:
    """Shared ground area over the smaller footprint's area (0..1). ``a`` is clipped by
    the convex hull of ``b`` (a fisheye's footprint is concave: the hull errs towards
    more overlap, so towards one pair more, not one missed)."""
    inter = _clip(a, _hull(b))
    small = min(_area(a), _area(b))
    return _area(inter) / small if len(inter) >= 3 and small > 0 else 0.0


def image_pairs(
    names: list[str],
    tags: list[ImageTags],
    sequential: int = 3,
    min_overlap: float = 0.1,
    alt_above_ground: Sequence[float | None] | None = None,
    cam_q: Sequence[list[float] | None] | None = None,
) -> list[tuple[str, str]]:
    """Pairs to match, from the overlap graph: each image with the next ``sequential``
    ones (the daemon kept them at the target overlap), and any two whose ground
    footprints overlap by ``min_overlap`` or more of the smaller one. A footprint is
    the image outline projected from the keyframe's position, camera attitude,
    intrinsics and height above the take-off point onto flat ground; a lawn-mower
    survey's neighbouring lines overlap sideways, which sequence alone misses. Without
    an attitude the footprint is taken as nadir (north up)."""
    pairs: set[tuple[int, int]] = set()
    n = len(names)
    for i in range(n):
        for j in range(i + 1, min(n, i + 1 + sequential)):
            pairs.add((i, j))
    known = [i for i in range(n) if tags[i].lat is not None and tags[i].lon is not None]
    if not known:
        return [(names[i], names[j]) for i, j in sorted(pairs)]
    lat0, lon0 = tags[known[0]].lat or 0.0, tags[known[0]].lon or 0.0
    nadir = [math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)]  # image top north, looking down
    polys: dict[int, list[tuple[float, float]]] = {}
    for i in known:
        h = alt_above_ground[i] if alt_above_ground is not None else None
        if h is None:
            continue
        east, north = _local_xy(tags[i].lat or 0.0, tags[i].lon or 0.0, lat0, lon0)
        q = (cam_q[i] if cam_q is not None else None) or nadir
        poly = footprint((north, east), h, q, tags[i])
        if poly is not None:
            polys[i] = poly
    # Footprints whose bounding boxes do not meet share no ground: a sweep along the
    # north axis compares each footprint only with those it may overlap. Every pair
    # took 26 s for 2000 keyframes, and the station rewrites pairs.txt while it runs.
    box = {
        i: (min(n for n, _ in p), max(n for n, _ in p), min(e for _, e in p), max(e for _, e in p))
        for i, p in polys.items()
    }
    order = sorted(polys, key=lambda i: box[i][0])
    prune = min_overlap > 0.0  # with 0, footprints that share nothing are paired too
    for a_i, i in enumerate(order):
        for j in order[a_i + 1 :]:
            if prune and box[j][0] > box[i][1]:
                break
            if prune and (box[j][2] > box[i][3] or box[i][2] > box[j][3]):
                continue
            a, b = min(i, j), max(i, j)
            if footprint_overlap(polys[a], polys[b]) >= min_overlap:
                pairs.add((a, b))
    return [(names[i], names[j]) for i, j in sorted(pairs)]


# ------------------------------------------------------------------------- SIFT


def _sift_worker_init() -> None:
    # Ctrl-C reaches the whole process group: the station stops its worker itself,
    # after the features it has been given (a worker killed mid-job would break the
    # pool and every keyframe after it).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        os.nice(10)
    except OSError:
        pass


def sift_to_colmap(jpeg_path: str, out_path: str, max_features: int = 4000) -> int:
    """SIFT keypoints + descriptors of one image in COLMAP's feature import format:
    ``N 128`` then per feature ``x y scale orientation d1 ... d128`` (0-255), x and y
    as COLMAP counts them (OpenCV's + 0.5: the first pixel's centre is 0.5, 0.5), the
    descriptors normalised as COLMAP's own extractor does by default (L1-root), so that
    they mix with features COLMAP computes."""
    import cv2
    import numpy as np

    img = cv2.imread(jpeg_path, cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise ValueError(f"cannot read {jpeg_path}")
    # OpenCV's SIFT doubles the image for its first octave; before 4.8 (or without
    # precise upscaling) that resize puts every keypoint 0.25 px right of and below
    # where it is: taken out here, so that the features land where COLMAP's would.
    try:
        sift = cv2.SIFT.create(nfeatures=max_features, enable_precise_upscale=True)
        shift = 0.5
    except (TypeError, cv2.error):  # OpenCV 4.5-4.7 say cv2.error for the keyword
        sift = cv2.SIFT.create(nfeatures=max_features)
        shift = 0.25
    # No mask: OpenCV takes None, which its stubs leave out.
    kps, desc = sift.detectAndCompute(img, None)  # type: ignore[call-overload]
    lines = [f"{len(kps)} 128"]
    if desc is not None:
        # As COLMAP stores SIFT by default: L1-normalised, square-rooted (RootSIFT),
        # times 512, clipped to 0..255.
        d = np.sqrt(desc / np.maximum(np.abs(desc).sum(axis=1, keepdims=True), 1e-12))
        d = np.clip(np.round(d * 512.0), 0, 255).astype(np.uint8)
        for kp, row in zip(kps, d, strict=True):
            lines.append(
                f"{kp.pt[0] + shift:.3f} {kp.pt[1] + shift:.3f} {kp.size / 2.0:.3f} "
                f"{math.radians(kp.angle):.5f} " + " ".join(str(int(v)) for v in row)
            )
    _write_atomic(Path(out_path), ("\n".join(lines) + "\n").encode())
    return len(kps)


# ---------------------------------------------------------------------- dataset


def _write_atomic(path: Path, data: bytes) -> None:
    """path holds data whole, or what it held before: written beside it, synced and
    renamed over it. What a failed write left of the copy (a full disk) is removed."""
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def _append_line(path: Path, line: str) -> bool:
    """Appends line whole or not at all: a disk that takes part of it is cut back to
    the line before, so that the next line does not run into it. False when not
    appended: the keyframe is stored all the same, and the index, rewritten whole
    (refresh_files), gets its line then."""
    data = (line + "\n").encode()
    try:
        with open(path, "ab", buffering=0) as f:
            start = f.tell()
            try:
                if f.write(data) == len(data):
                    return True
            except OSError:
                pass
            f.truncate(start)
    except OSError:
        pass
    return False


class _Unwritable(OSError):
    """A vehicle's dataset folder cannot be made (said once, when first heard)."""


Key = tuple[str, int]  # (flight, sequence): each run of the daemon counts from 0 again


class VehicleDataset:
    """One vehicle's dataset folder; thread-safe. A vehicle whose daemon restarted
    (its sequence numbers start again at 0) sends keyframes of several flights: they
    are told apart by the flight id in their metadata. The first flight's images keep
    their names, a later flight's are named FLIGHT_NNNNNN.jpg, so none is overwritten."""

    def __init__(self, root: Path, vehicle: str, sift: ProcessPoolExecutor | None) -> None:
        self.vehicle = vehicle
        self.dir = root / vehicle
        self.images = self.dir / "images"
        self.images.mkdir(parents=True, exist_ok=True)
        self.lock = threading.Lock()
        self.meta: dict[Key, dict[str, Any]] = {}
        self.names: set[str] = set()  # the images' names, one per keyframe
        self.flights: list[str] = []  # in the order first heard of
        self.duplicates = 0
        self.closed = False  # finish() began: nothing more is stored
        self.fetched = 0
        self.queries = 0  # gap-filling queries sent (one per chunk of a gap)
        self.announced: dict[str, int] = {}  # highest sequence each flight says it wrote
        self.missing_since: dict[Key, float] = {}
        # Missing keyframes a query that ended did not bring, and when to ask again.
        self.retry_at: dict[Key, float] = {}
        self.asking: threading.Event | None = None  # set when the last gap query ended
        self.done = False  # the vehicle said its (latest) flight ended
        self.done_flight = ""
        self.done_at = 0.0
        self.first_time = time.monotonic()
        # The vehicle's list of flights is asked for once it is heard, and again when
        # a flight the last list did not name appears: a daemon that restarted lists
        # the flight before with its final count, which the link may have lost. A
        # daemon of a version without the list does not answer: asked a few times.
        self.catalogue_due = True
        self.catalogue_tries = 0
        self.catalogue_next = 0.0
        self.listed: set[str] = set()  # the flights the last list named
        self.skipped_flights: list[str] = []  # earlier flights too old to fetch
        # The flight heard running last; those it followed that were heard running
        # before it; and those whose final keyframe count is known (a final status, or
        # a list naming them as not running). A followed flight whose count is not
        # known may have lost its last keyframes unseen: the summary says so.
        self.current: str | None = None
        self.superseded: list[str] = []
        self.ended: set[str] = set()
        # The dataset's files (pairs.txt, geo.txt, ...): rewritten when keyframes
        # arrived since, not before files_next; each image's tags read once.
        self.changed = False
        self.files_next = 0.0
        self.tags: dict[str, ImageTags] = {}
        self.sift = sift
        self.sift_jobs: list[Future[int]] = []
        if sift is not None:
            (self.dir / "features").mkdir(exist_ok=True)
        # resume: what an earlier run already holds; a file half-written when it was
        # killed is thrown away (the keyframe is fetched again by query)
        for tmp in self.dir.rglob("*.tmp"):
            tmp.unlink(missing_ok=True)
        index = self.dir / "keyframes.jsonl"
        if index.exists():
            # Bytes a power cut or a hand edit garbled are replaced, not fatal: one bad
            # line must not keep the vehicle's every keyframe out of the dataset.
            text = index.read_bytes().decode("utf-8", errors="replace")
            if text and not text.endswith("\n"):
                # A line cut short by a kill: dropped from the file, not only skipped,
                # so that the next line appended does not run on from it (and be lost
                # to the next resume).
                text = text[: text.rfind("\n") + 1]
                _write_atomic(index, text.encode())
            for line in text.splitlines():
                try:
                    m = json.loads(line)
                    name = m["file"]
                    if not isinstance(name, str) or os.path.basename(name) != name:
                        continue  # not a name this station gave an image
                    if (self.images / name).is_file():
                        flight = os.path.basename(str(m.get("flight") or ""))
                        seq = int(m["sequence"])
                        self._flight(flight)
                        self.meta[(flight, seq)] = dict(m, flight=flight or None)
                        self.names.add(name)
                except (ValueError, KeyError, TypeError):
                    continue  # no JSON object, or not one of ours
            # The flight whose images have plain names stays the one (the index is
            # in flight-id order, which need not be the order they were stored in).
            plain = [f for (f, _), m in self.meta.items() if not m["file"].startswith(f"{f}_")]
            if plain:
                self.flights.remove(plain[0])
                self.flights.insert(0, plain[0])
        if sift is not None:
            # Jobs are submitted only as keyframes arrive: an image an earlier run
            # stored without its features (killed before its worker got to it, or
            # half-way through, the .tmp thrown away above) gets them now.
            for m in self.meta.values():
                if not (self.dir / "features" / (m["file"] + ".txt")).exists():
                    self._queue_sift(m["file"])

    def _queue_sift(self, name: str) -> None:
        """Has the worker write the SIFT features of ``images/<name>``."""
        if self.sift is not None:
            out = str(self.dir / "features" / (name + ".txt"))
            try:
                job = self.sift.submit(sift_to_colmap, str(self.images / name), out)
            except Exception as err:  # a broken pool: the keyframe is stored all the same
                print(f"keyframed-ground: {self.vehicle}: SIFT not queued: {err}", file=sys.stderr)
                return
            self.sift_jobs.append(job)

    def _unused_name(self, name: str, flight: str, seq: int) -> str:
        """``name`` when it is a JPEG's name no other keyframe holds (under the lock);
        else one made from the flight and sequence number. The name comes from the
        sender: one already taken would overwrite another keyframe's image, one that
        is no ``.jpg`` (a ``.tmp``, the index's own) would be thrown away or clash."""
        if name.endswith(".jpg") and not name.startswith(".") and name not in self.names:
            return name
        stem = f"{flight}_seq{seq:06d}" if flight else f"seq{seq:06d}"
        candidate, n = f"{stem}.jpg", 1
        while candidate in self.names:
            n += 1
            candidate = f"{stem}_{n}.jpg"
        return candidate

    def _flight(self, flight: str) -> bool:
        """Notes a flight (under the lock); True for the dataset's first."""
        if flight not in self.flights:
            self.flights.append(flight)
            if flight not in self.listed:
                # A flight the vehicle's list did not name: ask for the list again.
                self.catalogue_due = True
                self.catalogue_tries = 0
                self.catalogue_next = 0.0
        return self.flights[0] == flight

    def note_flight(self, flight: str) -> None:
        with self.lock:
            self._flight(flight)

    def _follow(self, flight: str) -> None:
        """``flight`` is the vehicle's latest (under the lock): the one heard before it,
        if another, has ended. One already followed by another stays behind it."""
        if flight == self.current or flight in self.superseded:
            return
        if self.current is not None:
            self.superseded.append(self.current)
        self.current = flight

    def note_running(self, flight: str) -> None:
        """The vehicle is flying ``flight``: a live keyframe or status said so."""
        with self.lock:
            self._flight(flight)
            self._follow(flight)

    def note_end(self, flight: str) -> None:
        """``flight`` has ended and its final keyframe count is known: its final status
        said so, which may overtake its last keyframes."""
        with self.lock:
            self._flight(flight)
            self.ended.add(flight)
            self._follow(flight)

    def end_unknown(self) -> list[str]:
        """Flights followed by another without their final keyframe count known."""
        with self.lock:
            return [f for f in self.superseded if f not in self.ended]

    def last_flight_end_heard(self) -> bool | None:
        """Whether the latest flight's final status (its keyframe count) was heard; None
        with no flight. Not heard: it still flies, or its end was lost with the link."""
        with self.lock:
            return None if self.current is None else self.current in self.ended

    def note_catalogue(self, flights: list[Any], max_age_s: float) -> None:
        """The vehicle's flights (keyframed/<vehicle>/flights): each one it is running,
        or we know of already, or that ended at most ``max_age_s`` ago is noted with
        its keyframe count, so that what we lack of it is fetched by query."""
        running = None
        with self.lock:
            wanted = []
            entries = []
            for f in flights:
                try:
                    flight = os.path.basename(str(f.get("flight") or ""))
                    n = int(f["keyframes"])
                    age = f.get("age_s")
                    recent = age is not None and float(age) <= max_age_s
                except (AttributeError, KeyError, TypeError, ValueError, OverflowError):
                    continue  # not a flight entry: the others still count
                if flight and 0 <= n <= MAX_FLIGHT_KEYFRAMES:
                    entries.append((f, flight, n, recent))
            # Named here, so hearing of them later is no reason to ask again.
            self.listed = {flight for _, flight, _, _ in entries}
            for f, flight, n, recent in entries:
                if f.get("current"):
                    running = flight
                else:
                    self.ended.add(flight)  # not running: its count is final
                if f.get("current") or flight in self.flights or recent:
                    wanted.append(flight)
                    self.announced[flight] = max(self.announced.get(flight, -1), n - 1)
                elif flight not in self.skipped_flights:
                    self.skipped_flights.append(flight)
            if not self.meta:
                # nothing stored yet, so no name given: the vehicle's order (the time
                # each flight started) decides which flight keeps plain file names
                self.flights = wanted + [f for f in self.flights if f not in wanted]
            else:
                for flight in wanted:
                    self._flight(flight)
        if running is not None:
            self.note_running(running)

    def progress(self) -> str:
        """The progress line's part for this vehicle: keyframes, their rate since the
        first, and where the newest one with a position was taken: the latest flight's
        (flight ids are UTC times) highest sequence, not the last to arrive (a gap
        filled later, or an earlier flight fetched, holds older keyframes)."""
        n = self.count()
        rate = n / max(1e-3, time.monotonic() - self.first_time)
        last = ""
        with self.lock:
            placed = []
            for (flight, seq), m in self.meta.items():
                lat, lon = _float_or_none(m.get("lat")), _float_or_none(m.get("lon"))
                if lat is not None and lon is not None:
                    placed.append((flight, seq, lat, lon))
            if placed:
                *_, lat, lon = max(placed)
                last = f" at {lat:.6f},{lon:.6f}"
        return f"{self.vehicle}: {n} keyframes, {rate * 60:.0f}/min{last}"

    def add(self, meta: dict[str, Any], jpeg: bytes, fetched: bool = False) -> bool:
        """Stores one keyframe; False when it was already there."""
        seq = int(meta["sequence"])
        if not 0 <= seq < MAX_FLIGHT_KEYFRAMES:
            raise ValueError(f"sequence number {seq} is not believed")
        flight = os.path.basename(str(meta.get("flight") or ""))
        name = meta.get("file") or f"{int(meta.get('frame_index', seq)):06d}.jpg"
        name = os.path.basename(str(name))
        with self.lock:
            if self.closed:
                return False  # the dataset's files are written: it would be left out of them
            if (flight, seq) in self.meta:
                self.duplicates += 1
                return False
            if not self._flight(flight):
                name = f"{flight}_{name}"
            name = self._unused_name(name, flight, seq)
            # The flight as it is keyed: a resume reads the same one back.
            meta = dict(meta, file=name, flight=flight or None)
            # A write that fails (a full disk) leaves the name free for the keyframe
            # when a gap query brings it again.
            _write_atomic(self.images / name, jpeg)
            self.names.add(name)
            self.meta[(flight, seq)] = meta
            if fetched:
                self.fetched += 1
            self.changed = True
            _append_line(self.dir / "keyframes.jsonl", json.dumps(meta, sort_keys=True))
        self._queue_sift(name)
        return True

    def missing(self) -> list[Key]:
        with self.lock:
            out: list[Key] = []
            for flight in self.flights:
                seqs = [s for f, s in self.meta if f == flight]
                top = max([self.announced.get(flight, -1), *seqs], default=-1)
                out += [(flight, s) for s in range(top + 1) if (flight, s) not in self.meta]
            return out

    def overdue(self, grace: float) -> list[Key]:
        """Missing keyframes noticed more than ``grace`` seconds ago: a status or a
        later keyframe can overtake a large keyframe still in flight, so a gap is
        only queried once it has lasted a moment."""
        now = time.monotonic()
        gone = self.missing()
        with self.lock:
            self.missing_since = {s: self.missing_since.get(s, now) for s in gone}
            self.retry_at = {s: t for s, t in self.retry_at.items() if s in self.missing_since}
            return [s for s in gone if now - self.missing_since[s] >= grace]

    def next_chunk(
        self, grace: float, skip: set[Key] | None = None, wait_retry: bool = True
    ) -> tuple[str, int, int] | None:
        """The keyframes to ask for in the next query, as (flight, first, last): the
        first run of consecutive ones missing for ``grace`` seconds, at most GAP_CHUNK
        of it, leaving out those in ``skip`` and (with ``wait_retry``) those a query
        that ended lately did not bring."""
        now = time.monotonic()
        gone = self.overdue(grace)
        with self.lock:
            ready = [
                k
                for k in gone
                if not (skip and k in skip) and not (wait_retry and self.retry_at.get(k, 0) > now)
            ]
        if not ready:
            return None
        flight = ready[0][0]
        first, last = runs([s for f, s in ready if f == flight])[0]
        return flight, first, min(last, first + GAP_CHUNK - 1)

    def query_ended(self, flight: str, first: int, last: int) -> None:
        """A gap query has ended: what it did not bring waits GAP_RETRY_S."""
        at = time.monotonic() + GAP_RETRY_S
        with self.lock:
            for s in range(first, last + 1):
                if (flight, s) not in self.meta:
                    self.retry_at[(flight, s)] = at

    def count(self) -> int:
        with self.lock:
            return len(self.meta)

    def refresh_files(self) -> None:
        """Rewrites the dataset's files while the station runs, when keyframes arrived
        since they were last written: at most every FILES_EVERY_S seconds, and ten
        times as long apart as writing them took."""
        now = time.monotonic()
        if not self.changed or now < self.files_next:
            return
        self.files_next = now + FILES_EVERY_S  # after a failure too, not at every turn
        try:
            self.write_files()
        except Exception:
            self.changed = True  # tried again later
            raise
        took = time.monotonic() - now
        self.files_next = now + took + max(FILES_EVERY_S, 10.0 * took)

    def write_files(self) -> tuple[str | None, dict[str, Any] | None, int]:
        """Rewrites keyframes.jsonl in sequence order and writes the COLMAP/ODM files,
        each to a temporary name and renamed, for the keyframes stored so far; returns
        the COLMAP camera, ODM's cameras and the number of pairs."""
        with self.lock:
            # flights by id, the UTC time each started: in the order they were flown
            metas = [self.meta[k] for k in sorted(self.meta)]
            self.changed = False
            # Under the lock: a keyframe stored meanwhile appends its line to the file
            # this one replaces, and would be left out of the index.
            lines = "".join(json.dumps(m, sort_keys=True) + "\n" for m in metas)
            _write_atomic(self.dir / "keyframes.jsonl", lines.encode())
        names = [m["file"] for m in metas]
        for n in names:
            if n not in self.tags:
                self.tags[n] = read_tags((self.images / n).read_bytes())
        tags = [self.tags[n] for n in names]
        # Only a calibration the tags carry: a camera made of EXIF's nominal focal length
        # (centred principal point, no distortion) would be taken for one. Without it
        # there is no cameras.txt or cameras.json (nor one an earlier run left).
        camera = next((c for c in (colmap_camera(t) for t in tags) if c), None)
        if camera:
            header = "# Camera list with one line of data per camera:\n"
            header += "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
            _write_atomic(self.dir / "cameras.txt", (header + camera + "\n").encode())
        else:
            (self.dir / "cameras.txt").unlink(missing_ok=True)
        odm = next((c for c in (odm_cameras(t) for t in tags) if c), None)
        if odm:
            _write_atomic(self.dir / "cameras.json", (json.dumps(odm, indent=2) + "\n").encode())
        else:
            (self.dir / "cameras.json").unlink(missing_ok=True)
        rel = [_float_or_none(m.get("alt_rel")) for m in metas]
        quats = [_quaternion_or_none(m.get("cam_q")) for m in metas]
        pairs = image_pairs(names, tags, alt_above_ground=rel, cam_q=quats)
        _write_atomic(self.dir / "pairs.txt", "".join(f"{a} {b}\n" for a, b in pairs).encode())
        geo = ["EPSG:4326"]
        for n, t, m in zip(names, tags, metas, strict=True):
            row = geo_row(n, t, m)
            if row is not None:
                geo.append(row)
        _write_atomic(self.dir / "geo.txt", ("\n".join(geo) + "\n").encode())
        return camera, odm, len(pairs)

    def finish(self, hurry: threading.Event | None = None) -> dict[str, Any]:
        """Writes the dataset's files, then waits for the SIFT worker (unless told to
        hurry: the features left are computed by the next run on this folder), and
        returns the summary."""
        # A gap query's reply still arriving (a second signal stopped the waiting for
        # it) is not stored after the files are written, where they would not name it:
        # it stays missing, and a run on this folder again fetches it.
        with self.lock:
            self.closed = True
        # First: the files need no features, and a backlog of SIFT (a resumed dataset
        # of thousands) must not keep them from disk.
        camera, odm, pairs = self.write_files()
        hurry = hurry or threading.Event()
        sift_failed = 0
        sift_left = 0
        for job in self.sift_jobs:
            while not hurry.is_set() and not job.done():
                try:
                    job.exception(timeout=0.2)
                except TimeoutError:
                    pass
            if not job.done():
                job.cancel()  # one already running finishes (or leaves a .tmp)
                sift_left += 1
                continue
            try:
                job.result()
            except BaseException as err:  # one bad image must not cost the dataset
                sift_failed += 1
                print(f"keyframed-ground: {self.vehicle}: SIFT failed: {err}", file=sys.stderr)
        if sift_left:
            print(
                f"keyframed-ground: {self.vehicle}: {sift_left} keyframes left without SIFT "
                "features (stopped); a run on this folder computes them once it hears the vehicle",
                file=sys.stderr,
            )
        return {
            "vehicle": self.vehicle,
            "keyframes": self.count(),
            "fetched_by_query": self.fetched,
            "gap_queries": self.queries,
            "duplicates_ignored": self.duplicates,
            "sift_failed": sift_failed,
            "sift_left": sift_left,
            "earlier_flights_skipped": self.skipped_flights,
            # sequence numbers; "FLIGHT:N" for another flight than the first
            "missing": [
                s if f == (self.flights or [""])[0] else f"{f}:{s}" for f, s in self.missing()
            ],
            "flights_end_unknown": self.end_unknown(),
            "last_flight": self.current,
            "last_flight_ended": self.last_flight_end_heard(),
            "pairs": pairs,
            "calibrated": camera is not None,  # else no cameras.txt, cameras.json
            "camera": camera,
            "odm_camera": next(iter(odm)) if odm else None,
        }


def _float_or_none(v: Any) -> float | None:
    """A metadata value as a finite number; None for anything else (an integer too
    large for a float, inf and NaN included)."""
    try:
        f = float(v) if v not in (None, "") else None
    except (TypeError, ValueError, OverflowError):
        return None
    return f if f is not None and math.isfinite(f) else None


def _quaternion_or_none(v: Any) -> list[float] | None:
    """A keyframe's ``cam_q`` as four finite numbers, not all zero; else None."""
    if not isinstance(v, list | tuple) or len(v) != 4:
        return None
    q = [_float_or_none(x) for x in v]
    if any(x is None or not math.isfinite(x) for x in q):
        return None
    out = [float(x) for x in q if x is not None]
    return out if any(out) else None


def attitude(meta: dict[str, Any], tags: ImageTags) -> tuple[float, float, float] | None:
    """The camera's yaw, pitch, roll in degrees, Pix4D's convention (yaw 0: image top
    north, pitch 0: nadir; OpenDroneMap's for all but DJI's cameras): the XMP
    Camera:Yaw/Pitch/Roll of the JPEG, as the rest of its geo.txt line, else the
    keyframe's metadata (the same angles, to 4 decimals); None when neither has all
    three."""
    if tags.attitude is not None:
        return tags.attitude
    ypr = [_float_or_none(meta.get(k)) for k in ("yaw", "pitch", "roll")]
    y, p, r = (v if v is not None and math.isfinite(v) else None for v in ypr)
    return (y, p, r) if y is not None and p is not None and r is not None else None


def geo_row(name: str, tags: ImageTags, meta: dict[str, Any]) -> str | None:
    """The image's line of OpenDroneMap's geo.txt, ``name lon lat alt [yaw pitch roll
    [xy_accuracy z_accuracy]]`` (positional columns), or None without a position. ODM
    takes a line's angles over the image's own, so unknown ones are left out, never
    0 0 0 (every camera nadir, image top north); and it replaces the image's accuracies
    by the line's, by none when the line has none. So an image with an accuracy the
    line cannot carry (its attitude unknown, or only one of the two known) gets no
    line: ODM then reads position, angles and accuracies from its tags, as it would
    without geo.txt, rather than lose the accuracies. Neither does one without an
    altitude: the line has no way to leave it out, and 0 would be made up."""
    if tags.lat is None or tags.lon is None or tags.alt is None:
        return None
    ypr = attitude(meta, tags)
    xy, z = tags.xy_accuracy, tags.z_accuracy
    if (xy is not None or z is not None) and (ypr is None or xy is None or z is None):
        return None
    row = f"{name} {tags.lon:.9f} {tags.lat:.9f} {tags.alt:.3f}"
    if ypr is not None:
        row += " " + " ".join(f"{v:.6f}" for v in ypr)
    if xy is not None and z is not None:
        row += f" {xy:.3f} {z:.3f}"
    return row


# ------------------------------------------------------------------------ station


class GroundStation:
    def __init__(
        self,
        session: Any,
        out: Path,
        vehicle: str,
        sift: bool,
        quiet: bool,
        earlier_flights_s: float = 3600.0,
    ) -> None:
        self.session = session
        self.earlier_flights_s = earlier_flights_s
        self.out = out
        self.vehicle = vehicle
        self.quiet = quiet
        self.datasets: dict[str, VehicleDataset] = {}
        # Vehicles heard whose folder could not be made, with why: in the summary as
        # their error (exit 3), said once, not once a message.
        self.unwritable: dict[str, str] = {}
        self.lock = threading.Lock()
        self.last_arrival = 0.0
        self.wake = threading.Event()
        # A second SIGINT/SIGTERM: close() stops waiting for and asking for keyframes
        # (a vehicle that answers slowly, or never) and writes what it has.
        self.hurry = threading.Event()
        # Not forked from this process: its Zenoh threads hold locks a fork would copy
        # held (the first job is submitted from a subscriber callback).
        self.pool = (
            ProcessPoolExecutor(
                max_workers=1,
                initializer=_sift_worker_init,
                mp_context=multiprocessing.get_context("forkserver"),
            )
            if sift
            else None
        )
        self.subs = [
            session.declare_subscriber(keyframe_key(vehicle), self._on_keyframe),
            session.declare_subscriber(status_key(vehicle), self._on_status),
        ]

    def dataset(self, vehicle: str) -> VehicleDataset:
        if vehicle in ("", ".", ".."):  # a folder of its own under --out, nowhere else
            raise ValueError(f"bad vehicle name {vehicle!r}")
        with self.lock:
            if vehicle in self.unwritable:
                raise _Unwritable(self.unwritable[vehicle])
            if vehicle not in self.datasets:
                try:
                    self.datasets[vehicle] = VehicleDataset(self.out, vehicle, self.pool)
                except OSError as err:
                    why = f"cannot make its dataset folder {self.out / vehicle}: " + (
                        err.strerror or str(err)
                    )
                    self.unwritable[vehicle] = why
                    print(f"keyframed-ground: {vehicle}: {why}", file=sys.stderr)
                    raise _Unwritable(why) from err
            return self.datasets[vehicle]

    @staticmethod
    def _vehicle_of(key: str) -> str:
        parts = key.split("/")
        return parts[1] if len(parts) > 2 else "unknown"

    def _on_keyframe(self, sample: Any) -> None:
        try:
            meta = json.loads(sample.attachment.to_bytes()) if sample.attachment else {}
            if "sequence" not in meta:
                print("keyframed-ground: keyframe without a sequence number", file=sys.stderr)
                return
            ds = self.dataset(self._vehicle_of(str(sample.key_expr)))
            ds.note_running(os.path.basename(str(meta.get("flight") or "")))
            try:
                ds.add(meta, sample.payload.to_bytes())
            except OSError as err:  # a full disk: fetched again by query once there is room
                print(
                    f"keyframed-ground: {ds.vehicle}: cannot store keyframe "
                    f"{meta['sequence']}: {err.strerror or err}",
                    file=sys.stderr,
                )
                return
            self.last_arrival = time.monotonic()
            if ds.missing():
                self.wake.set()
        except _Unwritable:
            pass  # said once, when the vehicle was first heard
        except Exception as err:  # a bad message must not stop the station
            print(f"keyframed-ground: bad keyframe message: {err}", file=sys.stderr)

    def _on_status(self, sample: Any) -> None:
        try:
            status = json.loads(sample.payload.to_bytes())
            ds = self.dataset(self._vehicle_of(str(sample.key_expr)))
            flight = os.path.basename(str(status.get("flight") or ""))
            final = status.get("state") in FINAL_STATES
            n = status.get("keyframes", status.get("kept"))
            ds.note_flight(flight)
            if n is not None and not 0 <= int(n) <= MAX_FLIGHT_KEYFRAMES:
                raise ValueError(f"a keyframe count of {n} is not believed")
            if n is not None:
                with ds.lock:
                    ds.announced[flight] = max(ds.announced.get(flight, -1), int(n) - 1)
            if final and n is not None:
                ds.note_end(flight)
            elif not final:
                ds.note_running(flight)
            if final and not ds.done:
                ds.done = True
                ds.done_flight = flight
                ds.done_at = time.monotonic()
                self.wake.set()
            elif status.get("state") == "running" and ds.done and flight != ds.done_flight:
                ds.done = False  # the daemon started again: a new flight
            if ds.missing():
                self.wake.set()
        except _Unwritable:
            pass
        except Exception as err:
            print(f"keyframed-ground: bad status message: {err}", file=sys.stderr)

    def read_catalogues(self, timeout: float = 5.0, force: bool = False) -> None:
        """Asks each vehicle which flights it holds: when first heard of, and again
        when a flight its last list did not name appears; with ``force`` (at close)
        each vehicle once more, whatever was asked before."""
        now = time.monotonic()
        for ds in list(self.datasets.values()):
            with ds.lock:
                wait = not ds.catalogue_due or ds.catalogue_tries >= 3 or now < ds.catalogue_next
                if wait and not force:
                    continue
                ds.catalogue_due = False
                ds.catalogue_tries += 1
                ds.catalogue_next = now + 5.0
            answered = False
            for reply in self.session.get(flights_key(ds.vehicle), timeout=timeout):
                if reply.ok is None:
                    continue
                try:
                    flights = json.loads(reply.ok.payload.to_bytes())["flights"]
                    ds.note_catalogue(list(flights), self.earlier_flights_s)
                    answered = True
                except Exception as err:  # a bad reply must not stop the station
                    print(
                        f"keyframed-ground: {ds.vehicle}: bad list of flights: {err}",
                        file=sys.stderr,
                    )
            if not answered:
                with ds.lock:
                    ds.catalogue_due = ds.catalogue_due or ds.catalogue_tries < 3
            if ds.missing():
                self.wake.set()

    def fill_gaps(self, grace: float = GAP_GRACE_S) -> None:
        """Asks each vehicle's store for the keyframes we have lacked for ``grace``
        seconds, at most GAP_CHUNK in one query, and only once the vehicle's last
        query has ended: on a slow link its answer may still be on the way, and a
        query sent again would only compete with it."""
        for ds in list(self.datasets.values()):
            if ds.asking is not None and not ds.asking.is_set():
                continue
            chunk = ds.next_chunk(grace)
            if chunk is not None:
                self._ask(ds, *chunk)

    def _ask(self, ds: VehicleDataset, flight: str, first: int, last: int) -> threading.Event:
        """Sends one range query without waiting for it; each keyframe is one reply,
        keyed .../keyframes/<seq>, stored as it arrives. The event returned is set when
        the query has ended: answered, failed, or out of time."""
        import zenoh

        done = threading.Event()
        selector = range_selector(ds.vehicle, first, last, flight)

        def on_reply(reply: Any) -> None:
            try:
                self._take_reply(ds, reply, first, last, flight)
            except Exception as err:  # a bad reply must not stop the station
                print(
                    f"keyframed-ground: {ds.vehicle}: bad reply to {selector}: {err}",
                    file=sys.stderr,
                )

        def on_end() -> None:
            ds.query_ended(flight, first, last)
            done.set()
            self.wake.set()

        with ds.lock:
            ds.asking = done
            ds.queries += 1
        timeout = GAP_QUERY_S + GAP_QUERY_PER_KEYFRAME_S * (last - first + 1)
        try:
            # Each reply as it comes: Zenoh's default (latest-value) consolidation would
            # hold a chunk's replies back until its last one, or the timeout.
            self.session.get(
                selector,
                zenoh.handlers.Callback(on_reply, on_end),
                timeout=timeout,
                consolidation=zenoh.ConsolidationMode.NONE,
            )
        except Exception as err:
            print(f"keyframed-ground: {ds.vehicle}: query {selector}: {err}", file=sys.stderr)
            on_end()
        return done

    def drain(self) -> None:
        """At close: waits for the gap queries under way, then asks once more for
        every keyframe still missing, a chunk at a time per vehicle, and waits for
        those answers too; what they do not bring is reported missing."""
        asked: dict[str, set[Key]] = {}
        limit = GAP_QUERY_S + GAP_QUERY_PER_KEYFRAME_S * GAP_CHUNK + 5.0
        while not self.hurry.is_set():
            for ds in list(self.datasets.values()):
                asking = ds.asking
                deadline = time.monotonic() + limit  # Zenoh ends it by its timeout
                while (
                    asking is not None
                    and not asking.wait(0.2)
                    and not self.hurry.is_set()
                    and time.monotonic() < deadline
                ):
                    pass
            if self.hurry.is_set():
                return
            sent = False
            for ds in list(self.datasets.values()):
                skip = asked.setdefault(ds.vehicle, set())
                chunk = ds.next_chunk(0.0, skip=skip, wait_retry=False)
                if chunk is None:
                    continue
                flight, first, last = chunk
                skip.update((flight, s) for s in range(first, last + 1))
                self._ask(ds, flight, first, last)
                sent = True
            if not sent:
                return

    def _take_reply(
        self, ds: VehicleDataset, reply: Any, first: int, last: int, flight: str
    ) -> int:
        """Stores one keyframe a gap query returned; 1 when it was new."""
        if reply.ok is None:
            return 0
        s = reply.ok
        meta = json.loads(s.attachment.to_bytes()) if s.attachment else {}
        if not isinstance(meta, dict):
            raise ValueError("the attachment is no JSON object")
        if "sequence" not in meta:
            meta["sequence"] = int(str(s.key_expr).rsplit("/", 1)[-1])
        if not first <= int(meta["sequence"]) <= last:
            return 0
        if str(meta.get("flight") or "") != flight:
            return 0  # a daemon that does not know flights: not this one
        if not ds.add(meta, s.payload.to_bytes(), fetched=True):
            return 0
        self.last_arrival = time.monotonic()
        return 1

    def progress(self) -> str:
        # a vehicle may be heard meanwhile: a copy of the list
        parts = [ds.progress() for ds in list(self.datasets.values())]
        return "; ".join(parts) or "waiting for keyframes"

    def run(
        self,
        duration: float | None,
        until_idle: float | None,
        stop: threading.Event,
        until_done: bool = False,
    ) -> None:
        start = time.monotonic()
        last_print = 0.0
        while not stop.is_set():
            self.wake.wait(0.5)
            self.wake.clear()
            self.read_catalogues()
            self.fill_gaps()
            for ds in list(self.datasets.values()):
                try:
                    ds.refresh_files()
                except Exception as err:  # e.g. a full disk: the keyframes still come
                    print(
                        f"keyframed-ground: {ds.vehicle}: cannot write the dataset's files: {err}",
                        file=sys.stderr,
                    )
            now = time.monotonic()
            if not self.quiet and now - last_print > 1.0:
                print("\r" + self.progress() + "   ", end="", file=sys.stderr, flush=True)
                last_print = now
            if duration is not None and now - start > duration:
                break
            if (until_done or until_idle is not None) and self.unwritable and not self.datasets:
                break  # every vehicle heard has nowhere to go: nothing will arrive
            # Its last keyframes may still be in flight behind the final status.
            if (
                until_done
                and self.datasets
                and all(d.done and now - d.done_at > GAP_GRACE_S for d in self.datasets.values())
            ):
                break
            if (
                until_idle is not None
                and self.last_arrival
                and now - self.last_arrival > until_idle
            ):
                # Idle: nothing arrived, by subscription or by query, for a while.
                # What is still missing is asked for once more at close() and reported.
                break
        if not self.quiet:
            print(file=sys.stderr)

    def close(self) -> list[dict[str, Any]]:
        for s in self.subs:
            s.undeclare()
        # The vehicles' lists once more: a flight's last keyframes, and its final
        # status, may have been lost on the link with nothing after them to tell.
        if not self.hurry.is_set():
            self.read_catalogues(force=True)
        self.drain()
        results = []
        for ds in list(self.datasets.values()):
            try:
                results.append(ds.finish(self.hurry))
            except Exception as err:  # one vehicle's failure must not cost the others'
                print(f"keyframed-ground: {ds.vehicle}: {err}", file=sys.stderr)
                results.append({"vehicle": ds.vehicle, "keyframes": ds.count(), "error": str(err)})
        for vehicle, why in sorted(self.unwritable.items()):
            results.append({"vehicle": vehicle, "keyframes": 0, "error": why})
        if self.pool is not None:
            self.pool.shutdown(wait=not self.hurry.is_set(), cancel_futures=True)
        return results


def zenoh_error_text(err: BaseException) -> str:
    """Zenoh's error as one line, without the places in its Rust sources it names
    ("at /root/.cargo/.../endpoint.rs:615.") and with a JSON5 parser's position as
    "line L, column C" (as the daemon says them)."""
    text = re.sub(r" at /\S*?\.rs:\d+\.?(?=[\s\"]|$)", "", str(err))
    if m := re.search(r'msg: "((?:[^"\\]|\\.)*)"', text):
        where = re.search(r"line: (\d+), column: (\d+)", text)
        text = (f"line {where[1]}, column {where[2]}: " if where else "") + m[1]
    elif (pos := re.search(r"-->\s*(\d+):(\d+)", text)) and (
        what := re.search(r"^\s*=\s*(.+)$", text, re.MULTILINE)
    ):
        text = f"line {pos[1]}, column {pos[2]}: {what[1]}"
    return " ".join(text.split())


def open_session(args: argparse.Namespace) -> Any:
    import zenoh

    conf = zenoh.Config.from_file(str(args.zenoh_config)) if args.zenoh_config else zenoh.Config()
    if args.mode:
        conf.insert_json5("mode", json.dumps(args.mode))
    if args.connect:
        conf.insert_json5("connect/endpoints", json.dumps(args.connect))
    if args.listen:
        conf.insert_json5("listen/endpoints", json.dumps(args.listen))
    if args.connect or args.listen:
        conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="keyframed-ground", description=__doc__, formatter_class=argparse.RawTextHelpFormatter
    )
    p.add_argument("--out", type=Path, required=True, help="dataset folder (one per vehicle)")
    p.add_argument("--vehicle", default="*", help="vehicle name, or * for all (default)")
    p.add_argument("--zenoh-config", type=Path, help="Zenoh JSON5 configuration file")
    p.add_argument("--mode", choices=["peer", "client"], help="Zenoh mode (default: config's)")
    p.add_argument("--connect", action="append", default=[], help="endpoint, e.g. tcp/IP:7447")
    p.add_argument("--listen", action="append", default=[], help="endpoint to listen on")
    p.add_argument("--sift", action="store_true", help="write SIFT features for COLMAP")
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    p.add_argument(
        "--until-idle", type=float, help="stop once no keyframe arrived for this many seconds"
    )
    p.add_argument(
        "--until-done", action="store_true", help="stop once every vehicle's flight has ended"
    )
    p.add_argument(
        "--earlier-flights",
        type=float,
        default=3600.0,
        metavar="SECONDS",
        help="fetch the keyframes of a vehicle's earlier flights (runs of its daemon before"
        " a restart) that ended at most this long ago (default 3600; 0: none)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress line")
    args = p.parse_args(argv)
    if args.zenoh_config and not args.zenoh_config.is_file():
        what = "not a file" if args.zenoh_config.exists() else "no such file"
        print(f"keyframed-ground: --zenoh-config {args.zenoh_config}: {what}", file=sys.stderr)
        return 2
    if not args.earlier_flights >= 0:
        print("keyframed-ground: --earlier-flights must be 0 or more seconds", file=sys.stderr)
        return 2
    # As the daemon takes them (zenoh.vehicle): a key chunk, a folder name.
    if args.vehicle != "*" and (
        not re.fullmatch(r"[A-Za-z0-9._-]{1,64}", args.vehicle) or args.vehicle in (".", "..")
    ):
        print(
            f"keyframed-ground: bad vehicle name {args.vehicle!r} (letters, digits, '-', '_' "
            "and '.', at most 64; or * for all)",
            file=sys.stderr,
        )
        return 2
    # Zenoh retries an endpoint it cannot reach without a word: one that cannot exist
    # (a port past 65535, no port) is a typo, said now.
    for flag, endpoints in (("--connect", args.connect), ("--listen", args.listen)):
        for endpoint in endpoints:
            proto, _, address = endpoint.partition("/")
            if not (re.fullmatch(r"[a-z][a-z0-9-]*", proto) and address):
                print(
                    f"keyframed-ground: {flag} {endpoint}: not PROTOCOL/ADDRESS "
                    "(e.g. tcp/192.168.1.10:7447)",
                    file=sys.stderr,
                )
                return 2
            if proto in ("tcp", "udp", "tls", "quic", "ws"):
                port = address.rpartition(":")[2].split("#")[0]
                if not (port.isdigit() and int(port) <= 65535 and address.rpartition(":")[0]):
                    print(
                        f"keyframed-ground: {flag} {endpoint}: not HOST:PORT with a port of "
                        "0 to 65535",
                        file=sys.stderr,
                    )
                    return 2
    for name in ("duration", "until_idle"):
        value = getattr(args, name)
        if value is not None and not (math.isfinite(value) and value > 0):
            flag = "--" + name.replace("_", "-")
            print(f"keyframed-ground: {flag} must be a number of seconds > 0", file=sys.stderr)
            return 2
    try:
        args.out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        print(f"keyframed-ground: cannot create {args.out}: {err.strerror}", file=sys.stderr)
        return 1
    # A folder that exists but takes no file (read-only, another user's) is said now,
    # not once the first vehicle is heard.
    try:
        with tempfile.TemporaryFile(dir=args.out):
            pass
    except OSError as err:
        print(f"keyframed-ground: cannot write in {args.out}: {err.strerror}", file=sys.stderr)
        return 1
    try:
        session = open_session(args)
    except Exception as err:
        print(
            f"keyframed-ground: cannot open the Zenoh session: {zenoh_error_text(err)}",
            file=sys.stderr,
        )
        return 1
    stop = threading.Event()
    station = GroundStation(
        session, args.out, args.vehicle, args.sift, args.quiet, args.earlier_flights
    )

    closing = threading.Event()

    def on_signal(*_: Any) -> None:
        # The first stops receiving and fetches what is missing; one while that goes on
        # gives up on it and writes the dataset as it stands (what is missing is
        # reported).
        if stop.is_set() or closing.is_set():
            station.hurry.set()
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    try:
        station.run(args.duration, args.until_idle, stop, args.until_done)
    finally:
        closing.set()
        results = station.close()
        session.close()
    if station.hurry.is_set():
        print("keyframed-ground: stopped without waiting for missing keyframes", file=sys.stderr)
    if not results:
        # Nothing at all: most likely the link, not the vehicle (a vehicle in Zenoh's
        # peer mode listens on a port of its own choosing, which --connect cannot guess).
        print(
            "keyframed-ground: heard no vehicle"
            + (f" named {args.vehicle}" if args.vehicle != "*" else "")
            + ": check the endpoints (a vehicle in peer mode needs a listen endpoint of its "
            "own for --connect; a client vehicle dials the station's --listen or a router)",
            file=sys.stderr,
        )
        return 4
    for r in results:
        print(json.dumps(r, sort_keys=True))
    for r in results:
        if r.get("last_flight_ended") is False:
            # Not an error (the station may be stopped while the vehicle flies), but the
            # dataset need not be complete: keyframes after its last status are unknown.
            flight = r["last_flight"] or "(no id)"
            print(
                f"keyframed-ground: {r['vehicle']}: flight {flight} has not ended "
                f"as far as the station knows ({r['keyframes']} keyframes held): keyframes "
                "taken after the last status heard may be missing; run the station again "
                "once the vehicle is in reach to fetch them",
                file=sys.stderr,
            )
    unwritten = [r["vehicle"] for r in results if r.get("error")]
    incomplete = [
        r["vehicle"]
        for r in results
        if not r.get("error") and (r.get("missing") or r.get("flights_end_unknown"))
    ]
    if unwritten:
        print(
            f"keyframed-ground: datasets not written for {unwritten} (see their error)",
            file=sys.stderr,
        )
    if incomplete:
        print(f"keyframed-ground: keyframes still missing for {incomplete}", file=sys.stderr)
    if unwritten or incomplete:
        return 3
    return 0


if __name__ == "__main__":
    sys.exit(main())
