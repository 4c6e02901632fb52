"""One protocol per perception role; backends (precomputed files, transformers models, MediaPipe)
implement them, and Stage II picks one per role from its config.

Conventions: images are (H, W, 3) uint8 RGB; pixel coordinates follow OpenCV (pixel centres at
integers); boxes are ``(x1, y1, x2, y2)`` in pixels; keypoints are COCO-17 (``types.COCO17_NAMES``)
as (17, 3) rows ``x, y, confidence`` with confidence 0 meaning "missing"; masks are (H, W) bool.
Every method is batched over frames so model backends can run efficiently; a backend that has
nothing for a frame returns an empty result for it (no detection, zero confidence, empty mask),
never raises for it.
"""

from __future__ import annotations

from typing import Protocol, Sequence, runtime_checkable

import numpy as np
from numpy.typing import NDArray


@runtime_checkable
class PersonDetector(Protocol):
    """Finds people in frames."""

    name: str

    def detect(self, frames: Sequence[NDArray[np.uint8]], frame_ids: Sequence[int]) -> list[NDArray[np.float64]]:
        """Per frame, (N, 5) float rows ``x1, y1, x2, y2, score`` (score in [0, 1]); (0, 5) if none."""
        ...


@runtime_checkable
class KeypointEstimator(Protocol):
    """2D body keypoints (COCO-17) of given people boxes."""

    name: str

    def estimate(self, frames: Sequence[NDArray[np.uint8]], frame_ids: Sequence[int],
                 boxes: Sequence[NDArray[np.float64]]) -> list[NDArray[np.float64]]:
        """Per frame, (N, 17, 3) keypoints for that frame's N boxes (same order)."""
        ...


@runtime_checkable
class MaskSegmenter(Protocol):
    """Person masks through a video, prompted by the performer's box."""

    name: str

    def segment(self, frames: Sequence[NDArray[np.uint8]], frame_ids: Sequence[int],
                boxes: NDArray[np.float64]) -> list[NDArray[np.bool_]]:
        """Per frame, the (H, W) mask of the person in ``boxes[i]`` ((T, 4), NaN rows = person not
        seen in that frame: the backend may propagate from earlier frames or return an empty mask).
        Frames arrive in time order, possibly in consecutive chunks of one video."""
        ...


@runtime_checkable
class BodyPriorEstimator(Protocol):
    """Camera-space SMPL body estimate per frame (an HMR/VIMO-style regressor)."""

    name: str

    def estimate(self, frames: Sequence[NDArray[np.uint8]], frame_ids: Sequence[int],
                 boxes: NDArray[np.float64]):
        """A :class:`embodmocap.io.body_prior.BodyPriorSeq` for these frames."""
        ...


@runtime_checkable
class DepthEstimator(Protocol):
    """Metric depth per frame: the sensor's depth refined by a model, or depth read from files."""

    name: str

    def depth_maps(self, frames: Sequence[NDArray[np.uint8]], frame_ids: Sequence[int],
                   sensor_depth: Sequence[NDArray[np.floating]] | None) -> list[NDArray[np.float32]]:
        """Per frame, an (h, w) float32 depth map in metres (0 = invalid). ``sensor_depth`` is the
        capture's own depth of the same frames (None for backends that do not use it)."""
        ...
