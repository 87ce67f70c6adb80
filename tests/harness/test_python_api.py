"""The native module on numpy arrays."""

from __future__ import annotations

from pathlib import Path

import cv2
import keyframed
import numpy as np
import pytest
from conftest import PHOTOS, photo_strip


def grey(name: str) -> np.ndarray:
    img = cv2.imread(str(PHOTOS / name), cv2.IMREAD_GRAYSCALE)
    assert img is not None
    return img


def test_sampled_variance_is_close_to_the_reference_on_photos():
    for name in ("aero1.jpg", "aero3.jpg", "building.jpg"):
        g = grey(name)
        ref = keyframed.reference_laplacian_variance(g)
        s9 = keyframed.sampled_laplacian_variance(g, 2, 3)
        assert abs(s9 / ref - 1) < 0.03
        # and it agrees with OpenCV's own Laplacian on the interior
        lap = cv2.Laplacian(g, cv2.CV_64F, ksize=1)[1:-1, 1:-1]
        assert ref == pytest.approx(lap.var(), rel=1e-9)


def test_scorer_adapts_and_rejects_blur():
    s = keyframed.SharpnessScorer()
    g = grey("aero1.jpg")
    for _ in range(20):
        assert s.evaluate(g)[2]
    score, thr, sharp = s.evaluate(cv2.GaussianBlur(g, (0, 0), 3))
    assert not sharp and score < thr


def test_selector_on_a_pan_keeps_frames_near_the_target():
    strip = cv2.cvtColor(photo_strip(), cv2.COLOR_BGR2GRAY)
    cfg = keyframed.SelectorConfig()
    cfg.analysis_width = 0
    sel = keyframed.KeyframeSelector(cfg)
    kept = []
    for i in range(100):
        x = 50 + 8 * i
        view = np.ascontiguousarray(strip[100:370, x : x + 480])
        d = sel.process(view, i, i * 33_333_333)
        if d["kept"]:
            kept.append(i)
    assert kept[0] == 0
    gaps = np.diff(kept) * 8 / 480.0  # fraction of the view moved between keyframes
    assert np.all(1 - gaps >= 0.6) and np.all(1 - gaps <= 0.75), kept


def test_bgr_input_and_bad_arrays():
    sel = keyframed.KeyframeSelector()
    bgr = cv2.imread(str(PHOTOS / "aero3.jpg"))
    d = sel.process(bgr, 0)
    assert d["kept"] and d["reason"] == "first"
    with pytest.raises(ValueError):
        sel.process(np.zeros((4, 4, 4), np.uint8), 1)
    with pytest.raises(TypeError):
        sel.process(np.zeros((4, 4), np.float32), 1)


def test_config_validation():
    cfg = keyframed.SelectorConfig()
    cfg.target = 0.5  # under the default band
    assert "band" in cfg.validate()
    with pytest.raises(ValueError):
        keyframed.KeyframeSelector(cfg)
    with pytest.raises(ValueError):
        cfg.mode = "nonsense"


def test_select_video_from_python(pan_video: Path, tmp_path):
    s = keyframed.select_video(str(pan_video), str(tmp_path / "o"))
    assert s["frames_read"] == 90 and s["kept"] >= 3 and s["error"] == ""
    with pytest.raises(RuntimeError, match="no such file"):
        keyframed.select_video(str(tmp_path / "missing.avi"), str(tmp_path / "o2"))
