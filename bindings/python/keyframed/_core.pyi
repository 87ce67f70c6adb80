# Types of the compiled keyframed._core (bindings/python/src/module.cpp), written by
# hand: keep them in step with the bindings. Images are numpy uint8 arrays, (H, W)
# grey or (H, W, 3) BGR; an image of any other dtype is refused, not converted.
# The dicts the functions return are plain dicts at run time, typed here by their keys
# (these TypedDicts are for the type checker only: the module has no such names).

from os import PathLike
from typing import TypedDict

import numpy as np
import numpy.typing as npt

class _Overlap(TypedDict):
    valid: bool
    overlap: float | None
    paper_distance: float | None
    motion_px: float | None
    features: int
    matches: int
    inliers: int

class _Decision(TypedDict):
    index: int
    timestamp_ns: int
    kept: bool
    # first, overlap_target, paper_distance, gap_fill, blurry, redundant, lost,
    # featureless, commanded or refocus
    reason: str
    candidate: bool
    promoted: int | None
    sharpness: float
    threshold: float
    sharp: bool
    overlap: float | None
    paper_distance: float | None
    tracking: bool
    motion_px: float | None
    fast_motion: bool
    features: int
    matches: int
    inliers: int
    total_ms: float
    times_ms: dict[str, float]  # luma, blur, resize, overlap and total

class _SelectSummary(TypedDict):
    frames_read: int
    kept: int
    rejected_blur: int
    rejected_overlap: int
    gap_fills: int
    seconds: float
    frames_per_second: float
    analysis_ms_mean: float
    truncated: bool
    error: str
    decisions_path: str
    summary_path: str

def sampled_laplacian_variance(
    gray: npt.NDArray[np.uint8], row_step: int = 2, col_step: int = 3
) -> float: ...
def reference_laplacian_variance(gray: npt.NDArray[np.uint8]) -> float: ...

class SelectorConfig:
    # "geometric" or "paper"
    mode: str
    target: float
    band_low: float
    band_high: float
    min_overlap: float
    motion_ratio: float
    motion_min_fraction: float
    motion_window: int
    capture_wait_ms: int
    analysis_width: int
    # "adaptive" or "absolute"
    blur_mode: str
    blur_threshold: float
    blur_floor: float
    blur_ratio: float
    blur_quantile: float
    blur_window: int
    blur_warmup: int
    blur_row_step: int
    blur_col_step: int
    blur_width: int
    orb_features: int
    paper_threshold: float
    paper_min_matches: int
    max_tracks: int
    min_tracks: int
    min_inliers: int
    ransac_px: float
    fast_threshold: int
    lk_window: int
    lk_levels: int
    def __init__(self) -> None: ...
    def validate(self) -> str: ...

class SharpnessScorer:
    def __init__(self, config: SelectorConfig = ...) -> None: ...
    def evaluate(self, gray: npt.NDArray[np.uint8]) -> tuple[float, float, bool]: ...
    def score(self, gray: npt.NDArray[np.uint8]) -> float: ...
    @property
    def threshold(self) -> float: ...

class OverlapEstimator:
    @staticmethod
    def create(config: SelectorConfig = ...) -> OverlapEstimator: ...
    def observe(self, gray: npt.NDArray[np.uint8]) -> _Overlap: ...
    def set_reference_to_current(self) -> None: ...
    def mark_candidate(self) -> None: ...
    def set_reference_to_candidate(self) -> _Overlap: ...
    def reset(self) -> None: ...

class KeyframeSelector:
    def __init__(self, config: SelectorConfig = ...) -> None: ...
    def process(
        self, image: npt.NDArray[np.uint8], index: int, timestamp_ns: int = 0
    ) -> _Decision: ...
    def finish(self) -> int | None: ...
    def request_capture(self) -> bool: ...
    @property
    def pending_captures(self) -> int: ...
    @property
    def keyframes(self) -> int: ...

def select_video(
    video: str | PathLike[str],
    out_dir: str | PathLike[str],
    config: SelectorConfig | None = None,
    decisions: str = "csv",
    jpeg_quality: int = 92,
    max_frames: int = -1,
    calibration: str | PathLike[str] = "",
    overwrite: bool = False,
) -> _SelectSummary: ...
