"""Depth for the scene TSDF: LiDAR depth with low-confidence and far pixels dropped.

Resolution choice: fusion runs at the **depth** resolution (e.g. 256 x 192) and the colour is the
RGB frame shrunk to that size with area averaging. Upsampling depth to the RGB size instead would
only add interpolated samples (no new measurements), smear depth edges into flying pixels, and
cost ~6-60x more integration work; at 1-2 cm voxels a depth pixel already spans about one voxel at
2 m, so the low resolution loses no geometry. Depth and RGB are the same camera at two resolutions
(:meth:`embodmocap.types.Intrinsics.scaled`), so no reprojection is needed.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Callable, Iterator, Sequence

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.scene.config import SceneConfig
from embodmocap.types import Capture, Intrinsics

log = logging.getLogger(__name__)

#: Optional depth refinement: (rgb (H, W, 3) uint8, depth_m (h, w), confidence (h, w) or None)
#: -> refined depth_m (h, w) float32 at the same depth resolution.
RefineFn = Callable[[NDArray[np.uint8], NDArray[np.float32], NDArray[np.uint8] | None], NDArray[np.float32]]


def filter_depth(depth_m: NDArray, confidence: NDArray | None, min_confidence: int, trunc_m: float) -> NDArray[np.float32]:
    """(h, w) float32 depth with invalid pixels set to 0.

    Invalid: non-finite, <= 0, beyond ``trunc_m``, or (when a confidence map is given) with
    confidence below ``min_confidence``. The input is not modified.
    """
    d = np.asarray(depth_m, dtype=np.float32)
    ok = np.isfinite(d) & (d > 0) & (d <= trunc_m)
    if confidence is not None:
        c = np.asarray(confidence)
        if c.shape != d.shape:
            raise ValueError(f"confidence {c.shape} and depth {d.shape} differ in size")
        ok &= c >= min_confidence
    return np.where(ok, d, np.float32(0.0)).astype(np.float32)


def colour_at_depth_resolution(rgb: NDArray[np.uint8], depth_intrinsics: Intrinsics) -> NDArray[np.uint8]:
    """The (H, W, 3) RGB frame shrunk to the depth map's (h, w) with area averaging."""
    import cv2

    K = depth_intrinsics
    if rgb.shape[:2] == (K.height, K.width):
        return np.ascontiguousarray(rgb)
    return cv2.resize(rgb, (K.width, K.height), interpolation=cv2.INTER_AREA)


def keyframe_depth(capture: Capture, frame_id: int, cfg: SceneConfig, indoor: bool) -> tuple[NDArray[np.float32], Intrinsics]:
    """Filtered depth of one frame: ``(depth_m (h, w) float32, intrinsics at depth resolution)``.

    Pixels with confidence below ``cfg.min_confidence``, beyond ``cfg.depth_trunc_m(indoor)``, or
    non-finite are 0.
    """
    d = capture.frames.depth_m(int(frame_id))
    c = capture.frames.confidence(int(frame_id))
    return filter_depth(d, c, cfg.min_confidence, cfg.depth_trunc_m(indoor)), capture.depth_intrinsics


@dataclass
class DepthStats:
    """Pixel counts over the frames read, to name the cause when nothing valid is left."""

    frames: int = 0
    raw_valid: int = 0
    confident: int = 0
    kept: int = 0
    per_frame_kept: list[int] = field(default_factory=list)

    def add(self, raw: NDArray, conf: NDArray | None, kept: NDArray, min_conf: int) -> None:
        self.frames += 1
        rv = np.isfinite(raw) & (raw > 0)
        self.raw_valid += int(rv.sum())
        self.confident += int((rv & (conf >= min_conf)).sum()) if conf is not None else int(rv.sum())
        k = int((kept > 0).sum())
        self.kept += k
        self.per_frame_kept.append(k)

    def cause(self, trunc_m: float, min_conf: int) -> str:
        if self.raw_valid == 0:
            return "every depth map is empty (0 or NaN everywhere)"
        if self.confident == 0:
            return f"no pixel has confidence >= {min_conf}"
        return f"every confident pixel is farther than the {trunc_m:g} m truncation"


def fusion_frames(capture: Capture, frame_ids: Sequence[int], T_world_cam: NDArray, cfg: SceneConfig, indoor: bool,
                  refine: RefineFn | None = None, stats: DepthStats | None = None,
                  ) -> Iterator[tuple[NDArray[np.uint8], NDArray[np.float32], Intrinsics, NDArray[np.float64]]]:
    """Yield ``(rgb (h, w, 3) uint8, depth_m (h, w) float32, intrinsics (h, w), T_world_cam (4, 4))``.

    Frames are read once each in increasing frame order (video decoding only runs forward); colour
    is at depth resolution (see the module docstring). ``refine``, when given, replaces the raw
    depth before filtering (the learned backend; its output is filtered like LiDAR depth).

    Raises:
        InputError: after the last frame, if no frame had any valid depth pixel (names the capture
            and the cause: empty maps, low confidence, or everything beyond the truncation).
    """
    ids = np.asarray(frame_ids, dtype=np.int64)
    T = np.asarray(T_world_cam, dtype=np.float64).reshape(len(ids), 4, 4)
    stats = DepthStats() if stats is None else stats
    trunc = cfg.depth_trunc_m(indoor)
    K = capture.depth_intrinsics
    for i in np.argsort(ids, kind="stable"):
        f = int(ids[i])
        rgb = capture.frames.rgb(f)
        raw = capture.frames.depth_m(f)
        conf = capture.frames.confidence(f)
        if refine is not None:
            raw = np.asarray(refine(rgb, raw, conf), dtype=np.float32)
        depth = filter_depth(raw, conf, cfg.min_confidence, trunc)
        stats.add(raw, conf, depth, cfg.min_confidence)
        yield colour_at_depth_resolution(rgb, K), depth, K, T[i]
    if stats.kept == 0:
        raise InputError(capture.path, f"no valid depth in {stats.frames} key frames: "
                         f"{stats.cause(trunc, cfg.min_confidence)}",
                         "check the capture has LiDAR depth, or lower min_confidence / raise the depth truncation")
    log.debug("%s: %d key frames, %.0f valid depth pixels per frame", capture.path, stats.frames,
              stats.kept / max(stats.frames, 1))
