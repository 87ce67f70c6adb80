"""keyframed: keyframe selection for Structure-from-Motion, from Python.

The native selection core (``keyframed._core``, built from daemon/core by
nanobind) is loaded on first use, so the pure-Python tools (``keyframed.synth``)
work even where the extension is not built.
"""

from __future__ import annotations

from typing import Any

_NATIVE = (
    "SharpnessScorer",
    "OverlapEstimator",
    "KeyframeSelector",
    "SelectorConfig",
    "select_video",
    "sampled_laplacian_variance",
    "reference_laplacian_variance",
)

__all__ = list(_NATIVE)


def __getattr__(name: str) -> Any:
    if name in _NATIVE:
        from . import _core

        return getattr(_core, name)
    raise AttributeError(f"module 'keyframed' has no attribute {name!r}")
