"""Register performer-view frames into the Stage I sparse model (Stage III, first step).

Each sampled view frame gets a camera pose in the scene's world from 2D-3D matches:

1. SIFT (OpenCV) on the frame's *background*: the person mask, dilated, is handed to the detector
   as an exclusion mask, so no keypoint lies on or next to the performer (who moves and is not in
   the scene model).
2. Candidate key frames: by image retrieval (a bag of visual words built with k-means from the key
   frames' own descriptors, tf-idf weighted; no external vocabulary) or, once a coarse offset is
   known, by pose (key frames that see what the predicted camera sees).
3. Matching with Lowe's ratio test against each candidate's features that observe a 3D point of the
   model; every match is a 2D-3D correspondence.
4. Absolute pose by LO-RANSAC + refinement (``pycolmap``) with the known intrinsics.

Key frame descriptors: the model's keypoints were detected by COLMAP, whose descriptors differ from
OpenCV's in layout. So the descriptors of the key frames' *observations* are recomputed here with
OpenCV at COLMAP's keypoint positions, scales and orientations, making query and key frame
descriptors come from the same code.

Pixel convention: ours puts the top-left pixel's centre at (0, 0); COLMAP's at (0.5, 0.5)
(see :mod:`embodmocap.scene.sfm`). All 2D points this module returns are in ours.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from concurrent.futures import Executor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Mapping, NamedTuple, Sequence

import numpy as np
from numpy.typing import NDArray

from embodmocap.calibrate.config import RegisterConfig
from embodmocap.calibrate.scene_index import (  # noqa: F401 (the scene index's names, also importable from here)
    INDEX_VERSION, SceneIndex, _normalise_rows, _opencv_threads, build_scene_index, load_or_build_scene_index,
    pose_candidates, pose_overlap, retrieve_candidates, scene_index_key,
)
from embodmocap.errors import InputError, require
from embodmocap.geometry.transforms import invert_T
from embodmocap.io.colmap import COLMAP_PIXEL_OFFSET, colmap_camera_params
from embodmocap.parallel import library_threads
from embodmocap.progress import progress
from embodmocap.types import Intrinsics

log = logging.getLogger(__name__)

#: One view frame to register: (sequence frame t, rgb (H, W, 3) uint8, person mask (H, W) bool).
ViewFrame = tuple[int, NDArray[np.uint8], NDArray[np.bool_]]


class FrameFeatures(NamedTuple):
    """The SIFT features of one view frame's background (:func:`frame_features`): what
    :func:`register_frames` needs of a frame, computed once however often the frame is tried.

    Attributes:
        t: sequence frame.
        xy: (n, 2) float64 keypoint positions (our pixel convention).
        desc: (n, 128) float32 unit-norm descriptors.
        seconds: wall time the detection took.
    """

    t: int
    xy: NDArray[np.float64]
    desc: NDArray[np.float32]
    seconds: float


@dataclass(frozen=True)
class Correspondences:
    """Inlier 2D-3D matches of one registered frame (kept for Stage III's reprojection loss).

    Attributes:
        t: sequence frame.
        xy: (N, 2) float64 pixel positions in the view frame, our convention.
        point3D_ids: (N,) int64 COLMAP ids of the matched model points.
        xyz: (N, 3) float64 world positions of those points, metres.
    """

    t: int
    xy: NDArray[np.float64]
    point3D_ids: NDArray[np.int64]
    xyz: NDArray[np.float64]


@dataclass(frozen=True)
class Registration:
    """Registration result of one view.

    Attributes:
        attempted: (A,) int64 sequence frames tried, in the given order.
        attempted_inliers: (A,) int64 pose inliers of each tried frame; 0 where it failed.
        t: (R,) int64 sequence frames registered (inliers >= ``min_inliers``).
        T_world_cam: (R, 4, 4) float64 camera-to-world poses in the scene's world (OpenCV axes).
        inliers: (R,) int64 pose inliers of each registered frame.
        reproj_error_px: (R,) float64 mean reprojection error of the inliers, pixels.
        correspondences: (R,) inlier 2D-3D matches, one per registered frame.
        candidates: (A,) names of the key frames each tried frame was matched against.
        seconds: wall time of ``features``, ``matching`` and ``pose``, summed over frames.
    """

    attempted: NDArray[np.int64]
    attempted_inliers: NDArray[np.int64]
    t: NDArray[np.int64]
    T_world_cam: NDArray[np.float64]
    inliers: NDArray[np.int64]
    reproj_error_px: NDArray[np.float64]
    correspondences: tuple[Correspondences, ...]
    candidates: tuple[tuple[str, ...], ...] = ()
    seconds: dict[str, float] = field(default_factory=dict)

    def merged(self, other: "Registration") -> "Registration":
        """This registration and ``other`` (disjoint frames) as one, sorted by frame."""
        att = np.concatenate([self.attempted, other.attempted])
        ai = np.concatenate([self.attempted_inliers, other.attempted_inliers])
        cands = tuple(self.candidates) + tuple(other.candidates)
        oa = np.argsort(att, kind="stable")
        t = np.concatenate([self.t, other.t])
        o = np.argsort(t, kind="stable")
        corr = tuple(self.correspondences) + tuple(other.correspondences)
        return Registration(
            attempted=att[oa], attempted_inliers=ai[oa], t=t[o],
            T_world_cam=np.concatenate([self.T_world_cam, other.T_world_cam])[o],
            inliers=np.concatenate([self.inliers, other.inliers])[o],
            reproj_error_px=np.concatenate([self.reproj_error_px, other.reproj_error_px])[o],
            correspondences=tuple(corr[i] for i in o),
            candidates=tuple(cands[i] for i in oa) if len(cands) == len(att) else (),
            seconds={k: round(self.seconds.get(k, 0.0) + other.seconds.get(k, 0.0), 3)
                     for k in set(self.seconds) | set(other.seconds)},
        )

    @property
    def registered_fraction(self) -> float:
        """Share of the tried frames that registered (0 when none was tried)."""
        return float(len(self.t) / len(self.attempted)) if len(self.attempted) else 0.0


def background_mask(person_mask: NDArray[np.bool_], dilation_px: int) -> NDArray[np.uint8]:
    """(H, W) uint8 255 where features may be detected: outside the person mask grown by
    ``dilation_px`` pixels (a disc), 0 on and around the person."""
    import cv2

    person = np.asarray(person_mask, dtype=np.uint8)
    if dilation_px > 0:
        r = int(dilation_px)
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        person = cv2.dilate(person, disc)
    return np.where(person > 0, 0, 255).astype(np.uint8)


def detect_background_features(rgb: NDArray[np.uint8], person_mask: NDArray[np.bool_],
                               cfg: RegisterConfig = RegisterConfig()) -> tuple[NDArray[np.float64], NDArray[np.float32]]:
    """SIFT on the background of one frame.

    Returns:
        xy (n, 2) float64 keypoint positions (our pixel convention) and desc (n, 128) float32
        unit-norm descriptors; no keypoint lies within ``cfg.mask_dilation_px`` of the person.
    """
    import cv2

    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise InputError(None, f"view frame is {rgb.dtype} {rgb.shape}, expected (H, W, 3) uint8", "pass RGB frames")
    if np.shape(person_mask) != rgb.shape[:2]:
        raise InputError(None, f"person mask {np.shape(person_mask)} does not match the frame {rgb.shape[:2]}",
                         "pass the mask of the same frame")
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    sift = cv2.SIFT_create(nfeatures=cfg.max_features, contrastThreshold=cfg.contrast_threshold)
    kps, desc = sift.detectAndCompute(gray, background_mask(person_mask, cfg.mask_dilation_px))
    if desc is None or not kps:
        return np.zeros((0, 2)), np.zeros((0, 128), dtype=np.float32)
    xy = np.array([k.pt for k in kps], dtype=np.float64)
    return xy, _normalise_rows(desc.astype(np.float32))


def frame_features(frame: ViewFrame, cfg: RegisterConfig = RegisterConfig()) -> FrameFeatures:
    """:func:`detect_background_features` of one ``(t, rgb, person mask)`` view frame."""
    t, rgb, mask = frame
    t0 = time.perf_counter()
    xy, desc = detect_background_features(rgb, mask, cfg)
    return FrameFeatures(int(t), xy, desc, time.perf_counter() - t0)


def match_to_keyframes(index: SceneIndex, desc: NDArray[np.float32], keyframes: Sequence[int],
                       ratio: float) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """2D-3D matches of a query frame against the observations of some key frames.

    Each key frame is matched on its own (a 3D point appears once per key frame, so the ratio test
    is meaningful there); the union of the matches is returned, duplicates removed.

    Returns:
        (M,) query feature indices and (M,) model point ids.
    """
    q_idx, p_ids = [], []
    for k in keyframes:
        kd = index.descriptors[k]
        if len(kd) < 2 or len(desc) == 0:
            continue
        # Unit vectors: squared distance = 2 - 2 cos, so the two nearest are the two largest
        # cosines (max, mask it, max again: cheaper than a partial sort).
        sim = desc @ kd.T
        rows = np.arange(len(desc))
        best = np.argmax(sim, axis=1)
        first = sim[rows, best]
        sim[rows, best] = -np.inf
        second = np.max(sim, axis=1)
        d1, d2 = np.maximum(2.0 - 2.0 * first, 0.0), np.maximum(2.0 - 2.0 * second, 0.0)
        ok = d1 < (ratio ** 2) * d2
        q_idx.append(rows[ok])
        p_ids.append(index.point3D_ids[k][best[ok]])
    if not q_idx:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    pairs = np.unique(np.column_stack([np.concatenate(q_idx), np.concatenate(p_ids)]), axis=0)
    return pairs[:, 0], pairs[:, 1]


def register_frames(view_frames: Sequence[ViewFrame | FrameFeatures], K: Intrinsics, sfm_dir: str | Path | SceneIndex,
                    cfg: RegisterConfig = RegisterConfig(),
                    predicted_T_world_cam: Mapping[int, NDArray] | None = None,
                    pool: Executor | None = None) -> Registration:
    """Register view frames into the Stage I sparse model.

    Args:
        view_frames: ``(t, rgb (H, W, 3) uint8, person_mask (H, W) bool)`` per frame to try, or its
            :class:`FrameFeatures` when already computed (with ``cfg``'s detection settings).
        K: the view's RGB intrinsics (our pixel convention), at the frames' resolution.
        sfm_dir: the Stage I sparse model folder, or a :class:`SceneIndex` built from it (reuse one
            index for both views).
        cfg: settings.
        predicted_T_world_cam: ``t -> (4, 4)`` predicted camera-to-world poses in the scene's world
            (e.g. VIO poses through a coarse offset); used for ``"pose"`` / ``"auto"`` candidates.
        pool: threads to register the frames on (shared with other work, e.g. the stage's feature
            detection); None: a pool of ``cfg.workers`` threads for this call. The caller keeps
            OpenCV and BLAS on one thread while work of its own runs on a shared pool.

    Returns:
        The :class:`Registration`; frames that fail have 0 inliers in ``attempted_inliers``.
    """
    pycolmap = require("pycolmap", "all")
    index = sfm_dir if isinstance(sfm_dir, SceneIndex) else build_scene_index(sfm_dir, cfg)
    if cfg.candidates == "pose" and predicted_T_world_cam is None:
        raise ValueError('candidates="pose" needs predicted_T_world_cam')
    camera = pycolmap.Camera(model="PINHOLE", width=K.width, height=K.height, params=colmap_camera_params(K))
    est = pycolmap.AbsolutePoseEstimationOptions()
    est.ransac.max_error = cfg.ransac_max_error_px
    est.ransac.min_inlier_ratio = cfg.min_inlier_ratio
    est.ransac.random_seed = cfg.seed
    predicted = dict(predicted_T_world_cam or {})

    def one(frame: ViewFrame | FrameFeatures):
        t, xy, desc, detect_s = frame if isinstance(frame, FrameFeatures) else frame_features(frame, cfg)
        t1 = time.perf_counter()
        chosen = _choose(index, desc, K, cfg, predicted.get(t))
        q_idx, p_ids = match_to_keyframes(index, desc, chosen, cfg.ratio)
        t2 = time.perf_counter()
        res = _absolute_pose(pycolmap, camera, est, xy[q_idx], p_ids, index, cfg) if len(q_idx) >= 4 else None
        t3 = time.perf_counter()
        log.debug("frame %d: %d features, %d matches, %d inliers", t, len(xy), len(q_idx), 0 if res is None else len(res[1]))
        return t, xy, chosen, q_idx, p_ids, res, (detect_s, t2 - t1, t3 - t2)

    # Each frame is registered on its own with a fixed RANSAC seed and single-threaded OpenCV (its
    # SIFT keeps the strongest features, and with several internal threads the order of equally
    # strong ones could vary); the pool's map returns results in the frames' order, so the result
    # does not depend on the thread count or on which thread finishes first.
    frames = list(view_frames)
    workers = max(1, min(cfg.workers or (os.cpu_count() or 1), len(frames)))
    # BLAS on one thread too (the matching's products): each pool thread running a multi-threaded
    # OpenBLAS product oversubscribes the cores, and OpenBLAS's waiting threads spin (measured:
    # matching products in a 2-thread pool cost 2.3x the CPU; same results).
    with one_library_thread():
        if pool is not None:
            outs = list(progress(pool.map(one, frames), "registration", total=len(frames), unit="frame"))
        elif workers > 1:
            from concurrent.futures import ThreadPoolExecutor

            with ThreadPoolExecutor(workers) as pool:
                outs = list(progress(pool.map(one, frames), "registration", total=len(frames), unit="frame"))
        else:
            outs = [one(f) for f in progress(frames, "registration", unit="frame")]
    seconds = {"features": 0.0, "matching": 0.0, "pose": 0.0}
    attempted, counts, cands, results = [], [], [], []
    for t, xy, chosen, q_idx, p_ids, res, dt in outs:
        for k, d in zip(("features", "matching", "pose"), dt):
            seconds[k] += d
        attempted.append(t)
        cands.append(tuple(index.names[i] for i in chosen))
        n = 0 if res is None else len(res[1])
        counts.append(n)
        if res is not None and n >= cfg.min_inliers:
            T, inl = res
            results.append((len(attempted) - 1, t, T, q_idx[inl], p_ids[inl], xy))
    return _collect(attempted, counts, cands, results, index, K, cfg, seconds)


@contextlib.contextmanager
def one_library_thread() -> Iterator[None]:
    """OpenCV and BLAS on one thread inside (restored after), as :func:`register_frames` runs its
    frames: each frame is registered on one thread, so its result does not depend on the thread
    count. A caller whose own work of this kind shares the threads (the stage's feature detection
    and key frame descriptors) holds it around all of that."""
    with _opencv_threads(1), library_threads(1, ("blas",)):
        yield


def _choose(index: SceneIndex, desc: NDArray, K: Intrinsics, cfg: RegisterConfig,
            predicted: NDArray | None) -> NDArray[np.int64]:
    use_pose = predicted is not None and cfg.candidates in ("pose", "auto")
    if use_pose:
        return pose_candidates(index, predicted[None], K, cfg.num_candidates, cfg.max_view_angle_deg,
                               cfg.pose_probe_depths_m)[0]
    return retrieve_candidates(index, desc, cfg.num_candidates)


def _absolute_pose(pycolmap, camera, est, xy: NDArray, p_ids: NDArray, index: SceneIndex,
                   cfg: RegisterConfig) -> tuple[NDArray, NDArray[np.int64]] | None:
    """(T_world_cam (4, 4), inlier indices into the matches) or None when RANSAC finds nothing."""
    xyz = np.stack([index.xyz_by_id[int(i)] for i in p_ids])
    res = pycolmap.estimate_and_refine_absolute_pose(xy + COLMAP_PIXEL_OFFSET, xyz, camera, est)
    if res is None:
        return None
    P = np.eye(4)
    P[:3, :4] = res["cam_from_world"].matrix()
    return invert_T(P), np.flatnonzero(np.asarray(res["inlier_mask"], dtype=bool))


def _collect(attempted, counts, cands, results, index: SceneIndex, K: Intrinsics, cfg: RegisterConfig,
             seconds: dict[str, float]) -> Registration:
    corrs, errs, kept = [], [], []
    for pos, t, T, qi, pid, xy in results:
        xyz = np.stack([index.xyz_by_id[int(i)] for i in pid])
        err = np.linalg.norm(project(K, T, xyz) - xy[qi], axis=-1)
        # RANSAC judged inliers before the refinement moved the pose: keep those still within bounds.
        ok = err <= cfg.ransac_max_error_px
        counts[pos] = int(ok.sum())
        if ok.sum() < cfg.min_inliers:
            continue
        kept.append((t, T, int(ok.sum())))
        errs.append(float(np.mean(err[ok])))
        corrs.append(Correspondences(t, xy[qi[ok]].copy(), pid[ok].astype(np.int64), xyz[ok]))
    results = kept
    reg = Registration(
        attempted=np.asarray(attempted, dtype=np.int64),
        attempted_inliers=np.asarray(counts, dtype=np.int64),
        t=np.asarray([r[0] for r in results], dtype=np.int64),
        T_world_cam=np.stack([r[1] for r in results]) if results else np.zeros((0, 4, 4)),
        inliers=np.asarray([r[2] for r in results], dtype=np.int64),
        reproj_error_px=np.asarray(errs, dtype=np.float64),
        correspondences=tuple(corrs),
        candidates=tuple(cands),
        seconds={k: round(v, 3) for k, v in seconds.items()},
    )
    log.info("registered %d of %d frames (%.1f s features, %.1f s matching, %.1f s pose)", len(reg.t),
             len(reg.attempted), seconds["features"], seconds["matching"], seconds["pose"])
    return reg


def project(K: Intrinsics, T_world_cam: NDArray, xyz: NDArray) -> NDArray[np.float64]:
    """(N, 2) pixels (our convention) of world points ``xyz`` (N, 3) seen by camera ``T_world_cam``."""
    T_cam_world = invert_T(np.asarray(T_world_cam, dtype=np.float64))
    p = np.asarray(xyz, dtype=np.float64) @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    return np.column_stack([K.fx * p[:, 0] / p[:, 2] + K.cx, K.fy * p[:, 1] / p[:, 2] + K.cy])


# ------------------------------------------------------------------------------------------------
# Reading view frames from Stage II outputs


def sample_frames(num_total: int, num: int) -> NDArray[np.int64]:
    """(<= num,) sequence frames spread evenly over ``0..num_total-1``, first and last included."""
    if num_total <= 0 or num <= 0:
        return np.zeros(0, dtype=np.int64)
    if num_total <= num:
        return np.arange(num_total, dtype=np.int64)
    return np.unique(np.linspace(0, num_total - 1, num).round().astype(np.int64))


def select_frames(T_vio_cam: NDArray, num: int, step_m: float = 0.05, step_deg: float = 3.0,
                  step_s: float = 0.2, fps: float = 30.0) -> NDArray[np.int64]:
    """(<= num,) sequence frames spread over time and over viewpoints, the steadiest of each stretch.

    Every frame gets a "progress" along the recording: ``1/step_s`` per second plus ``1/step_m``
    per metre of VIO path plus ``1/step_deg`` per degree turned, so a view that stands still
    spends few samples and one that walks or pans gets more. The progress is cut into ``num``
    equal stretches and from each the frame turning slowest (least motion blur; VIO rotation
    rate) is taken. First and last frames are always candidates; no image is read.

    Args:
        T_vio_cam: (T, 4, 4) VIO camera-to-world of every sequence frame.
        num: how many frames at most.
    """
    T = np.asarray(T_vio_cam, dtype=np.float64)
    n = len(T)
    if n == 0 or num <= 0:
        return np.zeros(0, dtype=np.int64)
    if n <= num:
        return np.arange(n, dtype=np.int64)
    from embodmocap.geometry.transforms import rotation_angle

    ok = np.all(np.isfinite(T.reshape(n, -1)), axis=1)
    Tf = np.where(ok[:, None, None], T, np.eye(4))
    dist = np.r_[0.0, np.linalg.norm(np.diff(Tf[:, :3, 3], axis=0), axis=1)]
    ang = np.r_[0.0, np.degrees(rotation_angle(np.swapaxes(Tf[:-1, :3, :3], -1, -2) @ Tf[1:, :3, :3]))]
    dist[~ok] = 0.0
    ang[~ok] = 0.0
    progress = np.cumsum(1.0 / (step_s * fps) + dist / step_m + ang / step_deg)
    # Steadiness: turn of the step into and out of each frame (blur comes from rotation).
    rate = np.maximum(ang, np.r_[ang[1:], 0.0])
    rate[~ok] = np.inf
    edges = np.linspace(progress[0], progress[-1], num + 1)
    bucket = np.clip(np.searchsorted(edges, progress, side="right") - 1, 0, num - 1)
    order = np.lexsort((np.arange(n), rate, bucket))  # per bucket: steadiest first, then earliest
    first = np.r_[True, bucket[order][1:] != bucket[order][:-1]]
    picked = order[first]
    picked = picked[np.isfinite(rate[picked])]
    return np.unique(picked).astype(np.int64)


def load_view_frames(view_layout, capture, ts: Sequence[int]) -> tuple[list[ViewFrame], Intrinsics, NDArray]:
    """The frames ``ts`` of one Stage II view, ready for :func:`register_frames`.

    Args:
        view_layout: ``SessionLayout(root).sequence(seq).view(v)`` (reads ``cameras.npz`` and
            ``masks.npy``).
        capture: the view's raw capture (:func:`embodmocap.io.captures.open_capture`).
        ts: sequence frames to load.

    Returns:
        (view frames, RGB intrinsics, (T, 4, 4) VIO camera-to-world of every sequence frame).
    """
    from embodmocap.io.frame_stack import read_mask
    from embodmocap.io.stage_files import read_cameras

    cams = read_cameras(view_layout.cameras, "cameras")
    K = Intrinsics.from_K(cams["K"], int(cams["width"]), int(cams["height"]))
    raw = np.asarray(cams["raw_frames"], dtype=np.int64)
    frames = [(int(t), np.asarray(capture.frames.rgb(int(raw[t]))), read_mask(view_layout.masks, int(t), K.width))
              for t in ts]
    return frames, K, np.asarray(cams["T_world_cam"], dtype=np.float64)
