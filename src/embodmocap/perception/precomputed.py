"""The ``precomputed`` perception backends: read what the user brings, frame by frame.

Each backend is built from the folder or file the manifest names for a view
(:class:`embodmocap.io.manifest.ViewEntry` ``keypoints`` / ``masks`` / ``depth`` / ``body_prior``)
and is indexed by the **raw frame number** of that view's capture. Files are found once, by the
trailing digits of their names; their contents are read on demand and never cached, so memory does
not grow with the sequence length (only the name index and the set of missing frames are kept).

A frame with no file is never an error: the backend returns the empty result of its role (no
person, an all-False mask, an all-zero depth, no prior row) and adds the frame to
``missing_frames`` so the stage can report it. A file that exists but cannot be read is an
:class:`~embodmocap.errors.InputError` naming it.

Backends and their inputs (formats in ``docs/formats.md``):

- :class:`PrecomputedKeypoints`: OpenPose JSON per frame (BODY_25, BODY_25B, COCO-18, COCO-17,
  mapped to COCO-17 by :mod:`embodmocap.io.openpose`) or one COCO keypoint JSON file. Returns every
  person of a frame; :class:`PrecomputedDetector` derives person boxes from them.
- :class:`PrecomputedMasks`: person mask PNGs (> 127 = person).
- :class:`PrecomputedDepth`: depth as uint16 PNG (millimetres by default) or float ``.npy`` (metres).
- :class:`PrecomputedBodyPrior`: a body prior ``.npz`` (:mod:`embodmocap.io.body_prior`).
"""

from __future__ import annotations

import threading
import logging
import os
import re
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from embodmocap.errors import InputError
from embodmocap.io.body_prior import BodyPriorSeq, read_body_prior
from embodmocap.io.openpose import (
    LAYOUT_SIZE, detect_layout, keypoint_files, read_coco_keypoints, read_openpose_raw, to_coco17,
)

log = logging.getLogger(__name__)

NAME = "precomputed"
"""The backend name every class here reports (``.name``)."""

_LAYOUT_SAMPLE = 64
"""How many files (spread over the folder) decide a 25-point layout: enough for a robust median,
cheap enough to stay well under a second."""

"""A point counts as "at the midpoint" within this fraction of the person's size."""

_IMAGE_NUMBER_RE = re.compile(r"(\d+)(?:[_.-](?:mask|depth|seg|person))?$", re.IGNORECASE)
"""Frame number of an image file from its stem: ``000012``, ``frame_0012``, ``cam1_12``,
``000012_mask``."""

_TRAILING_DIGITS_RE = re.compile(r"(\d+)\D*$")
"""Last run of digits in a COCO image id or file name (``"frames/img_000123.jpg"`` -> 123)."""


# ------------------------------------------------------------------------------------------------
# Boxes from keypoints


def boxes_from_keypoints(
    kps: NDArray, conf_thr: float = 0.3, scale: float = 1.2, image_size: tuple[int, int] | None = None
) -> NDArray[np.float64]:
    """Person boxes around the confident keypoints, enlarged about their centre.

    Args:
        kps: (..., 17, 3) keypoints ``x, y, confidence`` (any number of leading axes).
        conf_thr: points with confidence >= this count.
        scale: the box of the confident points is scaled by this about its centre (keypoints are
            joints, so the body's outline lies outside their box).
        image_size: ``(W, H)`` to clip the boxes to the image, or None.

    Returns:
        (..., 4) boxes ``x1, y1, x2, y2`` px; NaN rows where fewer than 2 points are confident.
    """
    kps = np.asarray(kps, dtype=np.float64)
    ok = kps[..., 2] >= conf_thr
    big = np.inf
    lo = np.where(ok[..., None], kps[..., :2], big).min(axis=-2)
    hi = np.where(ok[..., None], kps[..., :2], -big).max(axis=-2)
    with np.errstate(invalid="ignore"):  # inf - inf where no point is confident: NaN'd below
        centre, half = 0.5 * (lo + hi), 0.5 * scale * (hi - lo)
    boxes = np.concatenate([centre - half, centre + half], axis=-1)
    if image_size is not None:
        W, H = image_size
        boxes = np.clip(boxes, 0.0, [W - 1, H - 1, W - 1, H - 1])
    boxes[ok.sum(-1) < 2] = np.nan
    return boxes


def box_iou(a: NDArray, b: NDArray) -> NDArray[np.float64]:
    """(M, N) intersection over union of (M, 4) and (N, 4) boxes ``x1, y1, x2, y2``; NaN boxes give 0."""
    a, b = np.asarray(a, dtype=np.float64)[:, None, :4], np.asarray(b, dtype=np.float64)[None, :, :4]
    w = np.minimum(a[..., 2], b[..., 2]) - np.maximum(a[..., 0], b[..., 0])
    h = np.minimum(a[..., 3], b[..., 3]) - np.maximum(a[..., 1], b[..., 1])
    inter = np.clip(w, 0, None) * np.clip(h, 0, None)
    area = lambda x: (x[..., 2] - x[..., 0]) * (x[..., 3] - x[..., 1])  # noqa: E731
    union = area(a) + area(b) - inter
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = inter / union
    return np.nan_to_num(iou, nan=0.0)


# ------------------------------------------------------------------------------------------------
# Keypoints


class PrecomputedKeypoints:
    """Every person's COCO-17 keypoints per raw frame, from OpenPose JSON files or a COCO file.

    ``source`` is either a folder of per-frame OpenPose JSON files (names ending in the frame
    number, see :func:`embodmocap.io.openpose.keypoint_files`), a COCO keypoint JSON file, or a
    folder holding exactly one JSON file that is a COCO keypoint file. For a COCO file, images are
    mapped to frame numbers by the trailing digits of their ``file_name`` (``images`` list) or, when
    there is none, of their ``image_id``.

    Implements :class:`~embodmocap.perception.roles.KeypointEstimator` (keypoints of given boxes);
    :meth:`people` / :meth:`read` give all people of a frame.

    Attributes:
        source: the folder or file read.
        kind: ``"openpose"`` or ``"coco"``.
        layout: the OpenPose layout (``"BODY_25"`` ...; decided from a sample of the files when not
            given), ``"COCO17"`` for a COCO file, None until a folder's layout is needed.
    """

    name = NAME

    def __init__(self, source: str | Path, layout: str | None = None) -> None:
        self.source = Path(source)
        if layout is not None and layout not in LAYOUT_SIZE:
            raise ValueError(f"unknown keypoint layout {layout!r}; known: {sorted(LAYOUT_SIZE)}")
        self.layout = layout
        self._missing: set[int] = set()
        self._coco: dict[int, NDArray[np.float64]] | None = None
        self._files: dict[int, Path] = {}
        coco_file = self._coco_file()
        if coco_file is not None:
            self.kind = "coco"
            self._coco = _read_coco_by_frame(coco_file)
            self.layout = "COCO17"
        else:
            self.kind = "openpose"
            self._files = keypoint_files(self.source)
        if not self.frames.size:
            log.warning("%s: no keypoint files found", self.source)

    # -- what is there

    @property
    def frames(self) -> NDArray[np.int64]:
        """(F,) sorted frame numbers that have keypoints (a file, or an image of the COCO file)."""
        keys = self._coco.keys() if self._coco is not None else self._files.keys()
        return np.array(sorted(keys), dtype=np.int64)

    @property
    def missing_frames(self) -> list[int]:
        """Sorted frames asked for so far that had no keypoint file (each counted once)."""
        return sorted(self._missing)

    # -- reading

    def people(self, frame: int) -> NDArray[np.float64]:
        """(N, 17, 3) keypoints of every person in raw frame ``frame`` ((0, 17, 3) if none)."""
        frame = int(frame)
        if self._coco is not None:
            kp = self._coco.get(frame)
            if kp is None:
                self._missing.add(frame)
                return np.zeros((0, 17, 3))
            return kp.copy()
        path = self._files.get(frame)
        if path is None:
            self._missing.add(frame)
            return np.zeros((0, 17, 3))
        raw = read_openpose_raw(path)
        if raw.shape[0] == 0:
            return np.zeros((0, 17, 3))
        layout = self._layout_for(raw, path)
        return to_coco17(raw, layout)

    def read(self, frame_ids: Sequence[int]) -> list[NDArray[np.float64]]:
        """:meth:`people` for each frame of ``frame_ids``, in order."""
        return [self.people(f) for f in frame_ids]

    def estimate(self, frames: Sequence[NDArray[np.uint8]], frame_ids: Sequence[int],
                 boxes: Sequence[NDArray[np.float64]]) -> list[NDArray[np.float64]]:
        """Per frame, (N, 17, 3) keypoints of the file's person matching each of the N boxes.

        A box is matched to the person whose keypoint box (:func:`boxes_from_keypoints`) overlaps
        it most (one-to-one, IoU >= 0.3); an unmatched box gets zero keypoints. ``frames`` is not
        looked at (the keypoints were computed elsewhere).
        """
        out = []
        for f, b in zip(frame_ids, boxes):
            b = np.asarray(b, dtype=np.float64).reshape(-1, np.shape(b)[-1] if np.size(b) else 4)
            people = self.people(f)
            result = np.zeros((len(b), 17, 3))
            if len(b) and len(people):
                iou = box_iou(b[:, :4], boxes_from_keypoints(people))
                rows, cols = linear_sum_assignment(-iou)
                keep = iou[rows, cols] >= 0.3
                result[rows[keep]] = people[cols[keep]]
            out.append(result)
        return out

    # -- helpers

    def _coco_file(self) -> Path | None:
        """The COCO file to read, or None for a folder of per-frame OpenPose files."""
        if self.source.is_file():
            return self.source
        if not self.source.is_dir():
            raise InputError(self.source, "keypoint folder or file not found", "check the keypoints path in the manifest")
        jsons = [p for p in self.source.iterdir() if p.suffix.lower() == ".json"]
        if len(jsons) == 1 and looks_like_coco(jsons[0]):
            return jsons[0]
        return None

    def _layout_for(self, raw: NDArray, path: Path) -> str:
        """The folder's layout, decided once (from a spread sample of files) on first need."""
        if self.layout is None:
            K = raw.shape[1]
            if K != 25:
                self.layout = detect_layout([raw], path)
            else:
                # BODY_25 vs BODY_25B is judged from anatomy: use many people, not one frame.
                paths = list(self._files.values())
                pick = np.unique(np.linspace(0, len(paths) - 1, min(_LAYOUT_SAMPLE, len(paths))).astype(int))
                sample = [raw] + [s for s in (read_openpose_raw(paths[i]) for i in pick) if s.size]
                self.layout = detect_layout(sample, self.source)
            log.info("%s: keypoint layout %s", self.source, self.layout)
        if LAYOUT_SIZE[self.layout] != raw.shape[1]:
            raise InputError(path, f"file has {raw.shape[1]} keypoints per person but the folder's layout "
                             f"{self.layout} has {LAYOUT_SIZE[self.layout]}", "keep one pose model per folder")
        return self.layout


class PrecomputedDetector:
    """A :class:`~embodmocap.perception.roles.PersonDetector` from precomputed keypoints.

    Each person with at least ``min_keypoints`` confident points becomes a box
    (:func:`boxes_from_keypoints`, clipped to the frame) scored by the mean confidence of those
    points.
    """

    name = NAME

    def __init__(self, keypoints: PrecomputedKeypoints, conf_thr: float = 0.3, scale: float = 1.2,
                 min_keypoints: int = 3) -> None:
        self.keypoints = keypoints
        self.conf_thr = conf_thr
        self.scale = scale
        self.min_keypoints = min_keypoints

    def detect(self, frames: Sequence[NDArray[np.uint8]], frame_ids: Sequence[int]) -> list[NDArray[np.float64]]:
        """Per frame, (N, 5) rows ``x1, y1, x2, y2, score``; (0, 5) when nobody is there."""
        out = []
        for img, f in zip(frames, frame_ids):
            people = self.keypoints.people(f)
            size = (img.shape[1], img.shape[0]) if isinstance(img, np.ndarray) and img.ndim >= 2 else None
            boxes = boxes_from_keypoints(people, self.conf_thr, self.scale, size)
            ok = people[..., 2] >= self.conf_thr
            score = np.where(ok, people[..., 2], 0.0).sum(-1) / np.maximum(ok.sum(-1), 1)
            keep = ok.sum(-1) >= max(self.min_keypoints, 2)
            out.append(np.concatenate([boxes[keep], score[keep, None]], axis=1).reshape(-1, 5))
        return out


def looks_like_coco(path: Path) -> bool:
    """True when ``path`` is a COCO keypoint file (a results list or an annotations dict)."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096).lstrip()
    except OSError as err:
        raise InputError(path, f"cannot read ({err})", "check the file permissions") from err
    if head.startswith(b"["):
        return True
    return head.startswith(b"{") and b'"people"' not in head and (b'"annotations"' in head or b'"images"' in head)


def _read_coco_by_frame(path: Path) -> dict[int, NDArray[np.float64]]:
    """COCO keypoints keyed by frame number (trailing digits of file name, else of image id)."""
    by_image = read_coco_keypoints(path)
    names: dict = {}
    from embodmocap.io.jsonfile import read_json
    from embodmocap.io.openpose import MAX_COCO_JSON_BYTES

    doc = read_json(path, max_bytes=MAX_COCO_JSON_BYTES, what="COCO keypoint file", fix="re-export the keypoints")
    if isinstance(doc, dict):
        names = {im["id"]: im["file_name"] for im in doc.get("images", [])
                 if isinstance(im, dict) and "id" in im and isinstance(im.get("file_name"), str)}
    out: dict[int, NDArray[np.float64]] = {}
    for image_id, kp in by_image.items():
        label = Path(names[image_id]).stem if image_id in names else str(image_id)
        m = _TRAILING_DIGITS_RE.search(label)
        if m is None:
            raise InputError(path, f"image {image_id!r} has no frame number in its id or file name",
                             "name images by frame number (e.g. 000123.jpg) or use integer image ids")
        frame = int(m.group(1))
        if frame in out:
            raise InputError(path, f"frame {frame} is named by two images (one is {image_id!r})",
                             "keep one image per frame")
        out[frame] = kp
    return out


# ------------------------------------------------------------------------------------------------
# Image-per-frame folders (masks, depth)


def _image_files(folder: Path, suffixes: tuple[str, ...], what: str) -> dict[int, str]:
    """Frame number -> path for files of ``folder`` with one of ``suffixes`` and a frame number."""
    if not folder.is_dir():
        raise InputError(folder, f"{what} folder not found", "check the path in the manifest")
    files: dict[int, str] = {}
    with os.scandir(folder) as it:
        entries = sorted((e.name, e.path) for e in it if e.is_file())
    for fname, fpath in entries:
        stem, dot, suffix = fname.rpartition(".")
        if not dot or f".{suffix.lower()}" not in suffixes:
            continue
        m = _IMAGE_NUMBER_RE.search(stem)
        if m is None:
            continue
        frame = int(m.group(1))
        if frame in files:
            raise InputError(fpath, f"frame {frame} is also named by {Path(files[frame]).name}",
                             f"keep one {what} file per frame")
        files[frame] = fpath
    return files


class _PerFrameFiles:
    """What the per-frame file backends share: ``_files`` (frame -> path) and the frames asked
    for that had no file (``_missing``)."""

    _files: dict[int, Path]
    _missing: set[int]

    @property
    def frames(self) -> NDArray[np.int64]:
        """(F,) sorted frame numbers that have a file."""
        return np.array(sorted(self._files), dtype=np.int64)

    @property
    def missing_frames(self) -> list[int]:
        """Sorted frames asked for so far that had no file (each counted once)."""
        return sorted(self._missing)


class PrecomputedMasks(_PerFrameFiles):
    """Person masks from PNG files named by raw frame number (> 127 = person).

    Implements :class:`~embodmocap.perception.roles.MaskSegmenter` (the boxes are not needed).
    A mask whose size differs from the RGB frame is resized with nearest neighbour (a warning is
    logged once per folder); a frame with no file gives an all-False mask and is counted.
    ``workers`` threads decode the PNGs of one :meth:`segment` batch.
    """

    name = NAME

    def __init__(self, folder: str | Path, workers: int = 2) -> None:
        self.folder = Path(folder)
        # Threads decoding a batch's PNGs: OpenCV releases the GIL while decoding, so two
        # threads nearly double the rate on two cores.
        self.workers = workers
        self._files = _image_files(self.folder, (".png",), "mask")
        self._missing: set[int] = set()
        self._warned_size = False
        # mask() runs on several threads (segment, Stage II): the warn-once flag needs a lock.
        self._warn_lock = threading.Lock()
        if not self._files:
            log.warning("%s: no mask PNGs found", self.folder)

    def mask(self, frame: int, size: tuple[int, int] | None = None) -> NDArray[np.bool_]:
        """(H, W) bool mask of raw frame ``frame``.

        Args:
            frame: raw frame number.
            size: ``(W, H)`` of the RGB frame: the mask is resized to it when different. Required
                for a frame with no file (the empty mask needs a size).
        """
        frame = int(frame)
        path = self._files.get(frame)
        if path is None:
            self._missing.add(frame)
            if size is None:
                raise ValueError(f"frame {frame} has no mask file; pass size=(W, H) for its empty mask")
            return np.zeros((size[1], size[0]), dtype=bool)
        img = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise InputError(path, "not a readable PNG image", "re-export the mask")
        if size is not None and (img.shape[1], img.shape[0]) != tuple(size):
            with self._warn_lock:
                warn, self._warned_size = not self._warned_size, True
            if warn:
                log.warning("%s: masks are %dx%d but frames are %dx%d; resizing (nearest neighbour)",
                            self.folder, img.shape[1], img.shape[0], size[0], size[1])
            img = cv2.resize(img, (int(size[0]), int(size[1])), interpolation=cv2.INTER_NEAREST)
        return img > 127

    def segment(self, frames: Sequence[NDArray[np.uint8]], frame_ids: Sequence[int],
                boxes: NDArray[np.float64] | None = None) -> list[NDArray[np.bool_]]:
        """Per frame, the (H, W) mask at the size of that RGB frame; ``boxes`` are ignored."""
        jobs = [(int(f), (img.shape[1], img.shape[0])) for img, f in zip(frames, frame_ids)]
        if self.workers > 1 and len(jobs) > 1:
            with ThreadPoolExecutor(min(self.workers, len(jobs))) as pool:
                return list(pool.map(lambda job: self.mask(*job), jobs))
        return [self.mask(*job) for job in jobs]


class PrecomputedDepth(_PerFrameFiles):
    """Per-frame depth maps from a folder: uint16 PNG (``value * scale`` metres) or float ``.npy``
    (metres). Non-finite and negative values become 0 (invalid), as everywhere in the package."""

    name = NAME

    def __init__(self, folder: str | Path, scale: float = 0.001) -> None:
        self.folder = Path(folder)
        self.scale = float(scale)
        self._files = _image_files(self.folder, (".png", ".npy"), "depth")
        self._missing: set[int] = set()
        self._shape: tuple[int, int] | None = None
        if not self._files:
            log.warning("%s: no depth files found", self.folder)

    def depth(self, frame: int) -> NDArray[np.float32]:
        """(h, w) float32 depth in metres of raw frame ``frame``, 0 = invalid.

        A frame with no file gives all zeros at the size of the folder's other depth maps.
        """
        frame = int(frame)
        path = self._files.get(frame)
        if path is None:
            self._missing.add(frame)
            return np.zeros(self._reference_shape(), dtype=np.float32)
        d = _read_depth(path, self.scale)
        self._shape = d.shape
        return d

    def read(self, frame_ids: Sequence[int]) -> list[NDArray[np.float32]]:
        """:meth:`depth` for each frame of ``frame_ids``, in order."""
        return [self.depth(f) for f in frame_ids]

    def depth_maps(self, frames, frame_ids: Sequence[int], sensor_depth=None) -> list[NDArray[np.float32]]:
        """The :class:`~embodmocap.perception.roles.DepthEstimator` method: :meth:`read` (the frames
        and the sensor depth are not needed)."""
        return self.read(frame_ids)

    def _reference_shape(self) -> tuple[int, int]:
        if self._shape is None:
            if not self._files:
                raise InputError(self.folder, "no depth files to take the depth size from", "add depth files or drop the depth folder from the manifest")
            self._shape = _read_depth(next(iter(self._files.values())), self.scale).shape
        return self._shape


def _read_depth(path: str, scale: float) -> NDArray[np.float32]:
    """One depth file in metres (float32, 0 = invalid)."""
    if path.lower().endswith(".npy"):
        try:
            d = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as err:
            raise InputError(path, f"not a readable .npy file ({err})", "save depth with numpy.save") from err
        if d.ndim != 2 or d.dtype.kind != "f":
            raise InputError(path, f"depth .npy must be a 2D float array in metres, got {d.dtype} {d.shape}", "save float metres")
        d = d.astype(np.float32)
    else:
        img = cv2.imread(path, cv2.IMREAD_UNCHANGED)
        if img is None:
            raise InputError(path, "not a readable PNG image", "re-export the depth")
        if img.ndim != 2 or img.dtype != np.uint16:
            raise InputError(path, f"depth PNG must be single-channel 16-bit, got {img.dtype} with shape {img.shape}",
                             "write depth as uint16 millimetres")
        d = img.astype(np.float32) * np.float32(scale)
    d[~np.isfinite(d) | (d < 0)] = 0.0
    return d


# ------------------------------------------------------------------------------------------------
# Body prior


class PrecomputedBodyPrior:
    """A camera-space body prior file, looked up by raw frame number.

    Implements :class:`~embodmocap.perception.roles.BodyPriorEstimator`: :meth:`estimate` returns
    rows for the asked frames the file has (its ``frame_ids`` say which) and counts the others in
    ``missing_frames``; :meth:`take` gives one row per asked frame plus a ``found`` flag.
    """

    name = NAME

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.prior: BodyPriorSeq = read_body_prior(self.path)
        ids = self.prior.frame_ids
        order = np.argsort(ids, kind="stable")
        if np.any(np.diff(ids[order]) == 0):
            dup = int(ids[order][np.flatnonzero(np.diff(ids[order]) == 0)[0]])
            raise InputError(self.path, f"frame {dup} appears twice in the body prior", "keep one row per frame")
        self._sorted_ids, self._order = ids[order], order
        self._missing: set[int] = set()

    @property
    def frames(self) -> NDArray[np.int64]:
        """(F,) sorted frame numbers the file has."""
        return self._sorted_ids.copy()

    @property
    def missing_frames(self) -> list[int]:
        """Sorted frames asked for so far that the file lacks (each counted once)."""
        return sorted(self._missing)

    def rows(self, frame_ids: Sequence[int]) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
        """Row of each frame in ``self.prior`` ((T,), -1 where absent) and the (T,) found flags."""
        f = np.asarray(frame_ids, dtype=np.int64).reshape(-1)
        pos = np.clip(np.searchsorted(self._sorted_ids, f), 0, max(len(self._sorted_ids) - 1, 0))
        found = (self._sorted_ids[pos] == f) if len(self._sorted_ids) else np.zeros(len(f), bool)
        self._missing.update(int(x) for x in f[~found])
        return np.where(found, self._order[pos] if len(self._order) else -1, -1), found

    def take(self, frame_ids: Sequence[int]) -> tuple[BodyPriorSeq, NDArray[np.bool_]]:
        """One row per asked frame (zeros where absent) and the (T,) ``found`` flags."""
        f = np.asarray(frame_ids, dtype=np.int64).reshape(-1)
        rows, found = self.rows(f)
        p, r = self.prior, np.where(found, rows, 0)

        def pick(a: NDArray) -> NDArray:
            out = np.zeros((len(f),) + a.shape[1:])
            out[found] = a[r[found]]
            return out

        seq = BodyPriorSeq(pick(p.global_orient_cam), pick(p.body_pose), pick(p.betas), pick(p.transl_cam), f)
        return seq, found

    def estimate(self, frames: Sequence[NDArray[np.uint8]], frame_ids: Sequence[int],
                 boxes: NDArray[np.float64] | None = None) -> BodyPriorSeq:
        """The file's rows for those of ``frame_ids`` it has, in the asked order."""
        rows, found = self.rows(frame_ids)
        p, r = self.prior, rows[found]
        return BodyPriorSeq(p.global_orient_cam[r], p.body_pose[r], p.betas[r], p.transl_cam[r],
                            np.asarray(frame_ids, dtype=np.int64).reshape(-1)[found])
