"""Pluggable perception backends (one protocol per role; learned models load lazily).

Depth refinement: :class:`DepthRefiner` with the backends ``"none"`` (:class:`LidarDepth`) and
``"promptda"`` (:class:`PromptDepthAnything`), built by :func:`make_depth_refiner`.
"""

from embodmocap.perception.depth_refine import (
    DEPTH_REFINERS,
    DepthRefiner,
    LidarDepth,
    PromptDAOptions,
    PromptDepthAnything,
    make_depth_refiner,
)

__all__ = [
    "DEPTH_REFINERS",
    "DepthRefiner",
    "LidarDepth",
    "PromptDAOptions",
    "PromptDepthAnything",
    "make_depth_refiner",
]
