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
    """Pixel counts over the frames read, to name the cause when nothing valid is left, and to
    report how much of the depth the mesh used."""

    frames: int = 0
    raw_valid: int = 0
    confident: int = 0
    kept: int = 0
    pixels: int = 0
    """All depth pixels of the frames read (valid or not)."""
    fused: int = 0
    """Pixels handed to the TSDF (after confidence weighting); ``kept`` counts them before it."""
    fused_frames: int = 0
    """Frames handed to the TSDF (frames with too little valid depth are skipped)."""
    per_frame_kept: list[int] = field(default_factory=list)

    def add(self, raw: NDArray, conf: NDArray | None, kept: NDArray, min_conf: int) -> None:
        self.frames += 1
        self.pixels += int(np.size(raw))
        rv = np.isfinite(raw) & (raw > 0)
        self.raw_valid += int(rv.sum())
        self.confident += int((rv & (conf >= min_conf)).sum()) if conf is not None else int(rv.sum())
        k = int((kept > 0).sum())
        self.kept += k
        self.per_frame_kept.append(k)

    @property
    def used_fraction(self) -> float:
        """Share of the valid (finite, > 0) depth pixels of the frames read that were fused."""
        return self.fused / self.raw_valid if self.raw_valid else 0.0

    def cause(self, trunc_m: float, min_conf: int) -> str:
        if self.raw_valid == 0:
            return "every depth map is empty (0 or NaN everywhere)"
        if self.confident == 0:
            return f"no pixel has confidence >= {min_conf}"
        return f"every confident pixel is farther than the {trunc_m:g} m truncation"


def prefetch(items: Iterator, depth: int = 6) -> Iterator:
    """Yield ``items`` while a background thread reads ahead up to ``depth`` of them.

    Fusion alternates decoding (video, PNG: C code that releases the GIL) and integration (Open3D);
    reading the next frames while the current one is integrated overlaps the two. Order is kept,
    and an error in the reader is raised here, at the item where it happened.
    """
    import queue
    import threading

    q: queue.Queue = queue.Queue(maxsize=max(1, depth))
    done = object()
    stop = threading.Event()

    def reader() -> None:
        try:
            for it in items:
                while not stop.is_set():
                    try:
                        q.put((True, it), timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if stop.is_set():
                    return
            q.put((True, done))
        except BaseException as err:  # handed to the consumer, raised there
            q.put((False, err))

    th = threading.Thread(target=reader, name="fusion-reader", daemon=True)
    th.start()
    try:
        while True:
            ok, it = q.get()
            if not ok:
                raise it
            if it is done:
                return
            yield it
    finally:
        stop.set()
        th.join(timeout=5)


def weigh_by_confidence(depth: NDArray[np.float32], confidence: NDArray | None, weights: NDArray, n: int,
                        range_m: float = 0.0) -> NDArray[np.float32]:
    """Depth of the ``n``-th fused frame with the pixels that are not due this frame set to 0.

    The TSDF weighs every observation 1, so a pixel's weight ``w`` is applied as a share of
    frames: it is fused in frame ``n`` when ``floor((n + 1) w) > floor(n w)``, i.e. in exactly
    ``w`` of the frames, evenly spread (no randomness). Weight 1 keeps it in every frame. ``w`` is
    the weight of its confidence level, times ``min(1, (range_m / depth)^2)`` when ``range_m`` > 0:
    LiDAR noise grows with range, so a surface seen both from near and from across the room is
    fused mostly from the near views (a surface seen only from far still gets fused).

    Args:
        depth: (h, w) filtered depth, 0 = invalid.
        confidence: (h, w) integer confidence 0, 1, 2, or None (every pixel weighs 1 before range).
        weights: (3,) weight per confidence level, in (0, 1].
        n: index of the frame among the fused frames.
        range_m: depth (metres) beyond which the weight falls as the inverse square; 0 = off.
    """
    c = None if confidence is None else np.clip(np.asarray(confidence, dtype=np.int64), 0, 2)
    w = np.ones(depth.shape) if c is None else np.asarray(weights, dtype=np.float64)[c]  # (h, w)
    if range_m > 0:
        with np.errstate(divide="ignore"):
            w = w * np.minimum(1.0, (range_m / np.where(depth > 0, depth, np.inf)) ** 2)
    due = np.floor((n + 1) * w) > np.floor(n * w)
    if due.all():
        return depth
    return np.where(due, depth, np.float32(0.0)).astype(np.float32)


def check_depth(capture: Capture, cfg: SceneConfig, indoor: bool, samples: int = 30) -> float:
    """Share of valid depth pixels (after confidence and truncation) over up to ``samples`` frames
    spread over the capture; checked before Stage I writes anything.

    Raises:
        InputError: the share is below ``cfg.min_valid_depth_fraction`` (names the capture, the
            share and the likely cause).
    """
    n = capture.num_frames
    ids = np.unique(np.linspace(0, n - 1, min(samples, n)).round().astype(np.int64)) if n else np.zeros(0, np.int64)
    stats = DepthStats()
    trunc = cfg.depth_trunc_m(indoor)
    for f in ids:
        raw = capture.frames.depth_m(int(f))
        conf = capture.frames.confidence(int(f))
        stats.add(raw, conf, filter_depth(raw, conf, cfg.min_confidence, trunc), cfg.min_confidence)
    share = stats.kept / max(stats.pixels, 1)
    if share < cfg.min_valid_depth_fraction:
        what = (f"no valid depth in {stats.frames} sampled frames: {stats.cause(trunc, cfg.min_confidence)}"
                if stats.kept == 0 else
                f"too little valid depth: {100 * share:.1f} % of the depth pixels of {stats.frames} sampled frames "
                f"(need {100 * cfg.min_valid_depth_fraction:g} %)")
        raise InputError(capture.path, what, "the scan needs LiDAR depth of the room (was the depth sensor covered, "
                         "the capture exported without depth, or the scene out of range?); or lower "
                         "min_valid_depth_fraction / min_confidence")
    return share


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
    weights = np.asarray(cfg.confidence_weights, dtype=np.float64)
    for i in np.argsort(ids, kind="stable"):
        f = int(ids[i])
        raw = capture.frames.depth_m(f)
        conf = capture.frames.confidence(f)
        rgb = None
        if refine is not None:
            rgb = capture.frames.rgb(f)
            raw = np.asarray(refine(rgb, raw, conf), dtype=np.float32)
        depth = filter_depth(raw, conf, cfg.min_confidence, trunc)
        stats.add(raw, conf, depth, cfg.min_confidence)
        if stats.per_frame_kept[-1] < cfg.fuse_min_valid_fraction * depth.size:
            continue  # (the colour is decoded only for frames that are fused)
        if conf is not None or cfg.depth_weight_range_m > 0:
            depth = weigh_by_confidence(depth, conf, weights, stats.fused_frames, cfg.depth_weight_range_m)
        stats.fused_frames += 1
        stats.fused += int((depth > 0).sum())
        rgb = capture.frames.rgb(f) if rgb is None else rgb
        yield colour_at_depth_resolution(rgb, K), depth, K, T[i]
    if stats.kept == 0:
        raise InputError(capture.path, f"no valid depth in {stats.frames} key frames: "
                         f"{stats.cause(trunc, cfg.min_confidence)}",
                         "check the capture has LiDAR depth, or lower min_confidence / raise the depth truncation")
    log.debug("%s: %d key frames, %.0f valid depth pixels per frame", capture.path, stats.frames,
              stats.kept / max(stats.frames, 1))
