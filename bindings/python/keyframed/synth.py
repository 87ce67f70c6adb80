"""Deterministic synthetic drone flights with exact ground truth.

A flight is rendered over a planar, textured ground (z = 0 in a local ENU frame,
metres) seen by an ideal pinhole camera that is rigidly mounted on a multirotor.
Everything is a pure function of (flight name, duration, image size, frame rate,
exposure, seed): generating twice gives byte-identical ground truth and frames.

World
    One ground mosaic (250 m x 250 m at 0.05 m per texel, centred on the ENU origin)
    is built once per process from the opencv-doc photographs (aero1/aero3 as large
    rotated/scaled tiles, the others as scattered patches) blended with procedural
    texture (fields with crop stripes, roads, buildings, bushes, multi-octave value
    noise), so that every part of the ground carries trackable texture. Frames are
    perspective warps of a half-octave mip-map pyramid of it (nearest half-octave
    level when the scale is nearly uniform across the frame, per-pixel blending of
    two levels otherwise), so that neither nadir nor oblique views alias.

Camera
    Pinhole, no distortion, horizontal FOV 70 degrees, fx = fy, principal point at
    the image centre in the OpenCV convention (the centre of pixel (0, 0) is at
    (0, 0), so cx = (width - 1) / 2). The physical model is a 1/2.3" sensor
    6.17 mm wide (height = 6.17 * height / width mm), focal length
    fx * 6.17 / width mm. Camera axes: x right, y down, z forward.

    The camera is fixed to the vehicle body (FRD) through a pure pitch mount of
    ``mount_pitch_deg`` (negative = down): R_body_cam = Ry(mount) * R0, where R0
    maps camera (x right, y down, z forward) onto body (y, z, x). Nadir flights use
    -90 deg (image top = vehicle nose); the orbit uses a fixed forward mount 55
    degrees down (the vehicle banks into the turn, its pitch stays near level).

Flights (30 fps by default; ``seconds`` shortens or lengthens them from the start)
    nadir   30 s lawnmower survey at 50 m above the ground, 8 m/s, legs 25 m apart
            heading north then south: cruise 0-3 s, deceleration 3-7 s, stationary
            7-12 s (``hover`` flag 7.5-11.5 s, once the attitude has settled),
            acceleration 12-16 s, U-turn 18-24 s with a fast 180 deg yaw snap
            (1.6 s) in its middle, second leg from 24 s; gusts at ~14.7 s and ~27 s,
            defocus at ~4.0-4.7 s and ~25.0-25.7 s.
    orbit   20 s orbit of radius 30 m round the ENU origin, 35 m up, 6 m/s, nose
            and camera along the track, camera 55 deg down; gusts at ~8.7 s and
            ~17.4 s, defocus at ~5.0-5.7 s and ~14.0-14.7 s.
    The seed moves event times slightly and changes jitter and sensor noise; the
    ground texture is the same for every seed. The nadir survey leaves the textured
    ground after ~37 s (ValueError); the orbit can run for any duration.

Vehicle attitude
    Roll/pitch/yaw in the aeronautical (NED, ZYX) convention, yaw clockwise from
    north. Roll and pitch follow the horizontal acceleration of the trajectory
    (tilt = atan(a / g), low-passed like a real vehicle), plus gusts (short damped
    3 Hz wobbles) and a tiny jitter.

Time
    Frame ``i`` is exposed over [t_i - exposure/2, t_i + exposure/2] with
    t_i = i / fps (the ground-truth pose is the mid-exposure pose). Unix time of
    frame 0 is ``EPOCH_UNIX_S`` (2026-06-01T10:00:00Z); the autopilot's
    ``time_boot_ms`` is ``BOOT_MS_AT_FRAME0`` at frame 0. Telemetry starts 2 s
    before frame 0 and ends 1 s after the last frame.

Geodesy
    ENU (x east, y north, z up, metres above the ground) is converted to WGS84 by a
    local flat-earth approximation around ``ORIGIN_LAT``/``ORIGIN_LON``:
    lat = lat0 + y / R_M, lon = lon0 + x / (R_N cos lat0) (radians), with R_M and
    R_N the WGS84 meridian and prime-vertical radii of curvature at lat0;
    alt (AMSL) = ``GROUND_ALT_AMSL_M`` + z. The same conversion is used for the
    ground truth and the tlog.

Blur ground truth
    The exposure defaults to 1/500 s (a daylight survey shutter: at 1/60 s the
    cruise alone would smear 2-4 px). ``blur_px`` is the largest image path length,
    during the exposure, of the ground points under the four corner pixels and the
    centre. Frames with ``blur_px`` >= 1 are the average of sub-frames at most 0.5 px
    apart (exact plane-induced warps of the mid-exposure view); below 1 px a single
    render is used. Defocus segments apply a Gaussian blur of ``defocus_sigma``
    pixels (3.2 px at 960 px width, scaled with the width, 0.1 s ramps).
    ``blurry = blur_px > 2 or defocus_sigma > 1``: being in pixels, it depends on
    the resolution (more frames are blurry at 1920 px than at 960 px). Sensor noise:
    Gaussian, sigma 2 DN.

Outputs of :func:`generate` (all in one directory)
    video.avi          MJPG (quality 90), BGR, one frame per ground-truth row. Under
                       AVI_MAX_BYTES (OpenCV's AVI writer holds 4 GiB): about 3.5
                       minutes at 1920x1080, 11 at 960x540; longer is refused.
    groundtruth.csv    one row per frame, columns ``GT_COLUMNS``.
    intrinsics.json    width, height, fx, fy, cx, cy, distortion, sensor and focal
                       length in mm, fps, exposure_s, mount_pitch_deg.
    calibration.yaml   the same camera as an OpenCV FileStorage YAML (camera_matrix,
                       distortion_coefficients, image_width, image_height as
                       cv::calibrateCamera samples write them, plus sensor_width_mm,
                       sensor_height_mm, focal_length_mm, make, model): what the
                       daemon's camera calibration setting reads.
    flight.tlog        MAVLink 2 tlog (8-byte big-endian unix microseconds + packed
                       message per record) from system 1 / component 1: HEARTBEAT
                       1 Hz, ATTITUDE 50 Hz, ATTITUDE_QUATERNION 50 Hz,
                       GLOBAL_POSITION_INT 10 Hz, GPS_RAW_INT 5 Hz, SYSTEM_TIME 1 Hz.
    meta.json          flight name, seed, frame count, epoch, origin, hover and
                       defocus frame ranges, event times.

Command line: ``python -m keyframed.synth --flight nadir --out DIR``.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import queue
import struct
import sys
import threading
import time
from dataclasses import dataclass, field
from datetime import UTC, datetime
from functools import lru_cache
from pathlib import Path
from typing import Any, NoReturn

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "BOOT_MS_AT_FRAME0",
    "DEFAULT_EXPOSURE_S",
    "EPOCH_UNIX_S",
    "FLIGHTS",
    "GROUND_ALT_AMSL_M",
    "GT_COLUMNS",
    "ORIGIN_LAT",
    "ORIGIN_LON",
    "Flight",
    "FlightInfo",
    "default_seconds",
    "enu_to_geodetic",
    "generate",
    "ground_mosaic",
    "intrinsics_matrix",
    "load_flight",
    "main",
    "overlap_fraction",
]

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]
U8 = NDArray[np.uint8]

# --------------------------------------------------------------------------- constants

FLIGHTS: tuple[str, ...] = ("nadir", "orbit")
_DEFAULT_SECONDS = {"nadir": 30.0, "orbit": 20.0}

EPOCH_UNIX_S = 1780308000  # 2026-06-01T10:00:00Z, unix time of frame 0
BOOT_MS_AT_FRAME0 = 123456  # autopilot time_boot_ms at frame 0
ORIGIN_LAT = 51.8900  # deg, ENU origin (Essex)
ORIGIN_LON = 0.9400  # deg
GROUND_ALT_AMSL_M = 20.0  # ground plane height above mean sea level
GEOID_SEPARATION_M = 46.0  # ellipsoid height - AMSL height (for GPS_RAW_INT.alt_ellipsoid)

HFOV_DEG = 70.0
SENSOR_WIDTH_MM = 6.17  # 1/2.3" sensor
DEFAULT_EXPOSURE_S = 1.0 / 500.0  # daylight survey shutter; 1/60 s would smear every frame
BLUR_PX_THRESHOLD = 2.0
DEFOCUS_SIGMA_THRESHOLD = 1.0
DEFOCUS_SIGMA_AT_960 = 3.2
NOISE_SIGMA_DN = 2.0
MJPG_QUALITY = 90
# OpenCV's own AVI writer keeps the file's sizes in 32 bits: past 4 GiB it aborts the
# process as it closes the file. A flight whose video would pass this is refused.
AVI_MAX_BYTES = 3_800_000_000

TEXEL_M = 0.05
WORLD_HALF_M = 125.0
WORLD_SEED = 20260601
_GROUND_MARGIN_M = 2.0

_PRE_S = 2.0  # trajectory (and telemetry) starts this long before frame 0
_POST_S = 2.0
_DT = 0.001  # trajectory grid step
_G = 9.80665

GT_COLUMNS: tuple[str, ...] = (
    "index",
    "t",
    "x",
    "y",
    "z",
    "qw",
    "qx",
    "qy",
    "qz",
    "roll_deg",
    "pitch_deg",
    "yaw_deg",
    "lat",
    "lon",
    "alt",
    "blur_px",
    "defocus_sigma",
    "blurry",
    "hover",
)

_PHOTO_DIR = Path("/usr/share/doc/opencv-doc/examples/data")
_AERIAL = ("aero1.jpg", "aero3.jpg")
_PATCHES = (
    "baboon.jpg",
    "building.jpg",
    "fruits.jpg",
    "home.jpg",
    "graf1.png",
    "leuvenA.jpg",
    "box_in_scene.png",
    "starry_night.jpg",
    "stuff.jpg",
    "board.jpg",
    "orange.jpg",
    "apple.jpg",
    "blox.jpg",
    "butterfly.jpg",
    "smarties.png",
    "messi5.jpg",
    "pic1.png",
)


# --------------------------------------------------------------------------- geodesy


def enu_to_geodetic(x: F64 | float, y: F64 | float, z: F64 | float) -> tuple[F64, F64, F64]:
    """Local flat-earth ENU (m) -> WGS84 latitude, longitude (deg) and altitude (m AMSL)."""
    a = 6378137.0
    e2 = 6.69437999014e-3
    phi = math.radians(ORIGIN_LAT)
    s2 = math.sin(phi) ** 2
    r_n = a / math.sqrt(1.0 - e2 * s2)
    r_m = a * (1.0 - e2) / (1.0 - e2 * s2) ** 1.5
    lat = ORIGIN_LAT + np.degrees(np.asarray(y, np.float64) / r_m)
    lon = ORIGIN_LON + np.degrees(np.asarray(x, np.float64) / (r_n * math.cos(phi)))
    alt = GROUND_ALT_AMSL_M + np.asarray(z, np.float64)
    return lat, lon, alt


# --------------------------------------------------------------------------- rotations

# ENU <- NED (a symmetric permutation with a sign: it is its own inverse)
_T_ENU_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
# body FRD <- camera (x right, y down, z forward) for a forward-looking camera
_R_BODY_CAM0 = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def _euler_to_rotmat(roll: F64, pitch: F64, yaw: F64) -> F64:
    """ZYX aeronautical Euler angles (rad) -> R_ned_body, shape (n, 3, 3)."""
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cy, sy = np.cos(yaw), np.sin(yaw)
    r = np.empty((len(roll), 3, 3))
    r[:, 0, 0] = cy * cp
    r[:, 0, 1] = cy * sp * sr - sy * cr
    r[:, 0, 2] = cy * sp * cr + sy * sr
    r[:, 1, 0] = sy * cp
    r[:, 1, 1] = sy * sp * sr + cy * cr
    r[:, 1, 2] = sy * sp * cr - cy * sr
    r[:, 2, 0] = -sp
    r[:, 2, 1] = cp * sr
    r[:, 2, 2] = cp * cr
    return r


def _mount_rotation(mount_pitch_deg: float) -> F64:
    """R_body_cam for a camera pitched by mount_pitch_deg (negative = down)."""
    p = math.radians(mount_pitch_deg)
    ry = np.array(
        [[math.cos(p), 0.0, math.sin(p)], [0.0, 1.0, 0.0], [-math.sin(p), 0.0, math.cos(p)]]
    )
    return ry @ _R_BODY_CAM0


def _rotmat_to_quat(r: F64) -> F64:
    """Rotation matrices (n, 3, 3) -> unit quaternions (n, 4) as w, x, y, z with w >= 0."""
    n = r.shape[0]
    q = np.empty((n, 4))
    tr = r[:, 0, 0] + r[:, 1, 1] + r[:, 2, 2]
    cands = np.stack(
        [tr, r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]],
        axis=1,
    )
    k = np.argmax(cands, axis=1)
    for idx in range(n):
        m = r[idx]
        if k[idx] == 0:
            s = math.sqrt(max(tr[idx] + 1.0, 0.0)) * 2.0
            q[idx] = (
                0.25 * s,
                (m[2, 1] - m[1, 2]) / s,
                (m[0, 2] - m[2, 0]) / s,
                (m[1, 0] - m[0, 1]) / s,
            )
        elif k[idx] == 1:
            s = math.sqrt(max(1.0 + m[0, 0] - m[1, 1] - m[2, 2], 0.0)) * 2.0
            q[idx] = (
                (m[2, 1] - m[1, 2]) / s,
                0.25 * s,
                (m[0, 1] + m[1, 0]) / s,
                (m[0, 2] + m[2, 0]) / s,
            )
        elif k[idx] == 2:
            s = math.sqrt(max(1.0 + m[1, 1] - m[0, 0] - m[2, 2], 0.0)) * 2.0
            q[idx] = (
                (m[0, 2] - m[2, 0]) / s,
                (m[0, 1] + m[1, 0]) / s,
                0.25 * s,
                (m[1, 2] + m[2, 1]) / s,
            )
        else:
            s = math.sqrt(max(1.0 + m[2, 2] - m[0, 0] - m[1, 1], 0.0)) * 2.0
            q[idx] = (
                (m[1, 0] - m[0, 1]) / s,
                (m[0, 2] + m[2, 0]) / s,
                (m[1, 2] + m[2, 1]) / s,
                0.25 * s,
            )
    q *= np.where(q[:, :1] < 0.0, -1.0, 1.0)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q


def _quat_to_rotmat(q: F64) -> F64:
    """Quaternions (n, 4) w, x, y, z -> rotation matrices (n, 3, 3)."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    r = np.empty((q.shape[0], 3, 3))
    r[:, 0, 0] = 1 - 2 * (y * y + z * z)
    r[:, 0, 1] = 2 * (x * y - w * z)
    r[:, 0, 2] = 2 * (x * z + w * y)
    r[:, 1, 0] = 2 * (x * y + w * z)
    r[:, 1, 1] = 1 - 2 * (x * x + z * z)
    r[:, 1, 2] = 2 * (y * z - w * x)
    r[:, 2, 0] = 2 * (x * z - w * y)
    r[:, 2, 1] = 2 * (y * z + w * x)
    r[:, 2, 2] = 1 - 2 * (x * x + y * y)
    return r


# --------------------------------------------------------------------------- camera


def intrinsics_matrix(width: int, height: int) -> F64:
    """Pinhole K for the synthetic camera (HFOV 70 deg, square pixels, OpenCV centre)."""
    fx = (width / 2.0) / math.tan(math.radians(HFOV_DEG) / 2.0)
    return np.array([[fx, 0.0, (width - 1) / 2.0], [0.0, fx, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def _ground_to_image(k: F64, r_wc: F64, c: F64) -> F64:
    """Homographies (n, 3, 3) mapping ground (X, Y, 1) to image (u, v, 1) * depth."""
    r_cw = np.transpose(r_wc, (0, 2, 1))
    m = np.empty_like(r_cw)
    m[:, :, 0] = r_cw[:, :, 0]
    m[:, :, 1] = r_cw[:, :, 1]
    m[:, :, 2] = -np.einsum("nij,nj->ni", r_cw, c)
    return np.einsum("ij,njk->nik", k, m)


def _apply_h(h: F64, pts: F64) -> tuple[F64, F64]:
    """Apply one homography to (n, 2) points: returns (n, 2) points and w."""
    p = pts @ h[:, :2].T + h[:, 2]
    w = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        return p[:, :2] / w[:, None], w


# --------------------------------------------------------------------------- polygons


def _clip_halfplane(poly: F64, a: float, b: float, c: float) -> F64:
    """Sutherland-Hodgman step: keep the part of ``poly`` where a*x + b*y + c >= 0."""
    n = len(poly)
    if n == 0:
        return poly
    d = poly[:, 0] * a + poly[:, 1] * b + c
    out: list[F64] = []
    for i in range(n):
        j = (i + 1) % n
        p, q = poly[i], poly[j]
        dp, dq = d[i], d[j]
        if dp >= 0.0:
            out.append(p)
        if (dp >= 0.0) != (dq >= 0.0):
            out.append(p + (q - p) * (dp / (dp - dq)))
    if not out:
        return np.zeros((0, 2))
    return np.array(out)


def _clip_rect(poly: F64, x0: float, y0: float, x1: float, y1: float) -> F64:
    poly = _clip_halfplane(poly, 1.0, 0.0, -x0)
    poly = _clip_halfplane(poly, -1.0, 0.0, x1)
    poly = _clip_halfplane(poly, 0.0, 1.0, -y0)
    return _clip_halfplane(poly, 0.0, -1.0, y1)


def _area(poly: F64) -> float:
    if len(poly) < 3:
        return 0.0
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def _rect(width: int, height: int) -> F64:
    return np.array(
        [[-0.5, -0.5], [width - 0.5, -0.5], [width - 0.5, height - 0.5], [-0.5, height - 0.5]]
    )


def overlap_fraction(
    h_ij: ArrayLike,
    width: int,
    height: int,
    width_j: int | None = None,
    height_j: int | None = None,
) -> float:
    """Fraction of image i's area whose content lands inside image j under ``h_ij``.

    ``h_ij`` maps pixels of image i to pixels of image j (OpenCV pixel-centre
    convention; the image rectangle is [-0.5, w - 0.5] x [-0.5, h - 0.5]). It must
    be scaled so that the homogeneous w is positive for points in front of
    camera j (true for plane-induced homographies built by :class:`Flight` and for
    any homography normalised with h33 = 1 whose image-i centre maps in front, e.g.
    cv2.findHomography on matched features). Image i's rectangle is clipped to the
    half-plane w > 0, mapped into image j, clipped to image j's rectangle
    (Sutherland-Hodgman), mapped back, and its area is divided by width * height.
    """
    wj = width if width_j is None else width_j
    hj = height if height_j is None else height_j
    h = np.asarray(h_ij, np.float64)
    scale = float(np.abs(h[2]).max()) * (width + height) + 1e-300
    poly = _clip_halfplane(_rect(width, height), h[2, 0], h[2, 1], h[2, 2] - 1e-9 * scale)
    if len(poly) < 3:
        return 0.0
    pj, _ = _apply_h(h, poly)
    pj = _clip_rect(pj, -0.5, -0.5, wj - 0.5, hj - 0.5)
    if len(pj) < 3:
        return 0.0
    pi, _ = _apply_h(np.asarray(np.linalg.inv(h), np.float64), pj)
    return float(min(max(_area(pi) / float(width * height), 0.0), 1.0))


# --------------------------------------------------------------------------- mosaic


@dataclass(frozen=True)
class _Mosaic:
    levels: tuple[U8, ...]  # half-octave mip-map, BGRA; level j texel = TEXEL_M * 2**(j/2)
    level_mats: tuple[F64, ...]  # level-0 (col, row, 1) -> level-j (col, row, 1)
    ground_to_tex0: F64  # (X, Y, 1) -> level-0 (col, row, 1)


def _value_noise(rng: np.random.Generator, h: int, w: int, cell: float) -> F32:
    """Smooth random field (bicubic value noise) with ~unit std and features ~cell px."""
    gh = int(h / cell) + 4
    gw = int(w / cell) + 4
    grid = rng.standard_normal((gh, gw), dtype=np.float32)
    big = cv2.resize(
        grid, (int(round(gw * cell)), int(round(gh * cell))), interpolation=cv2.INTER_CUBIC
    )
    o = int(cell)
    out = np.ascontiguousarray(big[o : o + h, o : o + w], np.float32)
    out *= 1.0 / (float(out[::7, ::7].std()) + 1e-6)
    return out


def _load_photo(name: str) -> U8:
    img = cv2.imread(str(_PHOTO_DIR / name), cv2.IMREAD_COLOR)
    if img is None:
        # Without them the flight would quietly be another one (procedural ground
        # only), its results not comparable with anyone else's.
        raise FileNotFoundError(
            f"cannot read {_PHOTO_DIR / name}: the sample flights are made from OpenCV's "
            "sample photographs (Debian package opencv-doc; tools/setup.sh installs it)"
        )
    if name == "aero3.jpg":
        img = img[95:]  # drop the featureless sea and sky
    if name in _AERIAL:  # undo the haze of these high-altitude oblique shots
        lab = cv2.cvtColor(img, cv2.COLOR_BGR2LAB)
        clahe = cv2.createCLAHE(clipLimit=3.0, tileGridSize=(8, 8))
        lab[:, :, 0] = clahe.apply(np.ascontiguousarray(lab[:, :, 0]))
        img = cv2.cvtColor(lab, cv2.COLOR_LAB2BGR)
    return np.ascontiguousarray(img)


def _paste_photo(
    canvas: U8,
    img: U8,
    centre_px: tuple[float, float],
    scale: float,
    angle_deg: float,
    opacity: float,
    feather_px: float,
    gains: F64,
) -> None:
    """Blend ``img`` into ``canvas`` rotated/scaled about centre_px with feathered edges."""
    h, w = img.shape[:2]
    rot = cv2.getRotationMatrix2D((w / 2.0, h / 2.0), angle_deg, scale)
    rot[0, 2] += centre_px[0] - w / 2.0
    rot[1, 2] += centre_px[1] - h / 2.0
    corners = np.array([[0, 0, 1], [w, 0, 1], [w, h, 1], [0, h, 1]], np.float64) @ rot.T
    x0 = max(int(math.floor(corners[:, 0].min())), 0)
    y0 = max(int(math.floor(corners[:, 1].min())), 0)
    x1 = min(int(math.ceil(corners[:, 0].max())) + 1, canvas.shape[1])
    y1 = min(int(math.ceil(corners[:, 1].max())) + 1, canvas.shape[0])
    if x1 <= x0 or y1 <= y0:
        return
    rot[0, 2] -= x0
    rot[1, 2] -= y0
    size = (x1 - x0, y1 - y0)
    f = max(feather_px / scale, 1.0)
    yy = np.arange(h, dtype=np.float32)[:, None]
    xx = np.arange(w, dtype=np.float32)[None, :]
    edge = np.minimum(np.minimum(xx + 0.5, w - 0.5 - xx), np.minimum(yy + 0.5, h - 0.5 - yy))
    alpha_src = np.clip(edge / f, 0.0, 1.0).astype(np.float32)
    warped = cv2.warpAffine(img, rot, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    alpha = cv2.warpAffine(alpha_src, rot, size, flags=cv2.INTER_LINEAR, borderValue=0.0)
    alpha = (alpha * opacity)[:, :, None]
    roi = canvas[y0:y1, x0:x1].astype(np.float32)
    src = warped.astype(np.float32) * gains.astype(np.float32)
    roi += alpha * (src - roi)
    canvas[y0:y1, x0:x1] = np.clip(roi + 0.5, 0, 255).astype(np.uint8)


def _random_polyline(rng: np.random.Generator, half_m: float) -> F64:
    """A gently curving line across the world (metres)."""
    theta = rng.uniform(0.0, math.pi)
    d = np.array([math.cos(theta), math.sin(theta)])
    nrm = np.array([-d[1], d[0]])
    off = rng.uniform(-0.7, 0.7) * half_m
    s = np.linspace(-1.6 * half_m, 1.6 * half_m, 40)
    wiggle = np.cumsum(rng.normal(0.0, 1.5, s.size))
    smooth = np.convolve(np.pad(wiggle, 5, mode="edge"), np.ones(11) / 11.0, mode="valid")
    wiggle = np.asarray(smooth, np.float64)
    wiggle -= wiggle.mean()
    return s[:, None] * d + (off + wiggle)[:, None] * nrm


def _build_mosaic(seed: int = WORLD_SEED) -> _Mosaic:
    rng = np.random.default_rng(seed)
    half = WORLD_HALF_M
    n = int(round(2 * half / TEXEL_M))
    cs = 4  # coarse layer: 4 texels per coarse pixel (0.2 m)
    nc = n // cs
    cm = TEXEL_M * cs

    # ---- coarse procedural landscape: fields (Voronoi cells) with crop stripes
    nseed = 48
    seeds = rng.uniform(-half, half, (nseed, 2))
    lab_n = nc // 2
    g = (np.arange(lab_n) + 0.5) * (2 * half / lab_n) - half
    gx, gy = np.meshgrid(g, -g)  # row 0 is north
    d2 = (gx[None] - seeds[:, 0, None, None]) ** 2 + (gy[None] - seeds[:, 1, None, None]) ** 2
    labels = np.argmin(d2, axis=0).astype(np.int32)
    labels = cv2.resize(labels.astype(np.float32), (nc, nc), interpolation=cv2.INTER_NEAREST)
    labels = labels.astype(np.int32)
    palette = np.array(
        [
            [60, 120, 70],
            [50, 140, 90],
            [40, 100, 60],
            [70, 110, 150],
            [60, 90, 130],
            [80, 170, 190],
            [90, 180, 200],
            [100, 130, 110],
            [110, 150, 160],
            [45, 80, 95],
        ],
        np.float32,
    )
    colours = palette[rng.integers(0, len(palette), nseed)] + rng.uniform(-15, 15, (nseed, 3))
    ang = rng.uniform(0, math.pi, nseed)
    period = rng.uniform(1.2, 3.5, nseed)
    amp = rng.uniform(0.05, 0.22, nseed) * (rng.uniform(0, 1, nseed) > 0.2)
    cx = (np.arange(nc, dtype=np.float32) + 0.5) * cm - half
    xx, yy = np.meshgrid(cx, -cx)
    phase = (xx * np.cos(ang)[labels] + yy * np.sin(ang)[labels]) / period[labels]
    stripes = 1.0 + amp[labels].astype(np.float32) * np.sin(2 * np.pi * phase).astype(np.float32)
    low = (
        0.12 * _value_noise(rng, nc, nc, 40.0 / cm)
        + 0.08 * _value_noise(rng, nc, nc, 12.0 / cm)
        + 0.06 * _value_noise(rng, nc, nc, 5.0 / cm)
    )
    coarse = colours.astype(np.float32)[labels] * (stripes * (1.0 + low))[:, :, None]
    coarse = np.clip(coarse, 0, 255).astype(np.uint8)

    base = cv2.resize(coarse, (n, n), interpolation=cv2.INTER_CUBIC)
    del coarse, labels, xx, yy, phase, stripes, low

    # ---- photographs: aero1/aero3 as large tiles on a jittered grid, others as patches
    aer = [_load_photo(nm) for nm in _AERIAL]
    others = [_load_photo(nm) for nm in _PATCHES]
    grid_n = 4
    step = 2 * half / grid_n
    order = rng.permutation(grid_n * grid_n)
    for cell in order:
        gi, gj = divmod(int(cell), grid_n)
        centre = np.array([-half + (gj + 0.5) * step, -half + (gi + 0.5) * step])
        centre += rng.uniform(-0.2, 0.2, 2) * step
        img = aer[int(rng.integers(0, len(aer)))]
        if rng.uniform() < 0.5:
            img = np.ascontiguousarray(img[:, ::-1])
        m_per_px = rng.uniform(0.10, 0.14)
        _paste_photo(
            base,
            img,
            ((centre[0] + half) / TEXEL_M, (half - centre[1]) / TEXEL_M),
            m_per_px / TEXEL_M,
            float(rng.uniform(0, 360)),
            0.85,
            6.0 / TEXEL_M,
            rng.uniform(0.85, 1.12, 3),
        )
    for _ in range(36):
        if not others:
            break
        img = others[int(rng.integers(0, len(others)))]
        size_m = rng.uniform(6.0, 16.0)
        centre = rng.uniform(-0.9 * half, 0.9 * half, 2)
        _paste_photo(
            base,
            img,
            ((centre[0] + half) / TEXEL_M, (half - centre[1]) / TEXEL_M),
            size_m / TEXEL_M / max(img.shape[:2]),
            float(rng.uniform(0, 360)),
            0.9,
            1.0 / TEXEL_M,
            rng.uniform(0.8, 1.1, 3),
        )

    def to_t(p: F64) -> NDArray[np.int32]:  # metres -> texels with 2 fractional bits
        q = np.stack([(p[:, 0] + half) / TEXEL_M - 0.5, (half - p[:, 1]) / TEXEL_M - 0.5], 1)
        return np.round(q * 4).astype(np.int32)

    # ---- roads (verge + asphalt) and buildings, on top of the photographs
    roads = [_random_polyline(rng, half) for _ in range(3)]
    road_w = rng.uniform(5.0, 7.5, len(roads))
    for pl, wd in zip(roads, road_w, strict=True):
        cv2.polylines(
            base, [to_t(pl)], False, (120, 150, 160), int((wd + 2.0) / TEXEL_M), cv2.LINE_AA, 2
        )
    for pl, wd in zip(roads, road_w, strict=True):
        grey = float(rng.uniform(85, 110))
        cv2.polylines(
            base, [to_t(pl)], False, (grey, grey, grey + 4), int(wd / TEXEL_M), cv2.LINE_AA, 2
        )
    for _ in range(36):
        c = rng.uniform(-half, half, 2)
        sz = rng.uniform([5.0, 4.0], [14.0, 10.0])
        a = rng.uniform(0, math.pi)
        rm = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        box = (np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * sz / 2.0) @ rm.T + c
        cv2.fillPoly(base, [to_t(box + np.array([1.8, -1.8]))], (35, 45, 45), cv2.LINE_AA, 2)
        roof = [
            (60, 60, 150),
            (70, 80, 170),
            (150, 150, 150),
            (110, 110, 115),
            (180, 180, 185),
            (80, 110, 140),
        ][int(rng.integers(0, 6))]
        cv2.fillPoly(base, [to_t(box)], roof, cv2.LINE_AA, 2)
        ridge = np.array([[-1, 0], [1, 0]]) * sz / 2.0 @ rm.T + c
        dark = tuple(int(v * 0.7) for v in roof)
        cv2.polylines(base, [to_t(ridge)], False, dark, 6, cv2.LINE_AA, 2)

    # ---- fine detail everywhere: luminance modulation from value noise octaves
    mod = _value_noise(rng, n, n, 2.5 / TEXEL_M)
    mod *= 0.09
    mod += 0.07 * _value_noise(rng, n, n, 0.8 / TEXEL_M)
    mod += 0.05 * _value_noise(rng, n, n, 0.3 / TEXEL_M)
    mod += 0.04 * _value_noise(rng, n, n, 0.12 / TEXEL_M)
    mod += 1.0
    np.clip(mod, 0.45, 1.6, out=mod)
    chunk = 500
    for r0 in range(0, n, chunk):
        blk = base[r0 : r0 + chunk].astype(np.float32)
        blk *= mod[r0 : r0 + chunk, :, None]
        blk += 0.5
        np.clip(blk, 0, 255, out=blk)
        base[r0 : r0 + chunk] = blk.astype(np.uint8)
    del mod

    # ---- small objects: bushes, shrubs and stones (strong corners at every scale)
    n_obj = 5000
    px = rng.uniform(0, n, n_obj)
    py = rng.uniform(0, n, n_obj)
    rad = rng.uniform(0.15, 0.6, n_obj) / TEXEL_M
    kind = rng.uniform(0, 1, n_obj)
    jit = rng.uniform(-18, 18, (n_obj, 3))
    for i in range(n_obj):
        if kind[i] < 0.55:
            col = np.array([35.0, 75.0, 45.0]) + jit[i]  # bush
        elif kind[i] < 0.8:
            col = np.array([45.0, 60.0, 80.0]) + jit[i]  # dark soil / shadow
        else:
            col = np.array([185.0, 190.0, 195.0]) + jit[i]  # stone
        r = rad[i] if kind[i] < 0.8 else rad[i] * 0.35
        centre_q = (int(px[i] * 4), int(py[i] * 4))  # quarter texels (shift 2)
        if kind[i] < 0.9:
            cv2.circle(base, centre_q, max(int(r * 4), 4), col.tolist(), -1, cv2.LINE_AA, 2)
        else:
            half_side = max(r, 1.5)
            box = cv2.boxPoints(((px[i], py[i]), (2 * half_side, 1.4 * half_side), kind[i] * 900))
            cv2.fillPoly(base, [np.round(box * 4).astype(np.int32)], col.tolist(), cv2.LINE_AA, 2)

    # dashed centre lines on the roads
    for pl in roads:
        seg = np.diff(pl, axis=0)
        lens = np.hypot(seg[:, 0], seg[:, 1])
        s = np.concatenate([[0.0], np.cumsum(lens)])
        for s0 in np.arange(0.0, s[-1], 9.0):
            t = np.array([s0, s0 + 3.0])
            p = np.stack([np.interp(t, s, pl[:, 0]), np.interp(t, s, pl[:, 1])], 1)
            q = np.stack([(p[:, 0] + half) / TEXEL_M, (half - p[:, 1]) / TEXEL_M], 1)
            cv2.polylines(
                base, [np.round(q * 4).astype(np.int32)], False, (225, 230, 230), 3, cv2.LINE_AA, 2
            )

    # BGRA: OpenCV's 4-channel warps are about twice as fast as 3-channel ones
    # Half-octave pyramid: 0, 1, 2 ... by pyrDown (level-k texel j sits on level-0
    # texel 2**k * j); 0.5, 1.5 ... by an area resize of level 0 then pyrDown.
    full = cv2.cvtColor(base, cv2.COLOR_BGR2BGRA)
    del base
    hs = int(round(n / math.sqrt(2.0)))
    hsc = hs / n
    half_mat = np.array([[hsc, 0.0, 0.5 * hsc - 0.5], [0.0, hsc, 0.5 * hsc - 0.5], [0.0, 0.0, 1.0]])
    chains = [
        (full, np.eye(3)),
        (cv2.resize(full, (hs, hs), interpolation=cv2.INTER_AREA), half_mat),
    ]
    levels: list[U8] = []
    mats: list[F64] = []
    k = 0
    while min(chains[0][0].shape[:2]) > 64:
        for j, (img, mat) in enumerate(chains):
            levels.append(img)
            mats.append(np.diag([0.5**k, 0.5**k, 1.0]) @ mat)
            chains[j] = (cv2.pyrDown(img), mat)
        k += 1
    for lv in levels:
        lv.setflags(write=False)
    g0 = np.array(
        [
            [1.0 / TEXEL_M, 0.0, half / TEXEL_M - 0.5],
            [0.0, -1.0 / TEXEL_M, half / TEXEL_M - 0.5],
            [0.0, 0.0, 1.0],
        ]
    )
    return _Mosaic(tuple(levels), tuple(mats), g0)


@lru_cache(maxsize=2)
def _mosaic(seed: int = WORLD_SEED) -> _Mosaic:
    return _build_mosaic(seed)


def ground_mosaic() -> U8:
    """The level-0 ground texture (BGRA, row 0 = north edge, 0.05 m per texel, read-only).

    Texel (col, row) has its centre at x = -125 + (col + 0.5) * 0.05,
    y = 125 - (row + 0.5) * 0.05 (ENU metres).
    """
    return _mosaic().levels[0]


# --------------------------------------------------------------------------- trajectories


@dataclass
class _Plan:
    """A flight sampled on a dense uniform time grid (plus its events)."""

    name: str
    t0: float  # time of the first grid sample (s, frame time base)
    pos: F64  # (n, 3) ENU metres
    euler: F64  # (n, 3) roll, pitch, yaw (rad, NED, yaw unwrapped)
    mount_pitch_deg: float
    hover: list[tuple[float, float]]
    defocus: list[tuple[float, float, float]]  # t0, t1, sigma at 960 px width
    events: dict[str, Any] = field(default_factory=dict)

    def _idx(self, times: F64) -> tuple[NDArray[np.int64], F64]:
        x = (np.asarray(times, np.float64) - self.t0) / _DT
        i0 = np.clip(np.floor(x).astype(np.int64), 0, len(self.pos) - 2)
        return i0, (x - i0)[:, None]

    def sample(self, times: F64) -> tuple[F64, F64]:
        """Position (n, 3) and Euler angles (n, 3) at arbitrary times (linear interp)."""
        i0, f = self._idx(times)
        pos = self.pos[i0] * (1 - f) + self.pos[i0 + 1] * f
        eul = self.euler[i0] * (1 - f) + self.euler[i0 + 1] * f
        return pos, eul

    def rates(self, times: F64) -> tuple[F64, F64]:
        """NED velocity (m/s) and body rates p, q, r (rad/s) at ``times``."""
        i0, f = self._idx(times)
        vel_enu = (self.pos[i0 + 1] - self.pos[i0]) / _DT
        de = (self.euler[i0 + 1] - self.euler[i0]) / _DT
        eul = self.euler[i0] * (1 - f) + self.euler[i0 + 1] * f
        phi, th = eul[:, 0], eul[:, 1]
        p = de[:, 0] - de[:, 2] * np.sin(th)
        q = de[:, 1] * np.cos(phi) + de[:, 2] * np.sin(phi) * np.cos(th)
        r = -de[:, 1] * np.sin(phi) + de[:, 2] * np.cos(phi) * np.cos(th)
        vel_ned = np.stack([vel_enu[:, 1], vel_enu[:, 0], -vel_enu[:, 2]], 1)
        return vel_ned, np.stack([p, q, r], 1)

    def camera(self, times: F64) -> tuple[F64, F64, F64]:
        """Camera centres (n, 3), R_world_cam (n, 3, 3) ENU, R_ned_body (n, 3, 3)."""
        pos, eul = self.sample(times)
        r_nb = _euler_to_rotmat(eul[:, 0], eul[:, 1], eul[:, 2])
        r_wc = np.einsum("ij,njk,kl->nil", _T_ENU_NED, r_nb, _mount_rotation(self.mount_pitch_deg))
        return pos, r_wc, r_nb


def _smooth(x: F64, sigma_s: float) -> F64:
    """Gaussian low-pass along axis 0 of a signal on the _DT grid (edge-replicated)."""
    s = sigma_s / _DT
    half = int(4 * s)
    k = np.exp(-0.5 * (np.arange(-half, half + 1) / s) ** 2)
    k /= k.sum()
    out = np.empty_like(x)
    for c in range(x.shape[1]):
        xp = np.pad(x[:, c], half, mode="edge")
        out[:, c] = np.convolve(xp, k, mode="valid")
    return out


def _minjerk(tau: F64) -> F64:
    t = np.clip(tau, 0.0, 1.0)
    return t**3 * (10 - 15 * t + 6 * t * t)


def _attitude(
    pos: F64, yaw: F64, t: F64, rng: np.random.Generator, gusts: list[tuple[float, float, float]]
) -> F64:
    """Roll/pitch from smoothed horizontal acceleration, plus gusts and jitter."""
    vel = np.gradient(pos, _DT, axis=0)
    acc = _smooth(np.gradient(vel, _DT, axis=0), 0.35)
    a_n, a_e = acc[:, 1], acc[:, 0]
    a_fwd = a_n * np.cos(yaw) + a_e * np.sin(yaw)
    a_right = -a_n * np.sin(yaw) + a_e * np.cos(yaw)
    pitch = -np.arctan2(a_fwd, _G)
    roll = np.arctan2(a_right * np.cos(pitch), _G)
    yaw = yaw.copy()
    for tg, a_roll, a_pitch in gusts:
        env = np.exp(-(((t - tg) / 0.3) ** 2))
        ph = rng.uniform(0, 2 * math.pi, 2)
        roll += math.radians(a_roll) * env * np.sin(2 * math.pi * 3.0 * (t - tg) + ph[0])
        pitch += math.radians(a_pitch) * env * np.sin(2 * math.pi * 2.6 * (t - tg) + ph[1])
    for ang in (roll, pitch, yaw):
        ang += _jitter(rng, t, math.radians(0.08))
    return np.stack([roll, pitch, yaw], 1)


def _jitter(rng: np.random.Generator, t: F64, amp: float) -> F64:
    """Smooth small random wobble (sum of sinusoids), std ~ amp."""
    out = np.zeros_like(t)
    for _ in range(3):
        f = rng.uniform(0.2, 1.5)
        out += np.sin(2 * math.pi * f * t + rng.uniform(0, 2 * math.pi))
    return out * (amp / math.sqrt(1.5))


def _nadir_plan(seconds: float, seed: int) -> _Plan:
    """Lawnmower survey at 50 m, 8 m/s, legs 25 m apart, 4 s hover mid first leg."""
    rng = np.random.default_rng([seed, 1])
    alt, v_c, v_t, r_turn = 50.0, 8.0, 6.5, 12.5
    x0, y_s = -12.5, -56.0
    t = (
        np.arange(int(round((seconds + _PRE_S + _POST_S) / _DT)) + 1, dtype=np.float64) * _DT
        - _PRE_S
    )
    t_end = float(t[-1])

    # speed schedule: (t_start, duration, v0, v1) with cosine ramps between speeds
    phases: list[tuple[float, float, float, float]] = []

    def add(dur: float, v0: float, v1: float) -> None:
        start = phases[-1][0] + phases[-1][1] if phases else -_PRE_S
        phases.append((start, dur, v0, v1))

    ramp = 1.0
    d_ramp = (v_c + v_t) / 2 * ramp
    add(3.0 + _PRE_S, v_c, v_c)  # cruise until t = 3
    add(4.0, v_c, 0.0)  # decelerate
    add(5.0, 0.0, 0.0)  # stationary 7 .. 12; the hover flag excludes the 0.5 s settling
    add(4.0, 0.0, v_c)  # accelerate
    add(1.0, v_c, v_c)
    add(ramp, v_c, v_t)
    leg = sum((a + b) / 2 * d for _, d, a, b in phases)
    arc = math.pi * r_turn
    turns: list[tuple[float, float]] = []  # (arc start time, arc end time)
    while phases[-1][0] + phases[-1][1] < t_end:
        add(arc / v_t, v_t, v_t)
        turns.append((phases[-1][0], phases[-1][0] + phases[-1][1]))
        add(ramp, v_t, v_c)
        add((leg - 2 * d_ramp) / v_c, v_c, v_c)
        add(ramp, v_c, v_t)
    hover = (phases[2][0] + 0.5, phases[2][0] + phases[2][1] - 0.5)  # level and still

    s = np.zeros_like(t)
    s_acc = 0.0
    for start, dur, v0, v1 in phases:
        m = (t >= start) & (t <= start + dur)  # later phases overwrite shared ends
        tau = t[m] - start
        s[m] = (
            s_acc + v0 * tau + (v1 - v0) / 2 * (tau - dur / math.pi * np.sin(math.pi * tau / dur))
        )
        s_acc += (v0 + v1) / 2 * dur
    period = leg + arc
    k = np.floor(s / period)
    u = s - k * period
    even = (k % 2) == 0
    on_leg = u < leg
    xl = x0 + k * 2 * r_turn
    y_n = y_s + leg
    x = np.where(on_leg, xl, 0.0)
    y = np.where(on_leg, np.where(even, y_s + u, y_n - u), 0.0)
    a = np.maximum(u - leg, 0.0) / r_turn
    alpha = np.where(even, math.pi - a, math.pi + a)
    x = np.where(on_leg, x, xl + r_turn + r_turn * np.cos(alpha))
    y = np.where(on_leg, y, np.where(even, y_n, y_s) + r_turn * np.sin(alpha))
    pos = np.stack([x, y, np.full_like(x, alt)], 1)

    # heading: north on even legs, south on odd legs; a fast 180 deg snap mid-turn
    yaw = np.zeros_like(t)
    snap = 1.6
    snaps = []
    for i, (ta, tb) in enumerate(turns):
        tc = (ta + tb) / 2
        snaps.append(tc)
        sign = 1.0 if i % 2 == 0 else -1.0
        yaw += sign * math.pi * _minjerk((t - tc) / snap + 0.5)

    gust_t = [14.5 + rng.uniform(-0.3, 0.3)]
    gust_t += [27.0 + 14.0 * i + rng.uniform(-0.5, 0.5) for i in range(8)]
    gusts = [(g, 7.0 * rng.uniform(0.9, 1.1), 4.0 * rng.uniform(0.9, 1.1)) for g in gust_t]
    euler = _attitude(pos, yaw, t, rng, gusts)
    pos = pos + np.stack([_jitter(rng, t, 0.02) for _ in range(3)], 1)

    d0 = 4.0 + rng.uniform(-0.2, 0.2)
    defocus = [(d0, d0 + 0.7, DEFOCUS_SIGMA_AT_960)]
    for i in range(8):
        d = 25.0 + 13.0 * i + rng.uniform(-0.3, 0.3)
        defocus.append((d, d + 0.7, DEFOCUS_SIGMA_AT_960))
    events = {
        "yaw_snaps_t": [round(v, 3) for v in snaps],
        "gusts_t": [round(g[0], 3) for g in gusts],
        "turns_t": [[round(a, 3), round(b, 3)] for a, b in turns],
        "altitude_m": alt,
        "cruise_speed_mps": v_c,
        "leg_spacing_m": 2 * r_turn,
    }
    return _Plan("nadir", float(t[0]), pos, euler, -90.0, [hover], defocus, events)


def _orbit_plan(seconds: float, seed: int) -> _Plan:
    """Orbit at 30 m radius, 35 m height, 6 m/s, nose (and camera) along the track.

    A fixed forward camera pitched 55 degrees down, as on a Bebop-class drone: the
    oblique view sweeps round the circle. (Pointing at the centre instead would
    keep every pair of frames above ~0.72 overlap, which tests nothing.)
    """
    rng = np.random.default_rng([seed, 2])
    radius, alt, speed = 30.0, 35.0, 6.0
    t = (
        np.arange(int(round((seconds + _PRE_S + _POST_S) / _DT)) + 1, dtype=np.float64) * _DT
        - _PRE_S
    )
    omega = speed / radius
    alpha = math.radians(-110.0) + omega * t
    pos = np.stack([radius * np.cos(alpha), radius * np.sin(alpha), np.full_like(t, alt)], 1)
    # Heading = direction of travel (east, north) = (-sin a, cos a); yaw from north.
    yaw = np.unwrap(np.arctan2(-np.sin(alpha), np.cos(alpha)))
    mount = -55.0  # the turn banks the vehicle (roll); pitch stays near level
    gust_t = [9.0 + 8.5 * i + rng.uniform(-0.4, 0.4) for i in range(16)]
    gusts = [(g, 5.0 * rng.uniform(0.9, 1.1), 1.5 * rng.uniform(0.9, 1.1)) for g in gust_t]
    euler = _attitude(pos, yaw, t, rng, gusts)
    pos = pos + np.stack([_jitter(rng, t, 0.02) for _ in range(3)], 1)
    defocus = []
    for i in range(16):
        d = 5.0 + 9.0 * i + rng.uniform(-0.3, 0.3)
        defocus.append((d, d + 0.7, DEFOCUS_SIGMA_AT_960))
    events = {
        "gusts_t": [round(g[0], 3) for g in gusts],
        "orbit_radius_m": radius,
        "altitude_m": alt,
        "speed_mps": speed,
        "centre_enu": [0.0, 0.0],
    }
    return _Plan("orbit", float(t[0]), pos, euler, mount, [], defocus, events)


def default_seconds(flight: str) -> float:
    """Default duration of a named flight (s)."""
    if flight not in _DEFAULT_SECONDS:
        raise ValueError(f"unknown flight {flight!r} (choose from {', '.join(FLIGHTS)})")
    return _DEFAULT_SECONDS[flight]


def _plan(flight: str, seconds: float, seed: int) -> _Plan:
    if flight == "nadir":
        return _nadir_plan(seconds, seed)
    if flight == "orbit":
        return _orbit_plan(seconds, seed)
    raise ValueError(f"unknown flight {flight!r} (choose from {', '.join(FLIGHTS)})")


# --------------------------------------------------------------------------- rendering


def _level_map(m0: F64, width: int, height: int, nlev: int) -> F32:
    """Per-pixel mip level index (half octaves) for the image -> level-0 texel map ``m0``.

    The footprint is 0.75 * log2(major axis) + 0.25 * log2(minor axis) of the pixel's
    texel-space Jacobian: a compromise between aliasing and blur for oblique views.
    """
    step = 16
    nx = int(math.ceil(width / step)) + 1
    ny = int(math.ceil(height / step)) + 1
    u = (np.arange(nx) + 0.5) * (width / nx) - 0.5
    v = (np.arange(ny) + 0.5) * (height / ny) - 0.5
    uu, vv = np.meshgrid(u, v)
    w = m0[2, 0] * uu + m0[2, 1] * vv + m0[2, 2]
    x = (m0[0, 0] * uu + m0[0, 1] * vv + m0[0, 2]) / w
    y = (m0[1, 0] * uu + m0[1, 1] * vv + m0[1, 2]) / w
    a = (m0[0, 0] - x * m0[2, 0]) / w
    b = (m0[0, 1] - x * m0[2, 1]) / w
    c = (m0[1, 0] - y * m0[2, 0]) / w
    d = (m0[1, 1] - y * m0[2, 1]) / w
    p = (a * a + b * b + c * c + d * d) / 2
    det = np.abs(a * d - b * c)
    qq = np.sqrt(np.maximum(p * p - det * det, 0.0))
    smax = np.sqrt(p + qq)
    smin = np.sqrt(np.maximum(p - qq, 1e-12))
    lod = 1.5 * np.log2(np.maximum(smax, 1e-6)) + 0.5 * np.log2(np.maximum(smin, 1e-6))
    lod = np.clip(lod, 0.0, nlev - 1).astype(np.float32)
    return np.asarray(cv2.resize(lod, (width, height), interpolation=cv2.INTER_LINEAR), np.float32)


def _warp_level(mosaic: _Mosaic, k: int, m0: F64, width: int, r0: int, r1: int) -> U8:
    """Rows r0..r1 of the view of pyramid level k (m0: image -> level-0 texel)."""
    sk = mosaic.level_mats[k]
    shift = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, r0], [0.0, 0.0, 1.0]])
    view = cv2.warpPerspective(
        mosaic.levels[k],
        sk @ m0 @ shift,
        (width, r1 - r0),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REFLECT101,
    )
    return np.asarray(view, np.uint8)


def _render(mosaic: _Mosaic, h_gi: F64, lod: F32) -> U8:
    """The view through image->ground homography ``h_gi`` (BGRA, trilinear mip-mapping)."""
    height, width = lod.shape
    m0 = mosaic.ground_to_tex0 @ h_gi
    lmin, lmax = float(lod.min()), float(lod.max())
    if lmax - lmin < 0.6:
        # nearly uniform scale (nadir-like views): the nearest half-octave level alone
        # is within 2**0.4 of the ideal filter everywhere
        k0 = min(int(round((lmin + lmax) / 2.0)), len(mosaic.levels) - 1)
        return _warp_level(mosaic, k0, m0, width, 0, height)
    k_lo = int(math.floor(lmin))
    k_hi = min(max(int(math.ceil(lmax)), k_lo + 1), len(mosaic.levels) - 1)
    row_min = lod.min(axis=1)
    row_max = lod.max(axis=1)
    warps: dict[int, tuple[int, U8]] = {}
    for k in range(k_lo, k_hi + 1):  # each level once, over the rows that use it
        rows = np.nonzero((row_max >= k - 1) & (row_min <= k + 1))[0]
        if rows.size:
            r0, r1 = int(rows[0]), int(rows[-1]) + 1
            warps[k] = (r0, _warp_level(mosaic, k, m0, width, r0, r1))
    out = np.empty((height, width, 4), np.uint8)
    for k in range(k_lo, k_hi):
        rows = np.nonzero((row_max >= k) & (row_min <= k + 1))[0]
        if rows.size == 0:
            continue
        r0, r1 = int(rows[0]), int(rows[-1]) + 1
        a0, wa = warps[k]
        b0, wb = warps[k + 1]
        f = np.clip(lod[r0:r1] - k, 0.0, 1.0)
        blend = cv2.blendLinear(wa[r0 - a0 : r1 - a0], wb[r0 - b0 : r1 - b0], 1.0 - f, f)
        if k == k_lo:
            out[r0:r1] = blend
        else:
            np.copyto(out[r0:r1], blend, where=(lod[r0:r1] >= k)[:, :, None])
    return out


# --------------------------------------------------------------------------- generation


@dataclass(frozen=True)
class FlightInfo:
    """What :func:`generate` wrote."""

    flight: str
    out_dir: Path
    video: Path
    groundtruth: Path
    intrinsics: Path
    calibration: Path
    tlog: Path
    meta: Path
    frames: int
    width: int
    height: int
    fps: float
    seconds: float
    blurry_frames: int
    hover_frames: int
    elapsed_s: float


@dataclass
class _Truth:
    t: F64
    pos: F64
    r_wc: F64
    euler: F64
    blur_px: F64
    sigma: F64
    hover: NDArray[np.bool_]
    nsub: NDArray[np.int64]


def _frame_truth(
    plan: _Plan, n: int, fps: float, width: int, height: int, exposure_s: float
) -> _Truth:
    k = intrinsics_matrix(width, height)
    t = np.arange(n, dtype=np.float64) / fps
    pos, r_wc, _ = plan.camera(t)
    _, eul = plan.sample(t)
    h_ig = _ground_to_image(k, r_wc, pos)
    h_gi = np.linalg.inv(h_ig)
    pts = np.array(
        [
            [-0.5, -0.5],
            [width - 0.5, -0.5],
            [width - 0.5, height - 0.5],
            [-0.5, height - 0.5],
            [(width - 1) / 2.0, (height - 1) / 2.0],
        ]
    )
    ph = np.concatenate([pts, np.ones((5, 1))], 1)
    g = np.einsum("nij,pj->npi", h_gi, ph)  # (n, 5, 3) ground points (homogeneous)
    if np.any(g[:, :, 2] <= 0.0):
        bad = int(np.nonzero((g[:, :, 2] <= 0.0).any(axis=1))[0][0])
        raise ValueError(f"frame {bad} of {plan.name!r} sees above the horizon")
    gxy = g[:, :, :2] / g[:, :, 2:]
    lim = WORLD_HALF_M - _GROUND_MARGIN_M
    if np.abs(gxy).max() > lim:
        bad = int(np.nonzero((np.abs(gxy) > lim).any(axis=(1, 2)))[0][0])
        raise ValueError(
            f"{plan.name!r} leaves the textured ground at frame {bad} "
            f"(t = {bad / fps:.2f} s): use a shorter duration"
        )
    # motion-blur extent: path length of the 5 ground points' images over the exposure
    m = 9
    off = (np.arange(m) / (m - 1) - 0.5) * exposure_s
    tt = (t[:, None] + off[None, :]).ravel()
    pos_s, r_s, _ = plan.camera(tt)
    h_s = _ground_to_image(k, r_s, pos_s).reshape(n, m, 3, 3)
    gh = np.concatenate([gxy, np.ones((n, 5, 1))], 2)
    img = np.einsum("nmij,npj->nmpi", h_s, gh)
    uv = img[..., :2] / img[..., 2:]
    path = np.linalg.norm(np.diff(uv, axis=1), axis=-1).sum(axis=1)  # (n, 5)
    blur = path.max(axis=1)
    # sub-frames at most 0.5 px apart; none below 1 px of motion (cheap, visually exact)
    nsub = np.clip(np.ceil(blur / 0.5) + 1, 1, 64).astype(np.int64)
    nsub[blur < 1.0] = 1
    sigma: F64 = np.zeros(n)
    scale = width / 960.0
    ramp = 0.1
    for d0, d1, s in plan.defocus:
        prof = np.clip(np.minimum(t - d0, d1 - t) / ramp, 0.0, 1.0)
        sigma = np.maximum(sigma, s * scale * prof)
    hover = np.zeros(n, dtype=bool)
    for h0, h1 in plan.hover:
        hover |= (t >= h0) & (t < h1)
    return _Truth(t, pos, r_wc, eul, blur, sigma, hover, nsub)


class _Writer:
    """MJPG writer on a background thread (encoding overlaps rendering). Refuses (a
    ValueError from write) a video that would outgrow AVI_MAX_BYTES: as soon as its
    first second says the whole would, or once it does."""

    def __init__(self, path: Path, fps: float, size: tuple[int, int], frames: int) -> None:
        self._vw = cv2.VideoWriter(
            str(path),
            cv2.CAP_OPENCV_MJPEG,
            cv2.VideoWriter.fourcc(*"MJPG"),
            fps,
            size,
            [cv2.VIDEOWRITER_PROP_QUALITY, MJPG_QUALITY],
        )
        if not self._vw.isOpened():
            raise RuntimeError(f"cannot open {path} for writing")
        self._path, self._fps, self._size, self._frames = path, fps, size, frames
        self._written = 0
        self._too_large: str | None = None
        self._q: queue.Queue[U8 | None] = queue.Queue(maxsize=6)
        self._err: BaseException | None = None
        self._th = threading.Thread(target=self._run, name="synth-writer", daemon=True)
        self._th.start()

    def _run(self) -> None:
        check_at = max(1, int(round(self._fps)))  # the first second, then every 16 frames
        while True:
            f = self._q.get()
            if f is None:
                break
            if self._too_large is not None or self._err is not None:
                continue  # drained, not written: write() says why
            try:
                self._vw.write(f)
                self._written += 1
                if self._written == check_at or (
                    self._written > check_at and self._written % 16 == 0
                ):
                    self._check_size(first=self._written == check_at)
            except BaseException as e:  # re-raised in the caller's thread
                self._err = e

    def _check_size(self, first: bool) -> None:
        size = self._path.stat().st_size
        estimate = size * self._frames / self._written
        # the first second's rate is a guess (blur and texture change a frame's size):
        # refused then only when well over
        if (first and estimate > 1.25 * AVI_MAX_BYTES) or size > AVI_MAX_BYTES:
            fit = AVI_MAX_BYTES / (size / self._written) / self._fps
            w, h = self._size
            self._too_large = (
                f"the video would be about {estimate / 1e9:.1f} GB, more than the "
                f"{AVI_MAX_BYTES / 1e9:.1f} GB OpenCV's AVI writer can hold: fly fewer "
                f"seconds (about {fit:.0f} s fit at {w}x{h}) or a smaller image"
            )

    def write(self, frame: U8) -> None:
        if self._err is not None:
            raise RuntimeError("video writer failed") from self._err
        if self._too_large is not None:
            raise ValueError(self._too_large)
        self._q.put(frame)

    def close(self) -> None:
        self._q.put(None)
        self._th.join()
        self._vw.release()
        if self._err is not None:
            raise RuntimeError("video writer failed") from self._err


def _render_video(
    path: Path,
    plan: _Plan,
    truth: _Truth,
    width: int,
    height: int,
    fps: float,
    exposure_s: float,
    seed: int,
) -> None:
    mosaic = _mosaic()
    k = intrinsics_matrix(width, height)
    nlev = len(mosaic.levels)
    rng = np.random.default_rng([seed, 3])
    pad = 32
    bank = []
    for _ in range(3):
        nz = np.rint(rng.standard_normal((height + pad, width + pad, 3)) * NOISE_SIGMA_DN)
        bank.append((np.clip(nz, 0, 255).astype(np.uint8), np.clip(-nz, 0, 255).astype(np.uint8)))
    writer = _Writer(path, fps, (width, height), len(truth.t))
    try:
        for i in range(len(truth.t)):
            nsub = int(truth.nsub[i])
            p_mid, r_mid, _ = plan.camera(truth.t[i : i + 1])
            h_ig_mid = _ground_to_image(k, r_mid, p_mid)[0]
            h_gi_mid = np.linalg.inv(h_ig_mid)
            if nsub == 1:
                lod = _level_map(mosaic.ground_to_tex0 @ h_gi_mid, width, height, nlev)
                bgra = _render(mosaic, h_gi_mid, lod)
            else:
                # Render the mid-exposure view once on a canvas with a margin, then
                # average its exact plane-induced warps to the sub-frame poses.
                pad_px = int(math.ceil(0.6 * float(truth.blur_px[i]))) + 4
                shift = np.array([[1.0, 0.0, -pad_px], [0.0, 1.0, -pad_px], [0.0, 0.0, 1.0]])
                h_canvas = h_gi_mid @ shift  # canvas pixel -> ground
                cw, ch = width + 2 * pad_px, height + 2 * pad_px
                lod = _level_map(mosaic.ground_to_tex0 @ h_canvas, cw, ch, nlev)
                canvas = _render(mosaic, h_canvas, lod)
                ts = truth.t[i] + exposure_s * ((np.arange(nsub) + 0.5) / nsub - 0.5)
                pos, r_wc, _ = plan.camera(ts)
                h_gi = np.linalg.inv(_ground_to_image(k, r_wc, pos))
                to_canvas = np.linalg.inv(shift) @ h_ig_mid
                acc = np.zeros((height, width, 4), np.float32)
                for h in h_gi:
                    sub = cv2.warpPerspective(
                        canvas,
                        to_canvas @ h,
                        (width, height),
                        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                        borderMode=cv2.BORDER_REFLECT101,
                    )
                    cv2.accumulate(sub, acc)
                bgra = np.asarray(cv2.convertScaleAbs(acc, alpha=1.0 / nsub), np.uint8)
            img = cv2.cvtColor(bgra, cv2.COLOR_BGRA2BGR)
            if truth.sigma[i] > 0.05:
                img = cv2.GaussianBlur(img, (0, 0), float(truth.sigma[i]))
            fr = np.random.default_rng([seed, 4, i])
            pos_n, neg_n = bank[int(fr.integers(0, len(bank)))]
            dy, dx = (int(v) for v in fr.integers(0, pad, 2))
            img = cv2.add(img, pos_n[dy : dy + height, dx : dx + width])
            img = cv2.subtract(img, neg_n[dy : dy + height, dx : dx + width])
            writer.write(np.asarray(img, np.uint8))
    finally:
        writer.close()
    cap = cv2.VideoCapture(str(path))
    try:
        count = int(round(cap.get(cv2.CAP_PROP_FRAME_COUNT)))
        ok, first = cap.read()
    finally:
        cap.release()
    if not ok or first is None or first.shape != (height, width, 3) or count != len(truth.t):
        raise RuntimeError(f"{path} does not read back ({count} frames, expected {len(truth.t)})")


def _write_groundtruth(path: Path, truth: _Truth) -> None:
    q = _rotmat_to_quat(truth.r_wc)
    lat, lon, alt = enu_to_geodetic(truth.pos[:, 0], truth.pos[:, 1], truth.pos[:, 2])
    roll = np.degrees(truth.euler[:, 0])
    pitch = np.degrees(truth.euler[:, 1])
    yaw = np.mod(np.degrees(truth.euler[:, 2]), 360.0)
    blurry = (truth.blur_px > BLUR_PX_THRESHOLD) | (truth.sigma > DEFOCUS_SIGMA_THRESHOLD)
    with path.open("w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(GT_COLUMNS)
        for i in range(len(truth.t)):
            w.writerow(
                [
                    i,
                    f"{truth.t[i]:.9f}",
                    *(f"{v:.6f}" for v in truth.pos[i]),
                    *(f"{v:.9f}" for v in q[i]),
                    f"{roll[i]:.6f}",
                    f"{pitch[i]:.6f}",
                    f"{yaw[i]:.6f}",
                    f"{lat[i]:.9f}",
                    f"{lon[i]:.9f}",
                    f"{alt[i]:.4f}",
                    f"{truth.blur_px[i]:.4f}",
                    f"{truth.sigma[i]:.4f}",
                    int(blurry[i]),
                    int(truth.hover[i]),
                ]
            )


def _write_intrinsics(
    path: Path, width: int, height: int, fps: float, exposure_s: float, mount: float
) -> None:
    k = intrinsics_matrix(width, height)
    sw = SENSOR_WIDTH_MM
    doc = {
        "width": width,
        "height": height,
        "fx": k[0, 0],
        "fy": k[1, 1],
        "cx": k[0, 2],
        "cy": k[1, 2],
        "distortion": [0.0, 0.0, 0.0, 0.0, 0.0],
        "model": "pinhole",
        "pixel_center": "opencv (centre of pixel (0,0) at (0,0))",
        "hfov_deg": HFOV_DEG,
        "sensor_width_mm": sw,
        "sensor_height_mm": sw * height / width,
        "focal_length_mm": k[0, 0] * sw / width,
        "focal_length_35mm": k[0, 0] * 36.0 / width,
        "fps": fps,
        "exposure_s": exposure_s,
        "mount_pitch_deg": mount,
        "mount": "R_body_cam = Ry(mount_pitch) * [[0,0,1],[1,0,0],[0,1,0]] (body FRD)",
    }
    path.write_text(json.dumps(doc, indent=2) + "\n")


def _write_calibration(path: Path, width: int, height: int) -> None:
    """The same camera as an OpenCV FileStorage YAML, as cv::calibrateCamera samples
    write it (camera_matrix, distortion_coefficients, image_width/height) plus the
    sensor and focal length in mm, so the daemon reads it like a real calibration."""
    k = intrinsics_matrix(width, height)
    sw = SENSOR_WIDTH_MM
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    try:
        fs.write("image_width", width)
        fs.write("image_height", height)
        fs.write("camera_matrix", k)
        fs.write("distortion_coefficients", np.zeros((1, 5)))
        fs.write("sensor_width_mm", sw)
        fs.write("sensor_height_mm", sw * height / width)
        fs.write("focal_length_mm", float(k[0, 0] * sw / width))
        fs.write("make", "keyframed")
        fs.write("model", "synth")
    finally:
        fs.release()


def _ranges(mask: NDArray[np.bool_]) -> list[list[int]]:
    """Inclusive [first, last] index ranges of the True runs in ``mask``."""
    out: list[list[int]] = []
    idx = np.nonzero(mask)[0]
    if idx.size == 0:
        return out
    breaks = np.nonzero(np.diff(idx) > 1)[0]
    starts = np.concatenate([[idx[0]], idx[breaks + 1]])
    ends = np.concatenate([idx[breaks], [idx[-1]]])
    return [[int(a), int(b)] for a, b in zip(starts, ends, strict=True)]


def _write_tlog(path: Path, plan: _Plan, n_frames: int, fps: float) -> None:
    from pymavlink.dialects.v20 import common as mav2

    class _Sink:
        def __init__(self) -> None:
            self.buf = b""

        def write(self, b: bytes) -> None:
            self.buf = bytes(b)

    sink = _Sink()
    mav = mav2.MAVLink(sink, srcSystem=1, srcComponent=1)
    t_last = (n_frames - 1) / fps
    t_end = t_last + 1.0

    def times(rate: float) -> F64:
        k0 = math.ceil(-_PRE_S * rate - 1e-9)
        k1 = math.floor(t_end * rate + 1e-9)
        return np.arange(k0, k1 + 1) / rate

    custom_mode = 3 if plan.name == "nadir" else 7  # ArduCopter AUTO / CIRCLE
    records: list[tuple[float, int, bytes]] = []

    def emit(t: float, order: int, msg: Any) -> None:
        mav.send(msg)
        records.append((t, order, sink.buf))

    def boot_ms(t: float) -> int:
        return BOOT_MS_AT_FRAME0 + int(round(t * 1000.0))

    def unix_us(t: float) -> int:
        return EPOCH_UNIX_S * 1_000_000 + int(round(t * 1e6))

    # build the messages in time order so that sequence numbers increase with time
    items: list[tuple[float, int, str]] = []
    for name, rate, order in (
        ("HEARTBEAT", 1.0, 0),
        ("SYSTEM_TIME", 1.0, 1),
        ("ATTITUDE", 50.0, 2),
        ("ATTITUDE_QUATERNION", 50.0, 3),
        ("GLOBAL_POSITION_INT", 10.0, 4),
        ("GPS_RAW_INT", 5.0, 5),
    ):
        items += [(float(t), order, name) for t in times(rate)]
    items.sort(key=lambda it: (it[0], it[1]))
    ts = np.array([it[0] for it in items])
    pos, eul = plan.sample(ts)
    vel, rates = plan.rates(ts)
    r_nb = _euler_to_rotmat(eul[:, 0], eul[:, 1], eul[:, 2])
    q_nb = _rotmat_to_quat(r_nb)
    lat, lon, alt = enu_to_geodetic(pos[:, 0], pos[:, 1], pos[:, 2])
    base_mode = 1 | 4 | 8 | 16 | 128  # custom, guided, auto, stabilize, armed
    for idx, (t, order, name) in enumerate(items):
        roll, pitch = float(eul[idx, 0]), float(eul[idx, 1])
        yaw_w = (float(eul[idx, 2]) + math.pi) % (2 * math.pi) - math.pi
        hdg = int(round(math.degrees(float(eul[idx, 2])) * 100.0)) % 36000
        p, q, r = (float(v) for v in rates[idx])
        lat_i = int(round(float(lat[idx]) * 1e7))
        lon_i = int(round(float(lon[idx]) * 1e7))
        alt_mm = int(round(float(alt[idx]) * 1000.0))
        if name == "HEARTBEAT":
            msg = mav.heartbeat_encode(2, 3, base_mode, custom_mode, 4, 3)
        elif name == "SYSTEM_TIME":
            msg = mav.system_time_encode(unix_us(t), boot_ms(t))
        elif name == "ATTITUDE":
            msg = mav.attitude_encode(boot_ms(t), roll, pitch, yaw_w, p, q, r)
        elif name == "ATTITUDE_QUATERNION":
            qw, qx, qy, qz = (float(v) for v in q_nb[idx])
            msg = mav.attitude_quaternion_encode(boot_ms(t), qw, qx, qy, qz, p, q, r)
        elif name == "GLOBAL_POSITION_INT":
            vn_cm, ve_cm, vd_cm = (int(round(float(v) * 100.0)) for v in vel[idx])
            rel = int(round(float(pos[idx, 2]) * 1000.0))
            msg = mav.global_position_int_encode(
                boot_ms(t), lat_i, lon_i, alt_mm, rel, vn_cm, ve_cm, vd_cm, hdg
            )
        else:
            vn, ve = float(vel[idx, 0]), float(vel[idx, 1])
            gs = math.hypot(vn, ve)
            cog = int(round(math.degrees(math.atan2(ve, vn)) * 100.0)) % 36000
            msg = mav.gps_raw_int_encode(
                unix_us(t),
                3,
                lat_i,
                lon_i,
                alt_mm,
                80,
                120,
                int(round(gs * 100.0)),
                cog if gs > 0.3 else 65535,
                14,
                alt_mm + int(GEOID_SEPARATION_M * 1000),
                800,
                1200,
                150,
                0,
                0,
            )
        emit(t, order, msg)
    with path.open("wb") as fh:
        for t, _, buf in records:
            fh.write(struct.pack(">Q", unix_us(t)))
            fh.write(buf)


def _events_within(events: dict[str, Any], secs: float) -> dict[str, Any]:
    """Drop event times (keys ending in ``_t``) that fall outside the video."""
    out: dict[str, Any] = {}
    for key, val in events.items():
        if key.endswith("_t") and isinstance(val, list):
            val = [v for v in val if 0.0 <= (v[0] if isinstance(v, list) else v) <= secs]
        out[key] = val
    return out


def generate(
    flight: str,
    out_dir: Path,
    *,
    width: int = 960,
    height: int = 540,
    fps: float = 30.0,
    seconds: float | None = None,
    seed: int = 0,
    exposure_s: float = DEFAULT_EXPOSURE_S,
) -> FlightInfo:
    """Render flight ``flight`` ('nadir' or 'orbit') into ``out_dir`` with its ground truth.

    ``seconds`` defaults to :func:`default_seconds` (nadir 30 s, orbit 20 s). A
    shortened nadir flight keeps its structure from the start: cruise 0-3 s,
    deceleration 3-7 s, stationary 7-12 s (hover flag 7.5-11.5 s, once the
    attitude has settled), acceleration 12-16 s, turn 18-24 s. Raises
    ValueError for bad arguments (including durations that would leave the textured
    ground or views that would see the horizon).
    """
    t_start = time.perf_counter()
    if flight not in FLIGHTS:
        raise ValueError(f"unknown flight {flight!r} (choose from {', '.join(FLIGHTS)})")
    if not (16 <= width <= 8192 and 16 <= height <= 8192) or width % 2 or height % 2:
        raise ValueError(f"bad image size {width}x{height} (even, 16..8192)")
    if not (math.isfinite(fps) and 1.0 <= fps <= 240.0):
        raise ValueError(f"bad fps {fps} (1..240)")
    secs = default_seconds(flight) if seconds is None else float(seconds)
    if not (math.isfinite(secs) and secs > 0.0):
        raise ValueError(f"bad duration {seconds} s")
    if not (math.isfinite(exposure_s) and 0.0 < exposure_s <= 1.0 / fps):
        raise ValueError(f"bad exposure {exposure_s} s (0 .. 1/fps)")
    n = int(round(secs * fps))
    if n < 1:
        raise ValueError(f"duration {secs} s gives no frames at {fps} fps")
    if n > 20000:
        raise ValueError(f"too many frames ({n})")

    plan = _plan(flight, secs, seed)
    truth = _frame_truth(plan, n, fps, width, height, exposure_s)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {
        "video": out / "video.avi",
        "groundtruth": out / "groundtruth.csv",
        "intrinsics": out / "intrinsics.json",
        "calibration": out / "calibration.yaml",
        "tlog": out / "flight.tlog",
        "meta": out / "meta.json",
    }
    _write_groundtruth(paths["groundtruth"], truth)
    _write_intrinsics(paths["intrinsics"], width, height, fps, exposure_s, plan.mount_pitch_deg)
    _write_calibration(paths["calibration"], width, height)
    _write_tlog(paths["tlog"], plan, n, fps)
    _render_video(paths["video"], plan, truth, width, height, fps, exposure_s, seed)

    blurry = (truth.blur_px > BLUR_PX_THRESHOLD) | (truth.sigma > DEFOCUS_SIGMA_THRESHOLD)
    defocus = []
    for d0, d1, s in plan.defocus:
        m = (truth.t > d0) & (truth.t < d1)
        if m.any():
            idx = np.nonzero(m)[0]
            defocus.append(
                {
                    "t0": round(d0, 4),
                    "t1": round(d1, 4),
                    "sigma_px": round(s * width / 960.0, 4),
                    "frames": [int(idx[0]), int(idx[-1])],
                }
            )
    meta = {
        "flight": flight,
        "seed": seed,
        "world_seed": WORLD_SEED,
        "fps": fps,
        "frames": n,
        "seconds": secs,
        "width": width,
        "height": height,
        "exposure_s": exposure_s,
        "frame_time": "t = index / fps is the mid-exposure time",
        "epoch_unix_s": EPOCH_UNIX_S,
        "epoch_utc": datetime.fromtimestamp(EPOCH_UNIX_S, UTC).isoformat(),
        "time_boot_ms_at_frame0": BOOT_MS_AT_FRAME0,
        "origin": {
            "lat": ORIGIN_LAT,
            "lon": ORIGIN_LON,
            "ground_alt_amsl_m": GROUND_ALT_AMSL_M,
            "frame": "ENU metres; z above the ground plane",
            "geodetic": "local flat earth: WGS84 radii of curvature at the origin",
        },
        "ground": {
            "texel_m": TEXEL_M,
            "extent_m": [-WORLD_HALF_M, WORLD_HALF_M, -WORLD_HALF_M, WORLD_HALF_M],
        },
        "mount_pitch_deg": plan.mount_pitch_deg,
        "hover_frames": _ranges(truth.hover),
        "defocus": defocus,
        "blurry_frames": _ranges(blurry),
        "blurry_count": int(blurry.sum()),
        "blur_rule": "blur_px > 2.0 or defocus_sigma > 1.0",
        "events": _events_within(plan.events, secs),
    }
    paths["meta"].write_text(json.dumps(meta, indent=2) + "\n")
    return FlightInfo(
        flight=flight,
        out_dir=out,
        frames=n,
        width=width,
        height=height,
        fps=fps,
        seconds=secs,
        blurry_frames=int(blurry.sum()),
        hover_frames=int(truth.hover.sum()),
        elapsed_s=time.perf_counter() - t_start,
        **paths,
    )


# --------------------------------------------------------------------------- loading


@dataclass
class Flight:
    """Ground truth of a generated flight (see :func:`load_flight`)."""

    path: Path
    width: int
    height: int
    fps: float
    K: F64  # 3x3 camera matrix
    t: F64  # (n,) frame times, s
    positions: F64  # (n, 3) camera centres, ENU m
    quaternions: F64  # (n, 4) camera-to-world w, x, y, z
    rotations: F64  # (n, 3, 3) camera-to-world (columns: camera x, y, z in ENU)
    euler_deg: F64  # (n, 3) vehicle roll, pitch, yaw (NED, deg)
    geodetic: F64  # (n, 3) lat, lon (deg), alt (m AMSL)
    blur_px: F64
    defocus_sigma: F64
    blurry: NDArray[np.bool_]
    hover: NDArray[np.bool_]
    intrinsics: dict[str, Any]

    def __len__(self) -> int:
        return len(self.t)

    def ground_to_image(self, i: int) -> F64:
        """Homography ground (X, Y, 1) -> image i (u, v, 1), w = depth in camera i."""
        return _ground_to_image(self.K, self.rotations[i : i + 1], self.positions[i : i + 1])[0]

    def image_to_ground(self, i: int) -> F64:
        return np.asarray(np.linalg.inv(self.ground_to_image(i)), np.float64)

    def homography(self, i: int, j: int) -> F64:
        """Plane-induced homography image i -> image j (w > 0 in front of camera j)."""
        return self.ground_to_image(j) @ self.image_to_ground(i)

    def footprint(self, i: int) -> F64:
        """Ground (ENU x, y) of frame i's image corners, (4, 2)."""
        pts, _ = _apply_h(self.image_to_ground(i), _rect(self.width, self.height))
        return pts

    def overlap(self, i: int, j: int) -> float:
        """Fraction of frame i's image area whose ground is visible in frame j (0..1).

        Exact for the planar ground: area(rect_i ∩ H_{j->i}(rect_j)) / area(rect_i),
        measured in frame i's image. Computed by clipping rect_i to the part whose
        ground points are in front of camera j, mapping it into frame j, clipping to
        rect_j (Sutherland-Hodgman) and mapping back (see :func:`overlap_fraction`).
        Not symmetric in general (e.g. when the altitude changes).
        """
        if i == j:
            return 1.0
        return overlap_fraction(self.homography(i, j), self.width, self.height)


def load_flight(out_dir: Path | str) -> Flight:
    """Read groundtruth.csv and intrinsics.json written by :func:`generate`."""
    d = Path(out_dir)
    intr = json.loads((d / "intrinsics.json").read_text())
    with (d / "groundtruth.csv").open(newline="") as fh:
        rows = list(csv.reader(fh))
    header = rows[0]
    if tuple(header) != GT_COLUMNS:
        raise ValueError(f"{d / 'groundtruth.csv'}: unexpected columns {header}")
    a = np.array(rows[1:], dtype=np.float64).reshape(-1, len(GT_COLUMNS))
    col = {name: a[:, i] for i, name in enumerate(GT_COLUMNS)}
    q = np.stack([col["qw"], col["qx"], col["qy"], col["qz"]], 1)
    k = np.array(
        [[intr["fx"], 0.0, intr["cx"]], [0.0, intr["fy"], intr["cy"]], [0.0, 0.0, 1.0]],
    )
    return Flight(
        path=d,
        width=int(intr["width"]),
        height=int(intr["height"]),
        fps=float(intr["fps"]),
        K=k,
        t=col["t"],
        positions=np.stack([col["x"], col["y"], col["z"]], 1),
        quaternions=q,
        rotations=_quat_to_rotmat(q),
        euler_deg=np.stack([col["roll_deg"], col["pitch_deg"], col["yaw_deg"]], 1),
        geodetic=np.stack([col["lat"], col["lon"], col["alt"]], 1),
        blur_px=col["blur_px"],
        defocus_sigma=col["defocus_sigma"],
        blurry=col["blurry"] > 0.5,
        hover=col["hover"] > 0.5,
        intrinsics=intr,
    )


# --------------------------------------------------------------------------- CLI


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:  # one-line errors
        self.exit(2, f"{self.prog}: error: {message}\n")


def main(argv: list[str] | None = None) -> int:
    p = _Parser(
        prog="python -m keyframed.synth",
        description="Generate a synthetic drone flight (video + ground truth + tlog).",
    )
    p.add_argument("--flight", required=True, choices=FLIGHTS)
    p.add_argument("--out", required=True, type=Path, help="output directory")
    p.add_argument("--width", type=int, default=960)
    p.add_argument("--height", type=int, default=540)
    p.add_argument("--fps", type=float, default=30.0)
    p.add_argument("--seconds", type=float, default=None, help="duration (default per flight)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--exposure", type=float, default=DEFAULT_EXPOSURE_S, help="exposure, s")
    a = p.parse_args(argv)
    try:
        info = generate(
            a.flight,
            a.out,
            width=a.width,
            height=a.height,
            fps=a.fps,
            seconds=a.seconds,
            seed=a.seed,
            exposure_s=a.exposure,
        )
    except ValueError as e:
        p.error(str(e))
    except (OSError, RuntimeError) as e:
        print(f"{p.prog}: error: {e}", file=sys.stderr)
        return 1
    pct = 100.0 * info.blurry_frames / info.frames
    print(
        f"{info.flight}: {info.frames} frames {info.width}x{info.height} @ {info.fps:g} fps, "
        f"{info.blurry_frames} blurry ({pct:.1f}%), {info.hover_frames} hover, "
        f"{info.elapsed_s:.1f} s -> {info.out_dir}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
