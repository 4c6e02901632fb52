"""Stage I sparse model: SIFT on the scene's key frames, triangulated with the capture's poses fixed.

The capture already gives metric, gravity-aligned camera poses and the camera intrinsics. Running a
full SfM would re-estimate both and lose that frame, so this module only *triangulates*: COLMAP
(through ``pycolmap``) extracts SIFT features, matches image pairs chosen from the known poses,
verifies them geometrically, then triangulates tracks and refines the 3D points with every pose and
the intrinsics held constant. The model therefore lives in the capture's world (Z up, metres).

Stage III registers the performer views' frames into this model, so the COLMAP database (features,
matches) and the binary model are kept on disk::

    out_dir/
      images/         the key frames handed to SfM (JPEG or PNG), named as given
      database.db     COLMAP database: one PINHOLE camera, keypoints, descriptors, verified matches
      pairs.txt       the image pairs that were matched, one "name_a name_b" per line
      sparse/         COLMAP binary model (cameras.bin, images.bin, points3D.bin, rigs.bin, frames.bin)
      summary.json    quality figures, image order and timings of the run (see docs/formats.md)

Pixel convention: this package puts the centre of the top-left pixel at (0, 0); COLMAP puts it at
(0.5, 0.5). So COLMAP's principal point is ours plus 0.5 (:func:`embodmocap.io.colmap.colmap_camera_params`) and COLMAP
keypoint coordinates are ours plus 0.5 (:mod:`embodmocap.io.colmap` converts). Focal lengths and
poses are the same in both.

Never call COLMAP's vocabulary-tree matcher here: without a local vocabulary file it tries to
download one and aborts the whole Python process.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError, require
from embodmocap.geometry.transforms import invert_T, is_rigid
from embodmocap.io.atomic import atomic_dir, write_json, write_text
from embodmocap.io.colmap import intrinsics_from_colmap
from embodmocap.scene.adjust import adjust_with_vio_prior, correction_of
from embodmocap.scene.colmap_steps import (  # noqa: F401 (sfm_disk_estimate: public here)
    _check_free_space, _drop_short_tracks, _extract, _match, _quiet_colmap, _triangulate, sfm_disk_estimate,
)
from embodmocap.scene.config import SfmConfig
from embodmocap.progress import step
from embodmocap.types import Intrinsics

log = logging.getLogger(__name__)

#: Version of the folder layout and ``summary.json`` written by :func:`build_sparse_model`.
SFM_FORMAT_VERSION = 1

_IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")


@dataclass(frozen=True)
class SparseModel:
    """A sparse model on disk and its quality figures.

    Attributes:
        out_dir: the folder holding everything below.
        model_dir: COLMAP binary model (``out_dir/sparse``).
        database_path: COLMAP database (``out_dir/database.db``), kept for registering new images.
        image_dir: key frames as COLMAP read them (``out_dir/images``).
        image_names: (K,) names of the key frames in the model, in the order they were given.
        num_points: number of 3D points.
        mean_track_length: mean number of key frames observing a point.
        mean_reproj_error_px: mean reprojection error of all observations, pixels.
        observations_per_image: (K,) int64 number of each key frame's features that have a 3D point.
        num_pairs: number of image pairs matched.
        num_verified_pairs: pairs that passed geometric verification.
        seconds: wall time of each step (``write_images``, ``extract``, ``pairs``, ``match``,
            ``triangulate``, ``finish``); empty when the model was read back without a summary.
    """

    out_dir: Path
    model_dir: Path
    database_path: Path
    image_dir: Path
    image_names: tuple[str, ...]
    num_points: int
    mean_track_length: float
    mean_reproj_error_px: float
    observations_per_image: NDArray[np.int64]
    num_pairs: int = 0
    num_verified_pairs: int = 0
    seconds: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        obs = np.array(self.observations_per_image, dtype=np.int64, copy=True)
        obs.setflags(write=False)
        object.__setattr__(self, "observations_per_image", obs)
        object.__setattr__(self, "seconds", dict(self.seconds))

    def quality(self) -> dict[str, float | int]:
        """The figures a stage manifest reports."""
        return {
            "sfm_images": len(self.image_names),
            "sfm_points": self.num_points,
            "sfm_mean_track_length": self.mean_track_length,
            "sfm_mean_reproj_error_px": self.mean_reproj_error_px,
            "sfm_images_without_points": int(np.sum(self.observations_per_image == 0)),
        }


# ------------------------------------------------------------------------------------------------
# Pair selection from the known poses


def overlap_matrix(T_world_cam: NDArray, intrinsics: Intrinsics,
                   depths_m: Sequence[float] = (1.0, 2.0, 3.0)) -> NDArray[np.float64]:
    """How much each key frame's view is seen by each other key frame, from poses alone.

    Probe points are cast from camera i through a 3x3 grid of pixels (at 1/6, 1/2, 5/6 of the
    image) at each depth; ``overlap[i, j]`` is the share of i's probes that land inside image j in
    front of camera j. Depth-free: it over-estimates overlap behind an occluder, which only costs a
    wasted match.

    Args:
        T_world_cam: (K, 4, 4) camera-to-world, OpenCV axes.
        intrinsics: the key frames' camera.
        depths_m: probe depths along the rays, metres.

    Returns:
        (K, K) float64 in [0, 1]; the diagonal is 1.
    """
    T = np.asarray(T_world_cam, dtype=np.float64)
    k = intrinsics
    gu, gv = np.meshgrid(np.array([1, 3, 5]) * k.width / 6 - 0.5, np.array([1, 3, 5]) * k.height / 6 - 0.5)
    rays = np.stack([(gu.ravel() - k.cx) / k.fx, (gv.ravel() - k.cy) / k.fy, np.ones(gu.size)], axis=-1)
    probes_cam = (np.asarray(depths_m, dtype=np.float64)[:, None, None] * rays[None]).reshape(-1, 3)  # (S, 3)
    R, c = T[:, :3, :3], T[:, :3, 3]
    probes_world = np.einsum("iab,sb->isa", R, probes_cam) + c[:, None, :]  # (K, S, 3)
    # Probes of camera i expressed in camera j: R_j^T (X - c_j) -> (K_j, K_i, S, 3).
    rel = probes_world[None, :, :, :] - c[:, None, None, :]
    in_j = np.einsum("jba,jisb->jisa", R, rel)
    z = in_j[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = k.fx * in_j[..., 0] / z + k.cx
        v = k.fy * in_j[..., 1] / z + k.cy
    # Pixel area spans [-0.5, W - 0.5] in our convention; a little depth margin avoids z ~ 0.
    seen = (z > 0.05) & (u >= -0.5) & (u <= k.width - 0.5) & (v >= -0.5) & (v <= k.height - 0.5)
    return seen.mean(axis=-1).T  # (K_i, K_j)


def select_pairs(T_world_cam: NDArray, intrinsics: Intrinsics, cfg: SfmConfig = SfmConfig()) -> NDArray[np.int64]:
    """Image pairs worth matching, chosen from the known poses.

    Each key frame keeps its ``cfg.num_neighbours`` best partners by overlap (ties: nearer centre
    first) among those within ``cfg.max_view_angle_deg`` of its viewing direction and with overlap
    at least ``cfg.min_overlap`` (either way round); the union over all key frames is returned.

    Args:
        T_world_cam: (K, 4, 4) camera-to-world, OpenCV axes.
        intrinsics: the key frames' camera.
        cfg: pairing settings.

    Returns:
        (P, 2) int64 index pairs ``i < j``, sorted, unique.
    """
    T = np.asarray(T_world_cam, dtype=np.float64)
    n = len(T)
    ov = overlap_matrix(T, intrinsics, cfg.overlap_depths_m)
    ov = np.maximum(ov, ov.T)  # symmetric: a pair is as useful from either side
    axes = T[:, :3, 2]
    cos_angle = np.clip(axes @ axes.T, -1.0, 1.0)
    ok = (ov >= cfg.min_overlap) & (cos_angle >= np.cos(np.deg2rad(cfg.max_view_angle_deg)))
    np.fill_diagonal(ok, False)
    dist = np.linalg.norm(T[:, None, :3, 3] - T[None, :, :3, 3], axis=-1)
    # Rank partners by overlap, then by distance; ineligible partners sort last.
    score = np.where(ok, ov, -1.0)
    order = _rank(score, dist)
    keep = np.zeros_like(ok)
    m = min(cfg.num_neighbours, max(n - 1, 0))
    rows = np.repeat(np.arange(n), m)
    keep[rows, order[:, :m].ravel()] = True
    keep &= ok
    keep |= keep.T
    i, j = np.nonzero(np.triu(keep, 1))
    return np.column_stack([i, j]).astype(np.int64)


def _rank(score: NDArray, dist: NDArray) -> NDArray[np.int64]:
    """(K, K) column indices of each row sorted by descending score, then ascending distance."""
    # np.lexsort sorts along the last axis with the last key as the primary one.
    return np.lexsort((dist, -score), axis=-1)


# ------------------------------------------------------------------------------------------------
# Building the model


def build_sparse_model(
    images: Sequence[tuple[str, NDArray[np.uint8]]] | str | Path,
    intrinsics: Intrinsics,
    T_world_cam: NDArray,
    out_dir: str | Path,
    cfg: SfmConfig = SfmConfig(),
    times_s: NDArray | None = None,
) -> SparseModel:
    """Triangulate a sparse SIFT model of the key frames with their poses and intrinsics fixed.

    ``out_dir`` is built in a temporary folder next to it and swapped in whole at the end, so a
    crash leaves either the previous model or none. An existing ``out_dir`` is replaced whole, so
    it must be empty or hold a previous sparse model (anything else raises :class:`InputError`
    rather than deleting it).

    Args:
        images: K key frames as ``(name, rgb (H, W, 3) uint8)`` (names: unique plain file names;
            written with the suffix of ``cfg.image_format``, replacing an image suffix they have),
            or a folder of JPEG/PNG key frames taken in sorted name order (copied unchanged into
            ``out_dir/images``).
        intrinsics: the key frames' pinhole camera (our pixel convention); every image must be
            ``width x height``.
        T_world_cam: (K, 4, 4) camera-to-world poses, OpenCV camera axes, Z-up metric world.
        out_dir: output folder (layout in the module docstring).
        cfg: settings.
        times_s: (K,) capture times of the key frames, seconds (for ``cfg.refine_poses``; without
            them the poses are used as given).

    Returns:
        The model and its quality figures.

    Raises:
        InputError: fewer than 2 key frames, poses or images that disagree with each other or with
            the intrinsics, fewer than 2 key frames with SIFT features, or nothing triangulated.
    """
    pycolmap = require("pycolmap", "all")
    _check_config(cfg)
    out_dir = Path(out_dir)
    _check_replaceable(out_dir)
    src_dir, names, rgbs = _gather_images(images, out_dir)
    T = _check_poses(T_world_cam, len(names), src_dir)
    sel = _thin(len(names), cfg.max_images)
    names, T = [names[i] for i in sel], T[sel]
    rgbs = [rgbs[i] for i in sel] if rgbs is not None else None
    if rgbs is not None:  # folder input keeps its files' names and suffixes
        names = [_with_format(n, cfg.image_format) for n in names]
    _check_unique(names, out_dir)
    _check_free_space(out_dir, names, rgbs, src_dir, intrinsics, cfg)

    seconds: dict[str, float] = {}
    with atomic_dir(out_dir) as tmp, _quiet_colmap(pycolmap):
        pycolmap.set_random_seed(cfg.seed)
        with _timer(seconds, "write_images"):
            _write_images(tmp / "images", names, rgbs, src_dir, intrinsics, cfg)
        with _timer(seconds, "extract"):
            ids, cam_id = _extract(pycolmap, tmp, names, intrinsics, cfg, src_dir)
        with _timer(seconds, "pairs"):
            pairs = _pairs(T, intrinsics, cfg)
            write_text(tmp / "pairs.txt", "".join(f"{names[i]} {names[j]}\n" for i, j in pairs))
        with _timer(seconds, "match"):
            num_verified = _match(pycolmap, tmp, cfg)
        with _timer(seconds, "triangulate"):
            rec = _triangulate(pycolmap, tmp, names, ids, cam_id, T, cfg)
        drift = None
        if cfg.refine_poses and times_s is not None and rec.num_points3D() > 0 and len(ids) >= 4:
            with _timer(seconds, "adjust"):
                drift = adjust_with_vio_prior(rec, ids, T, np.asarray(times_s, dtype=np.float64)[sel], cfg)
                if drift.accepted:  # triangulated again with the corrected poses held fixed
                    rec = _triangulate(pycolmap, tmp, names, ids, cam_id, drift.T_world_cam, cfg)
        with _timer(seconds, "finish"):
            _drop_short_tracks(rec, cfg.min_track_length)
            if rec.num_points3D() == 0:
                raise InputError(src_dir, "no 3D point could be triangulated from the key frames",
                                 "check that the key frames overlap, are textured and match their poses")
            rec.write(tmp / "sparse")
        model = _summarise(rec, out_dir, names, len(pairs), num_verified, seconds)
        summary = _summary_json(model, intrinsics, cfg)
        if drift is not None:
            summary["drift_correction"] = {"accepted": drift.accepted, "reason": drift.reason, **drift.figures}
            if drift.accepted:  # what the mesh's fusion and any other frame of the capture need
                summary["drift_correction"].update(times_s=np.asarray(times_s, dtype=np.float64)[sel],
                                                   T_correction=correction_of(T, drift.T_world_cam))
        write_json(tmp / "summary.json", summary)
    log.info("sparse model: %d images, %d points, track %.2f, reprojection %.3f px (%.1f s)",
             len(names), model.num_points, model.mean_track_length, model.mean_reproj_error_px,
             sum(seconds.values()))
    return model


def _check_config(cfg: SfmConfig) -> None:
    if cfg.image_format not in ("jpg", "png"):
        raise ValueError(f"image_format must be 'jpg' or 'png', got {cfg.image_format!r}")
    if cfg.max_images < 2 or cfg.min_track_length < 2 or cfg.num_neighbours < 1:
        raise ValueError("max_images and min_track_length must be >= 2 and num_neighbours >= 1")
    if cfg.feature_threads == 0 or cfg.feature_threads < -1 or cfg.num_threads == 0 or cfg.num_threads < -1:
        raise ValueError("feature_threads and num_threads must be >= 1 or -1 (all cores)")
    if not 1 <= cfg.jpeg_quality <= 100:
        raise ValueError(f"jpeg_quality must be in 1..100, got {cfg.jpeg_quality}")


def _check_replaceable(out_dir: Path) -> None:
    """Refuse to replace a folder that is neither empty nor a previous sparse model."""
    if out_dir.exists() and any(out_dir.iterdir()) and not (out_dir / "summary.json").is_file():
        raise InputError(out_dir, "output folder exists and does not hold a sparse model",
                         "pass an empty or new folder for the sparse model")


def _gather_images(images, out_dir: Path) -> tuple[Path | None, list[str], list[NDArray] | None]:
    """(source folder or None, names, rgb arrays or None) of the key frames."""
    if isinstance(images, (str, Path)):
        folder = Path(images)
        if not folder.is_dir():
            raise InputError(folder, "key frame folder not found", "pass a folder of JPEG/PNG key frames")
        if folder.resolve() == out_dir.resolve() or out_dir.resolve() in folder.resolve().parents:
            raise InputError(folder, "the key frame folder lies inside the SfM output folder, which is replaced",
                             "keep key frames outside out_dir")
        names = sorted(p.name for p in folder.iterdir() if p.suffix.lower() in _IMAGE_SUFFIXES)
        if len(names) < 2:
            raise InputError(folder, f"{len(names)} key frame image(s) found, SfM needs at least 2",
                             "add JPEG/PNG key frames")
        return folder, names, None
    items = list(images)
    if len(items) < 2:
        raise InputError(None, f"{len(items)} key frame(s) given, SfM needs at least 2", "pass two or more key frames")
    names = [str(n) for n, _ in items]
    return None, names, [np.asarray(rgb) for _, rgb in items]


def _with_format(name: str, fmt: str) -> str:
    """``name`` with the file suffix of ``fmt`` (an image suffix it already has is replaced)."""
    if Path(name).suffix.lower() in _IMAGE_SUFFIXES:
        return str(Path(name).with_suffix("." + fmt))
    return f"{name}.{fmt}"


def _check_unique(names: list[str], where: Path) -> None:
    bad = [n for n in names if Path(n).name != n or n.startswith(".")]
    if bad:
        raise InputError(where, f"key frame name {bad[0]!r} is not a plain file name", "use names like 'kf_0001'")
    if len(set(names)) != len(names):
        raise InputError(where, "key frame names repeat", "give every key frame a unique name")


def _check_poses(T_world_cam: NDArray, n: int, where: Path | None) -> NDArray[np.float64]:
    T = np.asarray(T_world_cam, dtype=np.float64)
    if T.shape != (n, 4, 4):
        raise InputError(where, f"{n} key frames but poses of shape {T.shape}", "pass one (4, 4) pose per key frame")
    if not np.all(np.isfinite(T)) or not np.all(is_rigid(T)):
        raise InputError(where, "key frame poses are not finite rigid transforms", "pass camera-to-world poses")
    return T


def _thin(n: int, max_images: int) -> NDArray[np.int64]:
    """Indices of at most ``max_images`` of ``n`` items, evenly spread, first and last kept."""
    if n <= max_images:
        return np.arange(n)
    log.info("thinning %d key frames to %d for SfM", n, max_images)
    return np.unique(np.linspace(0, n - 1, max(max_images, 2)).round().astype(np.int64))


def _write_images(dst: Path, names: list[str], rgbs: list[NDArray] | None, src_dir: Path | None,
                  intrinsics: Intrinsics, cfg: SfmConfig) -> None:
    import cv2

    dst.mkdir(parents=True, exist_ok=True)
    shape = (intrinsics.height, intrinsics.width, 3)
    if rgbs is None:
        for name in names:
            shutil.copyfile(src_dir / name, dst / name)
        return
    params = [cv2.IMWRITE_JPEG_QUALITY, int(cfg.jpeg_quality)] if cfg.image_format == "jpg" else []
    for name, rgb in zip(names, rgbs):
        if rgb.shape != shape or rgb.dtype != np.uint8:
            raise InputError(None, f"key frame {name!r} is {rgb.dtype} {rgb.shape}, expected uint8 {shape}",
                             "pass RGB images at the intrinsics' resolution")
        if not cv2.imwrite(str(dst / name), np.ascontiguousarray(rgb[..., ::-1]), params):
            raise OSError(f"could not write {dst / name}")


def _pairs(T: NDArray, intrinsics: Intrinsics, cfg: SfmConfig) -> NDArray[np.int64]:
    if cfg.pairing == "exhaustive":
        i, j = np.triu_indices(len(T), 1)
        return np.column_stack([i, j]).astype(np.int64)
    if cfg.pairing != "poses":
        raise ValueError(f"unknown pairing {cfg.pairing!r}")
    pairs = select_pairs(T, intrinsics, cfg)
    log.debug("%d pairs from poses for %d key frames", len(pairs), len(T))
    return pairs


def _summarise(rec, out_dir: Path, names: list[str], num_pairs: int, num_verified: int,
               seconds: dict[str, float]) -> SparseModel:
    images = [rec.find_image_with_name(n) for n in names]
    obs = np.array([0 if im is None else im.num_points3D for im in images], dtype=np.int64)
    n_pts = int(rec.num_points3D())
    return SparseModel(
        out_dir=out_dir,
        model_dir=out_dir / "sparse",
        database_path=out_dir / "database.db",
        image_dir=out_dir / "images",
        image_names=tuple(names),
        num_points=n_pts,
        mean_track_length=float(rec.compute_mean_track_length()) if n_pts else 0.0,
        mean_reproj_error_px=float(rec.compute_mean_reprojection_error()) if n_pts else 0.0,
        observations_per_image=obs,
        num_pairs=num_pairs,
        num_verified_pairs=num_verified,
        seconds=seconds,
    )


def _summary_json(model: SparseModel, intrinsics: Intrinsics, cfg: SfmConfig) -> dict:
    from dataclasses import asdict

    return {
        "format_version": SFM_FORMAT_VERSION,
        "image_names": list(model.image_names),
        "intrinsics": asdict(intrinsics),
        "quality": model.quality(),
        "observations_per_image": model.observations_per_image,
        "num_pairs": model.num_pairs,
        "num_verified_pairs": model.num_verified_pairs,
        "seconds": model.seconds,
        "config": asdict(cfg),
    }


@contextmanager
def _timer(seconds: dict[str, float], key: str) -> Iterator[None]:
    t0 = time.perf_counter()
    try:
        with step(f"sparse model: {key}"):  # embodmocap.progress: elapsed time on a terminal
            yield
    finally:
        seconds[key] = round(time.perf_counter() - t0, 3)


# ------------------------------------------------------------------------------------------------
# Reading it back


def _open_model(out_dir: str | Path):
    pycolmap = require("pycolmap", "all")
    model_dir = Path(out_dir) / "sparse"
    if not (model_dir / "images.bin").is_file():
        raise InputError(model_dir, "no COLMAP model here", "run the scene stage (sparse model) first")
    return pycolmap.Reconstruction(model_dir)


def read_sparse_model(out_dir: str | Path) -> SparseModel:
    """The model written by :func:`build_sparse_model` in ``out_dir``, figures recomputed from disk.

    Image order and timings come from ``summary.json`` when present (else images by id, no timings).
    """
    out_dir = Path(out_dir)
    rec = _open_model(out_dir)
    summary_path = out_dir / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.is_file() else {}
    names = summary.get("image_names") or [rec.image(i).name for i in sorted(rec.reg_image_ids())]
    return _summarise(rec, out_dir, list(names), int(summary.get("num_pairs", 0)),
                      int(summary.get("num_verified_pairs", 0)), summary.get("seconds", {}))


def sparse_points(out_dir: str | Path) -> tuple[NDArray[np.float64], NDArray[np.uint8], NDArray[np.int64], NDArray[np.float64]]:
    """The model's 3D points.

    Returns:
        xyz (P, 3) float64 world metres, rgb (P, 3) uint8, track_len (P,) int64 (key frames seeing
        the point), error_px (P,) float64 mean reprojection error; ordered by COLMAP point id.
    """
    rec = _open_model(out_dir)
    ids = sorted(rec.point3D_ids())
    pts = [rec.point3D(i) for i in ids]
    xyz = np.array([p.xyz for p in pts], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in pts], dtype=np.uint8).reshape(-1, 3)
    track = np.array([p.track.length() for p in pts], dtype=np.int64)
    err = np.array([p.error for p in pts], dtype=np.float64)
    return xyz, rgb, track, err


def image_poses(out_dir: str | Path) -> dict[str, NDArray[np.float64]]:
    """``name -> T_world_cam`` (4, 4) of every registered image in the model (camera-to-world)."""
    rec = _open_model(out_dir)
    poses = {}
    for image_id in rec.reg_image_ids():
        image = rec.image(image_id)
        P = np.eye(4)
        P[:3, :4] = image.cam_from_world().matrix()
        poses[image.name] = invert_T(P)
    return poses


def colmap_intrinsics(out_dir: str | Path) -> Intrinsics:
    """The model's (single) camera in our pixel convention."""
    rec = _open_model(out_dir)
    cam = next(iter(rec.cameras.values()))
    return intrinsics_from_colmap(cam.params, cam.width, cam.height)
