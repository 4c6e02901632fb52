"""The Stage I sparse model prepared for registration (Stage III): the scene index.

Per key frame of the model: its pose, OpenCV SIFT descriptors recomputed at COLMAP's keypoints of
its observations (so query and key frame descriptors come from the same code, see
:mod:`embodmocap.calibrate.register`), the 3D point of each, and a bag of visual words (k-means on
the key frames' own descriptors, tf-idf) for retrieval; candidates by retrieval or by pose. Built
once per scene and cached next to the model (``register_index.npz``), reused by every view and
sequence of the scene.
"""

from __future__ import annotations

import contextlib
import logging
import sqlite3
from concurrent.futures import Executor
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from embodmocap.calibrate.config import RegisterConfig
from embodmocap.errors import InputError, require
from embodmocap.geometry.transforms import invert_T
from embodmocap.io.colmap import COLMAP_PIXEL_OFFSET, intrinsics_from_colmap
from embodmocap.types import Intrinsics

log = logging.getLogger(__name__)


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
                              cache: str | Path | None = None, pool: Executor | None = None) -> SceneIndex:
    """:func:`build_scene_index`, reusing the copy cached in ``cache`` (an ``.npz``) when it was
    built from the same model and settings, so every sequence of a scene shares one index.
    A missing, stale or unreadable cache is rebuilt and rewritten (atomically)."""
    if cache is None:
        return build_scene_index(sfm_dir, cfg, pool)
    cache = Path(cache)
    key = scene_index_key(sfm_dir, cfg)
    if cache.is_file():
        try:
            with np.load(cache, allow_pickle=False) as z:
                if str(z["key"]) == key:
                    return _index_from_arrays(Path(sfm_dir), z)
        except (OSError, KeyError, ValueError) as err:  # a damaged cache is only a cache
            log.warning("%s: unreadable scene index cache (%s); rebuilding it", cache, err)
    index = build_scene_index(sfm_dir, cfg, pool)
    _save_index(cache, key, index)
    return index


def _save_index(path: Path, key: str, index: SceneIndex) -> None:
    from embodmocap.io.atomic import atomic_path

    K = index.intrinsics
    ids = np.array(sorted(index.xyz_by_id), dtype=np.int64)
    # Uncompressed: float descriptors barely compress (30 MB -> 17 MB for a 49 key frame scene)
    # and compressing them cost a second of CPU on the run's critical path.
    with atomic_path(path, suffix=".npz") as tmp, open(tmp, "wb") as f:
        np.savez(f, key=np.str_(key), names=np.array(index.names), T_world_cam=index.T_world_cam,
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


def build_scene_index(sfm_dir: str | Path, cfg: RegisterConfig = RegisterConfig(),
                      pool: Executor | None = None) -> SceneIndex:
    """Read the Stage I model and prepare key frame descriptors and the retrieval vocabulary.

    ``pool``: threads to describe the key frames on (one task per key frame; the same index
    whatever the threads); None: this thread. The caller keeps OpenCV on one thread meanwhile.

    Raises:
        InputError: no model in ``sfm_dir``, or it has no triangulated points.
    """
    with _opencv_threads(1):
        return _build_scene_index(sfm_dir, cfg, pool)


@contextlib.contextmanager
def _read_only_keypoints(path: Path):
    """``image_id -> (rows, cols) float32`` keypoints of a COLMAP database, read without ever
    writing to it. Stage I's database is Stage I's output: opening it through pycolmap (SQLite in
    WAL mode) leaves ``-wal``/``-shm`` files beside it, or more if the process is killed meanwhile,
    and Stage III's upstream check then finds Stage I's ``sfm/`` changed."""
    if not path.is_file():
        raise InputError(path, "the scene's COLMAP database is missing", "re-run the scene stage (embodmocap scene)")
    con = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro&immutable=1", uri=True)
    try:
        def read(image_id: int) -> NDArray[np.float32]:
            row = con.execute("SELECT rows, cols, data FROM keypoints WHERE image_id = ?", (int(image_id),)).fetchone()
            if row is None or row[2] is None:
                return np.zeros((0, 6), dtype=np.float32)
            return np.frombuffer(row[2], dtype=np.float32).reshape(int(row[0]), int(row[1]))

        yield read
    finally:
        con.close()


def _build_scene_index(sfm_dir: str | Path, cfg: RegisterConfig, pool: Executor | None) -> SceneIndex:
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
    names, poses, shapes, pids = [], [], [], []
    with _read_only_keypoints(sfm_dir / "database.db") as read_keypoints:
        for image_id in sorted(rec.reg_image_ids()):
            image = rec.image(image_id)
            obs = np.asarray(image.get_observation_point2D_idxs(), dtype=np.int64)
            if len(obs) == 0:
                continue
            shapes.append(np.asarray(read_keypoints(image_id), dtype=np.float64)[obs])
            P = np.eye(4)
            P[:3, :4] = image.cam_from_world().matrix()
            names.append(image.name)
            poses.append(invert_T(P))
            # pycolmap exposes observations one by one; a key frame has a few hundred.
            pids.append(np.array([image.point2D(int(i)).point3D_id for i in obs], dtype=np.int64))

    def describe(name_shapes: tuple[str, NDArray]) -> NDArray[np.float32]:
        name, at = name_shapes
        gray = cv2.imread(str(sfm_dir / "images" / name), cv2.IMREAD_GRAYSCALE)
        if gray is None:
            raise InputError(sfm_dir / "images" / name, "key frame image missing or unreadable", "re-run the scene stage")
        return _describe_at(cv2, cv2.SIFT_create(), gray, at)

    descs = list((pool.map if pool is not None else map)(describe, zip(names, shapes)))
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
