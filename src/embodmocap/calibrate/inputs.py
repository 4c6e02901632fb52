"""What Stage III reads of one view, in memory: shared by its steps (:mod:`embodmocap.calibrate.solve`
and its step 4, :mod:`embodmocap.calibrate.final_sync`), below both so neither imports the other."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from numpy.typing import NDArray

from embodmocap.io.stage_files import CameraFile


@dataclass(frozen=True)
class ViewInputs:
    """One view's Stage II data, as Stage III uses it.

    Attributes:
        cameras: the view's ``cameras.npz`` (VIO world): K, size, (T, 4, 4) ``T_world_cam``,
            raw frames, depth intrinsics.
        keypoints: (T, 17, 3) the performer's 2D keypoints (x, y, confidence).
        depth_m: sequence frame t -> (h, w) float32 depth in metres (0 = invalid).
        mask: sequence frame t -> (H, W) bool person mask; None when the view has no masks.
        rgb: sequence frame t -> (H, W, 3) uint8 colour frame (needed by :func:`register_view` only).
    """

    cameras: CameraFile
    keypoints: NDArray
    depth_m: Callable[[int], NDArray]
    mask: Callable[[int], NDArray] | None = None
    rgb: Callable[[int], NDArray] | None = None
