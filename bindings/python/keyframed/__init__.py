"""keyframed: keyframe selection for Structure-from-Motion, from Python.

The native selection core (``keyframed._core``, built from daemon/core by
nanobind) is loaded on first use, so the pure-Python tools (``keyframed.synth``)
work even where the extension is not built.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

# All of them from the native core, loaded by __getattr__ on first use.
__all__ = [
    "SharpnessScorer",
    "OverlapEstimator",
    "KeyframeSelector",
    "SelectorConfig",
    "select_video",
    "sampled_laplacian_variance",
    "reference_laplacian_variance",
]

if TYPE_CHECKING:
    # The same names for the type checker, typed by _core.pyi.
    from ._core import (
        KeyframeSelector,
        OverlapEstimator,
        SelectorConfig,
        SharpnessScorer,
        reference_laplacian_variance,
        sampled_laplacian_variance,
        select_video,
    )


def __getattr__(name: str) -> Any:
    if name in __all__:
        from . import _core

        return getattr(_core, name)
    raise AttributeError(f"module 'keyframed' has no attribute {name!r}")


def __dir__() -> list[str]:
    # The native names too (tab completion, help()), without loading the core.
    return sorted(set(globals()) | set(__all__))
