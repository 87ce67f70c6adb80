"""What COLMAP makes of a ground-station dataset: pycolmap reads the images, the
camera from their EXIF tags (no parameters handed to it), a GPS prior per image, the
SIFT features of ``features/`` and the pairs of ``pairs.txt``, matches those pairs,
verifies them geometrically and reconstructs. Used by the end-to-end tests."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass
class ColmapResult:
    images: int
    focal_px: float  # the camera COLMAP made from the EXIF tags
    priors: dict[str, tuple[float, float, float]]  # image name -> lat, lon, alt
    pairs_listed: int
    pairs_verified: int
    registered: int  # images in the largest reconstruction


def _read_features(path: Path) -> tuple[np.ndarray, np.ndarray]:
    lines = path.read_text().splitlines()
    count, dim = (int(v) for v in lines[0].split())
    rows = np.array([[float(v) for v in line.split()] for line in lines[1 : 1 + count]])
    keypoints = rows[:, :4].astype(np.float32)  # x y scale orientation
    descriptors = rows[:, 4 : 4 + dim].astype(np.uint8)
    return keypoints, descriptors


def reconstruct(dataset: Path, work: Path) -> ColmapResult:
    import pycolmap

    work.mkdir(parents=True, exist_ok=True)
    db_path = work / "colmap.db"
    pycolmap.Database.open(db_path).close()  # creates the schema
    pycolmap.import_images(db_path, dataset / "images", pycolmap.CameraMode.SINGLE)
    db = pycolmap.Database.open(db_path)
    try:
        cameras = db.read_all_cameras()
        assert len(cameras) == 1, cameras
        focal = float(cameras[0].params[0])
        images = db.read_all_images()
        names = {im.image_id: im.name for im in images}
        priors = {}
        for prior in db.read_all_pose_priors():
            name = names[prior.corr_data_id.id]
            lat, lon, alt = (float(v) for v in prior.position)
            priors[name] = (lat, lon, alt)
        for im in images:
            kp, desc = _read_features(dataset / "features" / (im.name + ".txt"))
            db.write_keypoints(im.image_id, kp)
            db.write_descriptors(
                im.image_id, pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.SIFT, desc)
            )
    finally:
        db.close()
    pairing = pycolmap.ImportedPairingOptions()
    pairing.match_list_path = str(dataset / "pairs.txt")
    pycolmap.match_image_pairs(db_path, pairing_options=pairing, device=pycolmap.Device.cpu)
    db = pycolmap.Database.open(db_path)
    try:
        verified = sum(
            1 for _, tvg in zip(*db.read_two_view_geometries(), strict=True) if tvg.config >= 2
        )
    finally:
        db.close()
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = 2
    recs = pycolmap.incremental_mapping(db_path, dataset / "images", work / "sparse", opts)
    registered = max((r.num_reg_images() for r in recs.values()), default=0)
    listed = len((dataset / "pairs.txt").read_text().splitlines())
    return ColmapResult(len(images), focal, priors, listed, verified, registered)


@dataclass
class ColmapCliResult:
    keypoints: dict[str, int]  # image name -> keypoints COLMAP imported
    pairs_matched: int  # pairs of pairs.txt COLMAP matched
    pairs_verified: int  # of them, with a geometrically verified model
    camera_model: int  # COLMAP's camera model id (4: OPENCV)
    camera_params: list[float]


def colmap_cli_import(dataset: Path, work: Path) -> ColmapCliResult:
    """The dataset through COLMAP's own command line as docs/deploy.md runs it: the
    SIFT features with ``colmap feature_importer`` and the camera of cameras.txt, the
    pairs with ``colmap matches_importer --match_type pairs`` (on the CPU: no display
    here); what its database then holds."""
    import os
    import sqlite3
    import subprocess

    work.mkdir(parents=True, exist_ok=True)
    db = work / "colmap-cli.db"
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen"}
    camera = [ln for ln in (dataset / "cameras.txt").read_text().splitlines() if ln[:1] != "#"]
    _, model, _, _, *params = camera[0].split()
    commands = [
        ["feature_importer", "--image_path", str(dataset / "images")]
        + ["--import_path", str(dataset / "features"), "--ImageReader.single_camera", "1"]
        + ["--ImageReader.camera_model", model, "--ImageReader.camera_params", ",".join(params)],
        ["matches_importer", "--match_list_path", str(dataset / "pairs.txt")]
        + ["--match_type", "pairs", "--SiftMatching.use_gpu", "0"],
    ]
    for args in commands:
        r = subprocess.run(
            ["colmap", args[0], "--database_path", str(db), *args[1:]],
            capture_output=True,
            text=True,
            env=env,
            timeout=600,
        )
        assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    con = sqlite3.connect(db)
    try:
        keypoints = dict(
            con.execute(
                "SELECT images.name, keypoints.rows FROM images JOIN keypoints "
                "ON images.image_id = keypoints.image_id"
            ).fetchall()
        )
        matched = con.execute("SELECT COUNT(*) FROM matches WHERE rows > 0").fetchone()[0]
        verified = con.execute(
            "SELECT COUNT(*) FROM two_view_geometries WHERE rows > 0 AND config >= 2"
        ).fetchone()[0]
        cameras = con.execute("SELECT model, params FROM cameras").fetchall()
    finally:
        con.close()
    assert len(cameras) == 1, cameras
    values = np.frombuffer(cameras[0][1], dtype=np.float64).tolist()
    return ColmapCliResult(keypoints, int(matched), int(verified), int(cameras[0][0]), values)
