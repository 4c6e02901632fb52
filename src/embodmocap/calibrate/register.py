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

import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError, require
from embodmocap.geometry.transforms import invert_T
from embodmocap.io.colmap import COLMAP_PIXEL_OFFSET, colmap_camera_params, intrinsics_from_colmap
from embodmocap.types import Intrinsics

log = logging.getLogger(__name__)

#: One view frame to register: (sequence frame t, rgb (H, W, 3) uint8, person mask (H, W) bool).
ViewFrame = tuple[int, NDArray[np.uint8], NDArray[np.bool_]]


@dataclass(frozen=True)
class RegisterConfig:
    """Settings of view-frame registration. Defaults register 2 x 200 frames at 640x480 in about a
    minute on 2 CPU cores."""

    num_frames: int = 80
    """Frames sampled per view by :func:`select_frames`: spread over time and over viewpoints
    (the VIO path and turn), the steadiest frame of each stretch (least blur). A 6 s view has
    about 175 frames, a 60 s one 1,800. The offset has 4 parameters and the per-view error is
    dominated by a bias common to the view's frames, not by their number: beyond ~80 well spread
    frames more only cost time (SIFT is most of Stage III's time)."""
    workers: int = 0
    """Threads registering frames in parallel (0 = one per CPU core). OpenCV and pycolmap release
    the GIL; each frame's result does not depend on the thread count or order."""
    coarse_frames: int = 24
    """Frames registered first by retrieval; their VIO-consistent poses give a coarse offset from
    which the other frames get their candidate key frames by pose (:func:`pose_candidates`)."""
    max_features: int = 2048
    """SIFT features kept per query frame (the strongest)."""
    contrast_threshold: float = 0.03
    """OpenCV SIFT contrast threshold (lower = more, weaker features; OpenCV's default is 0.04)."""
    mask_dilation_px: int = 10
    """The person mask is grown by this many pixels before features are excluded, so that no
    descriptor window reaches into the performer."""
    num_candidates: int = 8
    """Scene key frames each query frame is matched against."""
    candidates: Literal["auto", "retrieval", "pose"] = "auto"
    """How candidate key frames are chosen: ``"retrieval"`` = most similar bag of visual words;
    ``"pose"`` = key frames whose view overlaps the query's predicted view (needs predicted poses);
    ``"auto"`` = pose where a prediction is given, retrieval elsewhere."""
    vocabulary_size: int = 256
    """Visual words of the retrieval vocabulary (k-means over the key frames' descriptors)."""
    vocabulary_samples: int = 20000
    """At most this many key frame descriptors (random) train the vocabulary."""
    max_view_angle_deg: float = 75.0
    """``"pose"`` candidates: key frames whose optical axis differs from the predicted one by more
    than this are never candidates."""
    pose_probe_depths_m: tuple[float, ...] = (1.5, 3.0, 5.0)
    """``"pose"`` candidates: depths (metres) of the probe points cast from the predicted camera
    (:func:`pose_overlap`); room scale by default."""
    ratio: float = 0.8
    """Lowe's ratio test: a match is kept when its distance is below ``ratio`` x the second best."""
    ransac_max_error_px: float = 6.0
    """Absolute pose RANSAC: largest reprojection error (pixels) of an inlier."""
    min_inliers: int = 20
    """A frame with fewer pose inliers counts as not registered."""
    min_inlier_ratio: float = 0.1
    """RANSAC's lowest accepted inlier share of the matches (COLMAP's option)."""
    seed: int = 0
    """Seed of the vocabulary's k-means and of RANSAC, so that runs repeat exactly."""


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


@dataclass(frozen=True)
class SceneIndex:
    """The Stage I model prepared for registration (build once, use for both views).

    Attributes:
        sfm_dir: the Stage I sparse model folder.
        names: (K,) key frame names.
        T_world_cam: (K, 4, 4) key frame camera-to-world poses from the model.
        intrinsics: the key frames' camera, our pixel convention.
        descriptors: (K,) per key frame (n_k, 128) float32 unit-norm OpenCV SIFT descriptors of its
            observations (features with a 3D point).
        point3D_ids: (K,) per key frame (n_k,) int64 model point of each descriptor.
        xyz_by_id: ``point3D id -> (3,)`` world position, metres.
        vocabulary: (V, 128) float32 visual words.
        idf: (V,) float64 inverse document frequency of each word.
        bow: (K, V) float64 L2-normalised tf-idf histograms of the key frames.
    """

    sfm_dir: Path
    names: tuple[str, ...]
    T_world_cam: NDArray[np.float64]
    intrinsics: Intrinsics
    descriptors: tuple[NDArray[np.float32], ...]
    point3D_ids: tuple[NDArray[np.int64], ...]
    xyz_by_id: Mapping[int, NDArray[np.float64]]
    vocabulary: NDArray[np.float32]
    idf: NDArray[np.float64]
    bow: NDArray[np.float64]


# ------------------------------------------------------------------------------------------------
# Scene index


INDEX_VERSION = 1


def scene_index_key(sfm_dir: str | Path, cfg: RegisterConfig = RegisterConfig()) -> str:
    """Fingerprint of what a :class:`SceneIndex` is built from (model, database, vocabulary
    settings): the key of its cache file."""
    from embodmocap.io.stage_manifest import fingerprint, path_fingerprint

    sfm_dir = Path(sfm_dir)
    return fingerprint("scene_index", INDEX_VERSION, path_fingerprint(sfm_dir / "sparse"),
                       path_fingerprint(sfm_dir / "database.db"), cfg.vocabulary_size, cfg.vocabulary_samples, cfg.seed)


def load_or_build_scene_index(sfm_dir: str | Path, cfg: RegisterConfig = RegisterConfig(),
                              cache: str | Path | None = None) -> SceneIndex:
    """:func:`build_scene_index`, reusing the copy cached in ``cache`` (an ``.npz``) when it was
    built from the same model and settings, so every sequence of a scene shares one index.
    A missing, stale or unreadable cache is rebuilt and rewritten (atomically)."""
    if cache is None:
        return build_scene_index(sfm_dir, cfg)
    cache = Path(cache)
    key = scene_index_key(sfm_dir, cfg)
    if cache.is_file():
        try:
            with np.load(cache, allow_pickle=False) as z:
                if str(z["key"]) == key:
                    return _index_from_arrays(Path(sfm_dir), z)
        except (OSError, KeyError, ValueError) as err:  # a damaged cache is only a cache
            log.warning("%s: unreadable scene index cache (%s); rebuilding it", cache, err)
    index = build_scene_index(sfm_dir, cfg)
    _save_index(cache, key, index)
    return index


def _save_index(path: Path, key: str, index: SceneIndex) -> None:
    from embodmocap.io.atomic import write_npz

    K = index.intrinsics
    ids = np.array(sorted(index.xyz_by_id), dtype=np.int64)
    write_npz(path, key=np.str_(key), names=np.array(index.names), T_world_cam=index.T_world_cam,
              intrinsics=np.array([K.fx, K.fy, K.cx, K.cy, K.width, K.height], dtype=np.float64),
              counts=np.array([len(d) for d in index.descriptors], dtype=np.int64),
              descriptors=np.concatenate(index.descriptors), point3D_ids=np.concatenate(index.point3D_ids),
              xyz_ids=ids, xyz=np.stack([index.xyz_by_id[int(i)] for i in ids]),
              vocabulary=index.vocabulary, idf=index.idf, bow=index.bow)


def _index_from_arrays(sfm_dir: Path, z) -> SceneIndex:
    fx, fy, cx, cy, w, h = z["intrinsics"]
    cuts = np.cumsum(z["counts"])[:-1]
    return SceneIndex(sfm_dir, tuple(str(n) for n in z["names"]), z["T_world_cam"],
                      Intrinsics(float(fx), float(fy), float(cx), float(cy), int(w), int(h)),
                      tuple(np.split(z["descriptors"], cuts)), tuple(np.split(z["point3D_ids"], cuts)),
                      {int(i): x for i, x in zip(z["xyz_ids"], z["xyz"])}, z["vocabulary"], z["idf"], z["bow"])


def build_scene_index(sfm_dir: str | Path, cfg: RegisterConfig = RegisterConfig()) -> SceneIndex:
    """Read the Stage I model and prepare key frame descriptors and the retrieval vocabulary.

    Raises:
        InputError: no model in ``sfm_dir``, or it has no triangulated points.
    """
    with _opencv_threads(1):
        return _build_scene_index(sfm_dir, cfg)


def _build_scene_index(sfm_dir: str | Path, cfg: RegisterConfig) -> SceneIndex:
    pycolmap = require("pycolmap", "all")
    cv2 = require("cv2", "all")
    sfm_dir = Path(sfm_dir)
    model_dir = sfm_dir / "sparse"
    if not (model_dir / "images.bin").is_file():
        raise InputError(model_dir, "no COLMAP sparse model here", "run the scene stage (embodmocap scene) first")
    rec = pycolmap.Reconstruction(model_dir)
    if rec.num_points3D() == 0:
        raise InputError(model_dir, "the sparse model has no 3D points",
                         "re-run the scene stage; the scene capture needs textured, in-focus views")
    cam = next(iter(rec.cameras.values()))
    intrinsics = intrinsics_from_colmap(cam.params, cam.width, cam.height)
    sift = cv2.SIFT_create()
    names, poses, descs, pids = [], [], [], []
    with pycolmap.Database.open(sfm_dir / "database.db") as db:
        for image_id in sorted(rec.reg_image_ids()):
            image = rec.image(image_id)
            obs = np.asarray(image.get_observation_point2D_idxs(), dtype=np.int64)
            if len(obs) == 0:
                continue
            gray = cv2.imread(str(sfm_dir / "images" / image.name), cv2.IMREAD_GRAYSCALE)
            if gray is None:
                raise InputError(sfm_dir / "images" / image.name, "key frame image missing or unreadable",
                                 "re-run the scene stage")
            shapes = np.asarray(db.read_keypoints(image_id), dtype=np.float64)[obs]
            desc = _describe_at(cv2, sift, gray, shapes)
            P = np.eye(4)
            P[:3, :4] = image.cam_from_world().matrix()
            names.append(image.name)
            poses.append(invert_T(P))
            descs.append(desc)
            # pycolmap exposes observations one by one; a key frame has a few hundred.
            pids.append(np.array([image.point2D(int(i)).point3D_id for i in obs], dtype=np.int64))
    all_ids = np.unique(np.concatenate(pids))
    xyz_by_id = {int(i): np.asarray(rec.point3D(int(i)).xyz, dtype=np.float64) for i in all_ids}
    vocabulary = _train_vocabulary(np.concatenate(descs), cfg)
    words = [_assign(vocabulary, d) for d in descs]
    counts = np.stack([np.bincount(w, minlength=len(vocabulary)) for w in words]).astype(np.float64)
    idf = np.log((1.0 + len(descs)) / (1.0 + np.sum(counts > 0, axis=0)))
    log.info("scene index: %d key frames, %d points, %d words", len(names), len(all_ids), len(vocabulary))
    return SceneIndex(sfm_dir, tuple(names), np.stack(poses), intrinsics, tuple(descs), tuple(pids),
                      xyz_by_id, vocabulary, idf, _normalise_rows(counts * idf))


def _describe_at(cv2, sift, gray: NDArray, shapes: NDArray) -> NDArray[np.float32]:
    """(n, 128) unit-norm OpenCV SIFT descriptors at COLMAP keypoints (x, y, a11, a12, a21, a22)."""
    x, y = shapes[:, 0] - COLMAP_PIXEL_OFFSET, shapes[:, 1] - COLMAP_PIXEL_OFFSET
    scale = np.hypot(shapes[:, 2], shapes[:, 4])
    angle = np.degrees(np.arctan2(shapes[:, 4], shapes[:, 2])) % 360.0
    # OpenCV's keypoint size is the diameter 2 sigma; the octave field picks the pyramid level the
    # descriptor is sampled from (first octave -1 = the 2x upsampled image, sigma0 = 1.6, 3 layers).
    size = 2.0 * scale
    level = np.log2(np.maximum(size, 1e-3) / (2 * 1.6))
    octave = np.clip(np.floor(level), -1, 7).astype(int)
    layer = np.clip(np.round((level - octave) * 3), 0, 3).astype(int)
    kps = [cv2.KeyPoint(float(a), float(b), float(s), float(g), 0, int((o & 255) | (lv << 8)))
           for a, b, s, g, o, lv in zip(x, y, size, angle, octave, layer)]
    _, desc = sift.compute(gray, kps)
    if desc is None or len(desc) != len(kps):  # compute drops nothing for in-image points
        raise RuntimeError("OpenCV SIFT dropped key frame keypoints")
    return _normalise_rows(desc.astype(np.float32))


def _normalise_rows(a: NDArray) -> NDArray:
    n = np.linalg.norm(a, axis=-1, keepdims=True)
    return a / np.maximum(n, 1e-12)


def _train_vocabulary(desc: NDArray[np.float32], cfg: RegisterConfig) -> NDArray[np.float32]:
    from scipy.cluster.vq import kmeans2

    rng = np.random.default_rng(cfg.seed)
    if len(desc) > cfg.vocabulary_samples:
        desc = desc[rng.choice(len(desc), cfg.vocabulary_samples, replace=False)]
    k = int(min(cfg.vocabulary_size, max(len(desc) // 4, 1)))
    centroids, _ = kmeans2(desc.astype(np.float64), k, iter=10, minit="points", seed=rng)
    return centroids.astype(np.float32)


def _assign(vocabulary: NDArray[np.float32], desc: NDArray[np.float32]) -> NDArray[np.int64]:
    """(n,) nearest word of each descriptor (squared distances via one matrix product)."""
    d2 = np.sum(vocabulary ** 2, axis=1)[None, :] - 2.0 * desc @ vocabulary.T
    return np.argmin(d2, axis=1)


# ------------------------------------------------------------------------------------------------
# Candidates


def retrieve_candidates(index: SceneIndex, desc: NDArray[np.float32], k: int) -> NDArray[np.int64]:
    """Indices of the ``k`` key frames whose bag of words is most similar (cosine) to ``desc``'s.

    Args:
        index: the scene index.
        desc: (n, 128) unit-norm descriptors of the query frame.
        k: how many key frames.
    """
    if len(desc) == 0:
        return np.zeros(0, dtype=np.int64)
    h = np.bincount(_assign(index.vocabulary, desc), minlength=len(index.vocabulary)) * index.idf
    score = index.bow @ _normalise_rows(h)
    return np.argsort(-score, kind="stable")[:k]


def pose_overlap(index: SceneIndex, T_world_cam: NDArray, intrinsics: Intrinsics,
                 depths_m: Sequence[float] = (1.5, 3.0, 5.0)) -> NDArray[np.float64]:
    """(Q, K) share of what each query camera sees that each key frame also sees, from poses alone.

    Probe points are cast from the query camera through a 3x3 pixel grid at each depth; the score
    is the share of probes inside the key frame's image and in front of it (no depth test, so it
    over-estimates behind occluders).

    Args:
        index: the scene index.
        T_world_cam: (Q, 4, 4) camera-to-world of the queries (scene world).
        intrinsics: the query camera.
    """
    Tq = np.asarray(T_world_cam, dtype=np.float64).reshape(-1, 4, 4)
    q = intrinsics
    gu, gv = np.meshgrid(np.array([1, 3, 5]) * q.width / 6 - 0.5, np.array([1, 3, 5]) * q.height / 6 - 0.5)
    rays = np.stack([(gu.ravel() - q.cx) / q.fx, (gv.ravel() - q.cy) / q.fy, np.ones(gu.size)], axis=-1)
    probes = (np.asarray(depths_m, dtype=np.float64)[:, None, None] * rays[None]).reshape(-1, 3)  # (S, 3)
    world = np.einsum("qab,sb->qsa", Tq[:, :3, :3], probes) + Tq[:, None, :3, 3]  # (Q, S, 3)
    Rk, ck = index.T_world_cam[:, :3, :3], index.T_world_cam[:, :3, 3]
    cam = np.einsum("kba,qksb->qksa", Rk, world[:, None] - ck[None, :, None])  # (Q, K, S, 3)
    kk = index.intrinsics
    z = cam[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = kk.fx * cam[..., 0] / z + kk.cx
        v = kk.fy * cam[..., 1] / z + kk.cy
    seen = (z > 0.05) & (u >= -0.5) & (u <= kk.width - 0.5) & (v >= -0.5) & (v <= kk.height - 0.5)
    return seen.mean(axis=-1)


def pose_candidates(index: SceneIndex, T_world_cam: NDArray, intrinsics: Intrinsics, k: int,
                    max_view_angle_deg: float = 75.0,
                    depths_m: Sequence[float] = (1.5, 3.0, 5.0)) -> NDArray[np.int64]:
    """(Q, k) indices of the key frames that see most of what each predicted query camera sees
    (:func:`pose_overlap`; ties: nearer centre first). Key frames looking more than
    ``max_view_angle_deg`` away from the query are ranked last."""
    Tq = np.asarray(T_world_cam, dtype=np.float64).reshape(-1, 4, 4)
    score = pose_overlap(index, Tq, intrinsics, depths_m)
    cos = np.einsum("qa,ka->qk", Tq[:, :3, 2], index.T_world_cam[:, :3, 2])
    score = np.where(cos >= np.cos(np.deg2rad(max_view_angle_deg)), score, -1.0)
    dist = np.linalg.norm(Tq[:, None, :3, 3] - index.T_world_cam[None, :, :3, 3], axis=-1)
    return np.lexsort((dist, -score), axis=-1)[:, :k]


# ------------------------------------------------------------------------------------------------
# Registration


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


def register_frames(view_frames: Sequence[ViewFrame], K: Intrinsics, sfm_dir: str | Path | SceneIndex,
                    cfg: RegisterConfig = RegisterConfig(),
                    predicted_T_world_cam: Mapping[int, NDArray] | None = None) -> Registration:
    """Register view frames into the Stage I sparse model.

    Args:
        view_frames: ``(t, rgb (H, W, 3) uint8, person_mask (H, W) bool)`` per frame to try.
        K: the view's RGB intrinsics (our pixel convention), at the frames' resolution.
        sfm_dir: the Stage I sparse model folder, or a :class:`SceneIndex` built from it (reuse one
            index for both views).
        cfg: settings.
        predicted_T_world_cam: ``t -> (4, 4)`` predicted camera-to-world poses in the scene's world
            (e.g. VIO poses through a coarse offset); used for ``"pose"`` / ``"auto"`` candidates.

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

    def one(frame: ViewFrame):
        t, rgb, mask = frame
        t = int(t)
        t0 = time.perf_counter()
        xy, desc = detect_background_features(rgb, mask, cfg)
        t1 = time.perf_counter()
        chosen = _choose(index, desc, K, cfg, predicted.get(t))
        q_idx, p_ids = match_to_keyframes(index, desc, chosen, cfg.ratio)
        t2 = time.perf_counter()
        res = _absolute_pose(pycolmap, camera, est, xy[q_idx], p_ids, index, cfg) if len(q_idx) >= 4 else None
        t3 = time.perf_counter()
        log.debug("frame %d: %d features, %d matches, %d inliers", t, len(xy), len(q_idx), 0 if res is None else len(res[1]))
        return t, xy, chosen, q_idx, p_ids, res, (t1 - t0, t2 - t1, t3 - t2)

    # Each frame is registered on its own with a fixed RANSAC seed and single-threaded OpenCV (its
    # SIFT keeps the strongest features, and with several internal threads the order of equally
    # strong ones could vary); the pool's map returns results in the frames' order, so the result
    # does not depend on the thread count or on which thread finishes first.
    frames = list(view_frames)
    workers = max(1, min(cfg.workers or (os.cpu_count() or 1), len(frames)))
    with _opencv_threads(1):
        if workers > 1:
            from concurrent.futures import ThreadPoolExecutor

            with ThreadPoolExecutor(workers) as pool:
                outs = list(pool.map(one, frames))
        else:
            outs = [one(f) for f in frames]
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


class _opencv_threads:
    """Context manager: OpenCV's internal thread count set to ``n`` inside, restored after."""

    def __init__(self, n: int) -> None:
        self.n = n

    def __enter__(self):
        import cv2

        self.prev = cv2.getNumThreads()
        cv2.setNumThreads(self.n)
        return self

    def __exit__(self, *exc) -> None:
        import cv2

        cv2.setNumThreads(self.prev)


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
