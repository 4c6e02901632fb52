"""Pluggable perception backends (one protocol per role; learned models load lazily).

Depth refinement: :class:`DepthRefiner` with the backends ``"none"`` (:class:`LidarDepth`) and
``"promptda"`` (:class:`PromptDepthAnything`), built by :func:`make_depth_refiner`.
"""

_LAZY = {"DEPTH_REFINERS", "DepthRefiner", "LidarDepth", "PromptDAOptions", "PromptDepthAnything", "make_depth_refiner"}

__all__ = sorted(_LAZY)


def __getattr__(name: str):
    # Imported on first use: the package's settings (perception.config) load without OpenCV or SciPy.
    if name in _LAZY:
        from embodmocap.perception import depth_refine

        return getattr(depth_refine, name)
    raise AttributeError(f"module 'embodmocap.perception' has no attribute {name!r}")
