"""2D keypoints in the formats people already have: OpenPose per-frame JSON and COCO keypoint JSON.

Everything is returned in the package's COCO-17 order (:data:`embodmocap.types.COCO17_NAMES`) as
``(x_px, y_px, confidence)``; confidence 0 means "not detected" (OpenPose writes 0, 0, 0 there).

OpenPose layouts understood (index -> name of the detector's output):

- ``COCO17``: the 17 COCO points in COCO order (what the synthetic studio writes).
- ``COCO18`` (OpenPose "COCO" model): Nose, Neck, RShoulder, RElbow, RWrist, LShoulder, LElbow,
  LWrist, RHip, RKnee, RAnkle, LHip, LKnee, LAnkle, REye, LEye, REar, LEar.
- ``BODY_25`` (OpenPose default): Nose, Neck, RShoulder, RElbow, RWrist, LShoulder, LElbow,
  LWrist, MidHip, RHip, RKnee, RAnkle, LHip, LKnee, LAnkle, REye, LEye, REar, LEar, LBigToe,
  LSmallToe, LHeel, RBigToe, RSmallToe, RHeel.
- ``BODY_25B`` (openpose_train experimental model, used by Pose2Sim): the 17 COCO points in COCO
  order, then UpperNeck, HeadTop, LBigToe, LSmallToe, LHeel, RBigToe, RSmallToe, RHeel.

With 25 points the two 25-point layouts are told apart from the data (see :func:`detect_layout`).
"""

from __future__ import annotations

import logging
import re
import warnings
from pathlib import Path
from typing import Iterable, Literal, Sequence

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.io.atomic import write_json
from embodmocap.io.jsonfile import read_json
from embodmocap.types import Keypoints2D

log = logging.getLogger(__name__)

Layout = Literal["COCO17", "COCO18", "BODY_25", "BODY_25B"]

#: For each layout, the index of every COCO-17 point (in COCO-17 order) in the detector's output.
COCO17_FROM: dict[str, tuple[int, ...]] = {
    "COCO17": tuple(range(17)),
    "BODY_25B": tuple(range(17)),
    #           nose  leye reye lear rear lsho rsho lelb relb lwri rwri lhip rhip lkne rkne lank rank
    "COCO18": (0, 15, 14, 17, 16, 5, 2, 6, 3, 7, 4, 11, 8, 12, 9, 13, 10),
    "BODY_25": (0, 16, 15, 18, 17, 5, 2, 6, 3, 7, 4, 12, 9, 13, 10, 14, 11),
}

#: Number of points each layout has.
LAYOUT_SIZE: dict[str, int] = {"COCO17": 17, "COCO18": 18, "BODY_25": 25, "BODY_25B": 25}

#: Trailing frame number of a keypoint file: ``*_000012_keypoints.json``, ``000012_keypoints.json``,
#: ``cam01.0012.json``, ``frame12.json``.
_FRAME_RE = re.compile(r"(\d+)(?:_keypoints)?\.json$", re.IGNORECASE)

#: Largest OpenPose per-frame JSON accepted: one frame of even a crowd (100 people, 25 points,
#: hands and face) is well under 1 MiB; a bigger file is not a keypoint file.
MAX_FRAME_JSON_BYTES = 4 << 20
#: Largest COCO keypoint file (every frame of a sequence in one file) accepted: ~1 KB per person
#: and frame, so 256 MiB covers hours of 60 fps video.
MAX_COCO_JSON_BYTES = 256 << 20

#: Points below this confidence are ignored when judging a layout or a person's size.
_CONF_MIN = 0.1
#: Largest relative midpoint offset accepted when one profile test alone decides the layout.
_PROFILE_MIDPOINT_TOL = 0.1


# --------------------------------------------------------------------------------------------
# OpenPose JSON
# --------------------------------------------------------------------------------------------


def write_openpose_json(path: str | Path, people: Sequence[NDArray]) -> Path:
    """Write one frame's people as OpenPose JSON (``version`` 1.3), atomically.

    Args:
        path: destination file (``NNNNNN_keypoints.json`` in a session).
        people: one (K, 3) array per person: x px, y px, confidence; K is the layout's size
            (17 for the COCO-17 layout the studio writes). An empty list writes ``"people": []``.
    """
    entries = []
    for kp in people:
        kp = np.asarray(kp, dtype=np.float64)
        if kp.ndim != 2 or kp.shape[1] != 3:
            raise ValueError(f"each person must be (K, 3), got {kp.shape}")
        entries.append({
            "person_id": [-1],
            "pose_keypoints_2d": [float(v) for v in kp.reshape(-1)],
            "face_keypoints_2d": [], "hand_left_keypoints_2d": [], "hand_right_keypoints_2d": [],
            "pose_keypoints_3d": [], "face_keypoints_3d": [], "hand_left_keypoints_3d": [],
            "hand_right_keypoints_3d": [],
        })
    path = Path(path)
    write_json(path, {"version": 1.3, "people": entries}, indent=None)
    return path


def read_openpose_raw(path: str | Path) -> NDArray[np.float64]:
    """The people of one OpenPose JSON file in the detector's own layout: (P, K, 3).

    Raises:
        InputError: unreadable JSON, no ``people`` list, a keypoint list whose length is not a
            multiple of 3, or people with different point counts.
    """
    path = Path(path)
    doc = read_json(path, max_bytes=MAX_FRAME_JSON_BYTES, what="keypoint file", fix="re-export the keypoints")
    if not isinstance(doc, dict) or not isinstance(doc.get("people"), list):
        raise InputError(path, "no 'people' list: not an OpenPose JSON file", "export with OpenPose --write_json")
    arrays = []
    for i, person in enumerate(doc["people"]):
        flat = person.get("pose_keypoints_2d") if isinstance(person, dict) else None
        if not isinstance(flat, list) or len(flat) % 3 != 0 or not flat:
            raise InputError(path, f"person {i}: 'pose_keypoints_2d' must be a non-empty flat list of x, y, c triples", "re-export the keypoints")
        try:
            arrays.append(np.asarray(flat, dtype=np.float64).reshape(-1, 3))
        except (TypeError, ValueError) as err:
            raise InputError(path, f"person {i}: non-numeric keypoint values", "re-export the keypoints") from err
    if not arrays:
        return np.zeros((0, 0, 3))
    counts = {len(a) for a in arrays}
    if len(counts) > 1:
        raise InputError(path, f"people have different keypoint counts {sorted(counts)}", "use one pose model per file")
    out = np.stack(arrays)
    if not np.all(np.isfinite(out)):
        raise InputError(path, "keypoints hold NaN or infinite values", "re-export the keypoints")
    return out


def to_coco17(raw: NDArray, layout: str) -> NDArray[np.float64]:
    """Map (..., K, 3) points of ``layout`` to (..., 17, 3) COCO-17 order."""
    if layout not in COCO17_FROM:
        raise ValueError(f"unknown keypoint layout {layout!r}; known: {sorted(COCO17_FROM)}")
    raw = np.asarray(raw, dtype=np.float64)
    if raw.shape[-2] != LAYOUT_SIZE[layout]:
        raise ValueError(f"layout {layout} has {LAYOUT_SIZE[layout]} points, data has {raw.shape[-2]}")
    return raw[..., list(COCO17_FROM[layout]), :]


def detect_layout(people: Iterable[NDArray], path: str | Path | None = None) -> str:
    """Guess the layout of a set of (P, K, 3) arrays (one file each, same detector).

    17 points -> ``COCO17``; 18 -> ``COCO18``; 25 -> ``BODY_25`` or ``BODY_25B``, decided by the
    anatomy over every confident person: in BODY_25 the neck (1) lies midway between the shoulders
    (2, 5) and the mid-hip (8) midway between the hips (9, 12); in BODY_25B points 1 and 2 are the
    eyes (next to the nose 0) and the upper neck (17) lies midway between the shoulders (5, 6).
    Distances are relative to the person's size, and the median over all people decides, so a few
    bad detections do not flip the answer.

    Raises:
        InputError: an unsupported point count, mixed counts, or 25 points with no person
            confident enough to decide (then pass ``layout=`` explicitly).
    """
    arrays = [np.asarray(p, dtype=np.float64) for p in people]
    arrays = [a for a in arrays if a.size]
    if not arrays:
        raise InputError(path, "no detected people to infer the keypoint layout from", "pass the layout explicitly")
    counts = {a.shape[1] for a in arrays}
    if len(counts) > 1:
        raise InputError(path, f"files mix keypoint counts {sorted(counts)}", "keep one pose model per folder")
    K = counts.pop()
    if K == 17:
        return "COCO17"
    if K == 18:
        return "COCO18"
    if K != 25:
        raise InputError(path, f"{K} keypoints per person is not a supported layout", "use COCO-17, COCO-18, BODY_25 or BODY_25B")
    kp = np.concatenate(arrays)  # (N, 25, 3)
    s25 = _midpoint_score(kp, 1, 2, 5) + _midpoint_score(kp, 8, 9, 12)
    s25b = _near_score(kp, 1, 0) + _near_score(kp, 2, 0) + _midpoint_score(kp, 17, 5, 6)
    ok = np.isfinite(s25) & np.isfinite(s25b)
    if not ok.any():
        return _profile_layout(kp, path)
    m25, m25b = float(np.median(s25[ok])), float(np.median(s25b[ok]))
    layout = "BODY_25" if m25 < m25b else "BODY_25B"
    log.debug("25-point layout scores: BODY_25 %.3f, BODY_25B %.3f -> %s", m25, m25b, layout)
    return layout


def read_openpose_json(path: str | Path, layout: str | None = None) -> NDArray[np.float64]:
    """Read one OpenPose JSON file as (P, 17, 3) COCO-17 points (P may be 0).

    Args:
        path: the file.
        layout: ``"COCO17"``, ``"COCO18"``, ``"BODY_25"``, ``"BODY_25B"`` or None to detect it
            from this file alone (for a folder prefer :func:`read_keypoint_folder`, which decides
            once over all files).
    """
    raw = read_openpose_raw(path)
    if raw.shape[0] == 0:
        return np.zeros((0, 17, 3))
    layout = layout or detect_layout([raw], path)
    _check_layout(layout, raw.shape[1], path)
    return to_coco17(raw, layout)


def keypoint_files(folder: str | Path) -> dict[int, Path]:
    """Frame number -> file for every ``*.json`` in ``folder`` named by a trailing frame number.

    Raises:
        InputError: missing folder, or two files naming the same frame.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(folder, "keypoint folder not found", "check the path in the manifest")
    files: dict[int, Path] = {}
    for p in sorted(folder.glob("*.json")):
        m = _FRAME_RE.search(p.name)
        if m is None:
            continue
        frame = int(m.group(1))
        if frame in files:
            raise InputError(p, f"frame {frame} is also named by {files[frame].name}", "keep one keypoint file per frame")
        files[frame] = p
    return files


def read_keypoint_folder(
    folder: str | Path,
    frame_ids: Sequence[int] | NDArray,
    layout: str | None = None,
    pick: Literal["largest", "first", "confident"] = "largest",
) -> tuple[Keypoints2D, list[int]]:
    """Read one person's COCO-17 keypoints for ``frame_ids`` from a folder of OpenPose JSON files.

    Args:
        folder: folder of per-frame JSON files (any of the names :func:`keypoint_files` accepts).
        frame_ids: the frames wanted, in order.
        layout: the detector's layout, or None to detect it once over the whole folder.
        pick: which person to keep when a file holds several: ``"largest"`` (biggest box of
            confident points), ``"first"`` (the file's first) or ``"confident"`` (highest mean
            confidence).

    Returns:
        ``(keypoints, missing)``: keypoints (T, 17, 3) with frame_ids as given; ``missing`` lists
        the frames with no file or no person (their rows are all zero, confidence 0).
    """
    frame_ids = np.asarray(frame_ids, dtype=np.int64).reshape(-1)
    files = keypoint_files(folder)
    raws = {int(f): read_openpose_raw(files[int(f)]) for f in np.unique(frame_ids) if int(f) in files}
    present = [r for r in raws.values() if r.shape[0]]
    if layout is None and present:
        layout = detect_layout(present, folder)
    data = np.zeros((len(frame_ids), 17, 3))
    missing: list[int] = []
    for row, f in enumerate(frame_ids):
        raw = raws.get(int(f))
        if raw is None or raw.shape[0] == 0:
            missing.append(int(f))
            continue
        _check_layout(layout, raw.shape[1], files[int(f)])
        data[row] = to_coco17(raw[_pick_person(raw, pick)], layout)
    if missing:
        log.info("%s: %d of %d frames have no keypoints", folder, len(missing), len(frame_ids))
    return Keypoints2D(data, frame_ids), missing


# --------------------------------------------------------------------------------------------
# COCO keypoint JSON
# --------------------------------------------------------------------------------------------


def read_coco_keypoints(path: str | Path) -> dict[int | str, NDArray[np.float64]]:
    """Read a COCO keypoint file: image id -> (P, 17, 3) points in COCO-17 order.

    Accepts the two standard shapes:

    - annotations (``{"images": ..., "annotations": [{"image_id", "keypoints": [x, y, v] * 17,
      ...}]}``): the visibility flag ``v`` becomes confidence 1 where labelled (v = 1 or 2) and 0
      where not labelled (v = 0);
    - results (``[{"image_id", "category_id", "keypoints": [x, y, score] * 17, "score"}, ...]``):
      the per-point score is kept as the confidence.

    Images listed under ``"images"`` with no annotation map to an empty (0, 17, 3) array.

    Raises:
        InputError: unreadable JSON, neither shape, or a keypoint list that is not 51 numbers.
    """
    path = Path(path)
    doc = read_json(path, max_bytes=MAX_COCO_JSON_BYTES, what="COCO keypoint file", fix="re-export the keypoints")
    if isinstance(doc, dict) and isinstance(doc.get("annotations"), list):
        entries, is_annotation = doc["annotations"], True
        image_ids = [im.get("id") for im in doc.get("images", []) if isinstance(im, dict)]
    elif isinstance(doc, list):
        entries, is_annotation, image_ids = doc, False, []
    else:
        raise InputError(path, "neither a COCO annotation file nor a COCO results list", "export in COCO keypoint format")
    people: dict[int | str, list[NDArray]] = {i: [] for i in image_ids if i is not None}
    for n, e in enumerate(entries):
        if not isinstance(e, dict) or "image_id" not in e or "keypoints" not in e:
            raise InputError(path, f"entry {n} lacks 'image_id' or 'keypoints'", "export in COCO keypoint format")
        try:
            kp = np.asarray(e["keypoints"], dtype=np.float64)
        except (TypeError, ValueError) as err:
            raise InputError(path, f"entry {n}: non-numeric keypoints", "re-export the keypoints") from err
        if kp.shape != (51,):
            raise InputError(path, f"entry {n}: 'keypoints' has {kp.size} numbers, COCO-17 needs 51", "use a COCO-17 keypoint model")
        kp = kp.reshape(17, 3)
        if is_annotation:
            kp[:, 2] = (kp[:, 2] > 0).astype(np.float64)
        people.setdefault(e["image_id"], []).append(kp)
    return {k: (np.stack(v) if v else np.zeros((0, 17, 3))) for k, v in people.items()}


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------


def _check_layout(layout: str | None, K: int, path: Path) -> None:
    if layout not in LAYOUT_SIZE:
        raise InputError(path, f"unknown keypoint layout {layout!r}", f"use one of {sorted(LAYOUT_SIZE)}")
    if LAYOUT_SIZE[layout] != K:
        raise InputError(path, f"file has {K} keypoints per person but layout {layout} has {LAYOUT_SIZE[layout]}", "pass the right layout")


def _person_scale(kp: NDArray) -> NDArray:
    """(N,) diagonal of the box around each person's confident points, px (nan if < 2 points)."""
    ok = kp[..., 2] > _CONF_MIN
    xy = np.where(ok[..., None], kp[..., :2], np.nan)
    with warnings.catch_warnings():  # people with no confident point give all-NaN slices
        warnings.simplefilter("ignore", RuntimeWarning)
        ext = np.nanmax(xy, axis=-2) - np.nanmin(xy, axis=-2)
    scale = np.linalg.norm(ext, axis=-1)
    return np.where(ok.sum(-1) >= 2, scale, np.nan)


def _profile_layout(kp: NDArray, path: str | Path | None) -> str:
    """BODY_25 vs BODY_25B from tests a profile view passes (it never shows both eyes).

    In BODY_25 point 8 (mid-hip) lies midway between the hips 9 and 12; in BODY_25B point 17
    (upper neck) lies midway between the shoulders 5 and 6. The smaller median wins; when only one
    test has its points, it decides alone if its point is clearly at the midpoint.
    """
    scores = {}
    for name, (mid, a, b) in (("BODY_25", (8, 9, 12)), ("BODY_25B", (17, 5, 6))):
        d = _midpoint_score(kp, mid, a, b)
        d = d[np.isfinite(d)]
        if d.size:
            scores[name] = float(np.median(d))
    if len(scores) == 2:
        return min(scores, key=scores.get)
    if len(scores) == 1 and next(iter(scores.values())) < _PROFILE_MIDPOINT_TOL:
        return next(iter(scores))
    raise InputError(path, "cannot tell BODY_25 from BODY_25B: no confident person", "pass layout='BODY_25' or 'BODY_25B'")


def _midpoint_score(kp: NDArray, mid: int, a: int, b: int) -> NDArray:
    """(N,) distance of point ``mid`` from the midpoint of ``a`` and ``b``, over person size."""
    d = np.linalg.norm(kp[:, mid, :2] - 0.5 * (kp[:, a, :2] + kp[:, b, :2]), axis=-1)
    ok = np.all(kp[:, [mid, a, b], 2] > _CONF_MIN, axis=1)
    return np.where(ok, d / _person_scale(kp), np.nan)


def _near_score(kp: NDArray, i: int, j: int) -> NDArray:
    """(N,) distance between points ``i`` and ``j`` over person size."""
    d = np.linalg.norm(kp[:, i, :2] - kp[:, j, :2], axis=-1)
    ok = (kp[:, i, 2] > _CONF_MIN) & (kp[:, j, 2] > _CONF_MIN)
    return np.where(ok, d / _person_scale(kp), np.nan)


def _pick_person(raw: NDArray, pick: str) -> int:
    if pick == "first" or len(raw) == 1:
        return 0
    if pick == "largest":
        return int(np.nanargmax(np.nan_to_num(_person_scale(raw), nan=-1.0)))
    if pick == "confident":
        return int(np.argmax(raw[..., 2].mean(-1)))
    raise ValueError(f"unknown pick {pick!r}: use 'largest', 'first' or 'confident'")

