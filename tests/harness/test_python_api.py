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
    blurred: np.ndarray = cv2.GaussianBlur(g, (0, 0), 3)
    score, thr, sharp = s.evaluate(blurred)
    assert not sharp and score < thr


def test_selector_on_a_pan_keeps_frames_near_the_target():
    strip: np.ndarray = cv2.cvtColor(photo_strip(), cv2.COLOR_BGR2GRAY)
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


def test_a_requested_capture_keeps_the_next_sharp_frame_while_hovering():
    strip: np.ndarray = cv2.cvtColor(photo_strip(), cv2.COLOR_BGR2GRAY)
    sel = keyframed.KeyframeSelector()
    view = np.ascontiguousarray(strip[100:370, 200:680])
    reasons = []
    for i in range(30):
        if i == 10:
            assert sel.request_capture() and sel.pending_captures == 1
        frame: np.ndarray = cv2.GaussianBlur(view, (0, 0), 2) if i in (10, 11) else view
        reasons.append(sel.process(frame, i)["reason"])
    assert reasons[0] == "first" and reasons[12] == "commanded", reasons
    assert reasons[10:12] == ["blurry", "blurry"]
    assert sel.keyframes == 2 and sel.pending_captures == 0


def test_decisions_carry_per_stage_times():
    # Core reads no clock; the binding lends it one, as the daemon does.
    sel = keyframed.KeyframeSelector()
    bgr: np.ndarray | None = cv2.imread(str(PHOTOS / "aero1.jpg"))
    assert bgr is not None
    views = [np.ascontiguousarray(bgr[:, i * 4 : i * 4 + 600]) for i in range(3)]
    decisions = [sel.process(v, i) for i, v in enumerate(views)]
    for d in decisions:
        t = d["times_ms"]
        assert set(t) == {"luma", "blur", "resize", "overlap", "total"}
        assert t["total"] == d["total_ms"] > 0
        assert t["luma"] > 0 and t["blur"] > 0  # BGR is converted to luma, then scored
        assert all(v >= 0 for v in t.values())
        assert t["luma"] + t["blur"] + t["resize"] + t["overlap"] == pytest.approx(t["total"])
    assert decisions[1]["times_ms"]["overlap"] > 0  # tracked against the first keyframe


def test_bgr_input_and_bad_arrays():
    sel = keyframed.KeyframeSelector()
    bgr: np.ndarray | None = cv2.imread(str(PHOTOS / "aero3.jpg"))
    assert bgr is not None
    d = sel.process(bgr, 0)
    assert d["kept"] and d["reason"] == "first"
    with pytest.raises(ValueError):
        sel.process(np.zeros((4, 4, 4), np.uint8), 1)
    with pytest.raises(TypeError):
        sel.process(np.zeros((4, 4), np.float32), 1)


def test_arrays_the_core_cannot_read_are_refused():
    """An empty array, rows that do not follow one another (a flipped or broadcast
    view), a negative frame index, a sampling step of 0: refused with a ValueError,
    never read out of bounds; a slice of a larger array reads as itself."""
    sel = keyframed.KeyframeSelector()
    read = cv2.imread(str(PHOTOS / "aero3.jpg"), cv2.IMREAD_GRAYSCALE)
    assert read is not None
    grey: np.ndarray = np.asarray(read, dtype=np.uint8)
    bgr: np.ndarray = np.ascontiguousarray(np.dstack([grey, grey, grey]))
    bad: list[tuple[np.ndarray, str]] = [
        (np.zeros((0, 1000), np.uint8), "empty"),
        (np.zeros((10, 0), np.uint8), "empty"),
        (np.zeros((0, 10, 3), np.uint8), "empty"),
        (np.flipud(grey), "rows"),
        (np.broadcast_to(grey[:1], grey.shape), "rows"),
        (np.flipud(bgr), "rows"),
    ]
    for image, why in bad:
        with pytest.raises(ValueError, match=why):
            sel.process(image, 0)
        with pytest.raises(ValueError, match=why):
            keyframed.SharpnessScorer().score(image if image.ndim == 2 else image[:, :, 0])
    with pytest.raises(ValueError, match="index"):
        sel.process(grey, -1)
    with pytest.raises(ValueError, match="step"):
        keyframed.sampled_laplacian_variance(grey, 0, 3)
    # Nothing refused was taken half-way: the first good frame is the first keyframe.
    assert sel.process(grey, 0)["reason"] == "first"
    view: np.ndarray = grey[10:200, 20:300]
    assert keyframed.reference_laplacian_variance(view) == keyframed.reference_laplacian_variance(
        view.copy()
    )


def test_one_selector_from_two_threads_takes_turns(pan_video: Path) -> None:
    """process() lets go of the GIL; two threads on one selector take turns on its
    lock instead of racing on its state: every frame decided once, none lost."""
    import threading

    cap = cv2.VideoCapture(str(pan_video))
    frames: list[np.ndarray] = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        frames.append(np.asarray(f, dtype=np.uint8))
    assert len(frames) == 90
    sel = keyframed.KeyframeSelector()
    decided: list[int] = []

    def work(first: int) -> None:
        for i in range(first, len(frames), 2):
            decided.append(sel.process(frames[i], i)["index"])

    threads = [threading.Thread(target=work, args=(k,)) for k in (0, 1)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(decided) == list(range(90))
    assert sel.keyframes >= 1


def test_config_validation():
    cfg = keyframed.SelectorConfig()
    cfg.target = 0.5  # under the default band
    assert "band" in cfg.validate()
    with pytest.raises(ValueError):
        keyframed.KeyframeSelector(cfg)
    with pytest.raises(ValueError):
        cfg.mode = "nonsense"
    # The ranges the daemon's [selection] and `keyframed select` take, not only the
    # core's rules: a setting Python takes can be given to them again.
    for key, value in (("ransac_px", 0.05), ("analysis_width", 100000), ("blur_threshold", 1e12)):
        cfg = keyframed.SelectorConfig()
        setattr(cfg, key, value)
        assert f"selection.{key}" in cfg.validate(), (key, cfg.validate())
        with pytest.raises(ValueError, match=f"selection.{key}"):
            keyframed.KeyframeSelector(cfg)


def test_select_video_from_python(pan_video: Path, tmp_path):
    s = keyframed.select_video(str(pan_video), str(tmp_path / "o"))
    assert s["frames_read"] == 90 and s["kept"] >= 3 and s["error"] == ""
    # the same directory again: refused (the runs' keyframes would mix), or replaced
    with pytest.raises(RuntimeError, match="earlier run"):
        keyframed.select_video(str(pan_video), str(tmp_path / "o"), max_frames=30)
    again = keyframed.select_video(
        str(pan_video), str(tmp_path / "o"), max_frames=30, overwrite=True
    )
    assert again["frames_read"] == 30
    assert len(list((tmp_path / "o").glob("*.jpg"))) == again["kept"] < s["kept"]
    for bad in (0, -5):
        with pytest.raises(ValueError, match="max_frames"):
            keyframed.select_video(str(pan_video), str(tmp_path / "o4"), max_frames=bad)
    with pytest.raises(RuntimeError, match="no such file"):
        keyframed.select_video(str(tmp_path / "missing.avi"), str(tmp_path / "o2"))
    # paths as pathlib gives them; a NUL is refused, not cut at
    assert keyframed.select_video(pan_video, tmp_path / "o5", max_frames=10)["frames_read"] == 10
    with pytest.raises((TypeError, ValueError)):  # (nanobind's path caster refuses it)
        keyframed.select_video(str(pan_video) + "\0.avi", tmp_path / "o6")
    assert not (tmp_path / "o6").exists()
    # An output that fails part-way (the first keyframe's name taken by a directory):
    # raised, not a summary that reads like success.
    blocked = tmp_path / "o3"
    (blocked / "000000.jpg").mkdir(parents=True)
    with pytest.raises(RuntimeError, match="000000"):
        keyframed.select_video(str(pan_video), str(blocked))


def test_overlap_estimator_measures_a_pan():
    """Geometric overlap of a pan against its first view: the visible fraction shrinks
    as the view slides (1 - shift/width), a candidate can become the reference, and a
    featureless frame loses tracking."""
    strip: np.ndarray = cv2.cvtColor(photo_strip(), cv2.COLOR_BGR2GRAY)
    est = keyframed.OverlapEstimator.create(keyframed.SelectorConfig())

    def view(x: int) -> np.ndarray:
        return np.ascontiguousarray(strip[100:370, x : x + 480])

    first = est.observe(view(50))
    assert not first["valid"] and first["features"] > 50
    est.set_reference_to_current()
    for i in range(1, 16):
        r = est.observe(view(50 + 8 * i))
        assert r["valid"] and r["inliers"] >= 15
        assert r["overlap"] == pytest.approx(1 - 8 * i / 480, abs=0.02), i
        if i == 10:
            est.mark_candidate()
    # the frame at shift 80 px becomes the reference: the current one (120 px) is 40 px on
    r = est.set_reference_to_candidate()
    assert r["valid"] and r["overlap"] == pytest.approx(1 - 40 / 480, abs=0.02)
    lost = est.observe(np.full((270, 480), 128, np.uint8))
    assert not lost["valid"]


def test_paper_estimator_distance_grows_with_the_shift():
    cfg = keyframed.SelectorConfig()
    cfg.mode = "paper"
    est = keyframed.OverlapEstimator.create(cfg)
    strip: np.ndarray = cv2.cvtColor(photo_strip(), cv2.COLOR_BGR2GRAY)
    est.observe(np.ascontiguousarray(strip[100:370, 50:530]))
    est.set_reference_to_current()
    near = est.observe(np.ascontiguousarray(strip[100:370, 60:540]))["paper_distance"]
    far = est.observe(np.ascontiguousarray(strip[100:370, 250:730]))["paper_distance"]
    assert near is not None and far is not None and near < far


def test_config_has_every_selection_key_of_the_daemon():
    """The Python config exposes the same names as [selection] in the daemon's config."""
    text = (Path(__file__).parents[2] / "config/keyframed.toml").read_text()
    section = text.split("[selection]", 1)[1].split("\n[", 1)[0]
    keys = [
        line.lstrip("# ").split("=")[0].strip()
        for line in section.splitlines()
        if "=" in line and line.lstrip("# ")[:1].isalpha()
    ]
    assert len(keys) >= 25, keys
    cfg = keyframed.SelectorConfig()
    for key in keys:
        assert hasattr(cfg, key), key
    cfg.blur_warmup = 3
    cfg.lk_levels = 2
    assert cfg.blur_warmup == 3 and cfg.lk_levels == 2 and cfg.validate() == ""


def test_star_import():
    ns: dict[str, object] = {}
    exec("from keyframed import *", ns)
    assert {"KeyframeSelector", "OverlapEstimator", "select_video"} <= ns.keys()


def test_dir_lists_the_native_api() -> None:
    """Tab completion and help() see the core's names before first use loads it."""
    names = dir(keyframed)
    for name in keyframed.__all__:
        assert name in names
        assert callable(getattr(keyframed, name))
