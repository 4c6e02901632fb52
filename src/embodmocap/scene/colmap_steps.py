"""COLMAP steps of Stage I's sparse model (through ``pycolmap``): SIFT extraction into the database,
matching and verification of the chosen pairs, triangulation with the poses held fixed, and the
small helpers around them. :mod:`embodmocap.scene.sfm` strings them together."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.geometry.transforms import invert_T
from embodmocap.io.colmap import colmap_camera_params
from embodmocap.logs import quiet_colmap
from embodmocap.types import Intrinsics

if TYPE_CHECKING:
    from embodmocap.scene.config import SfmConfig

log = logging.getLogger("embodmocap.scene.sfm")


def _extract(pycolmap, root: Path, names: list[str], intrinsics: Intrinsics, cfg: SfmConfig,
             src_dir: Path | None) -> tuple[list[int], int]:
    """SIFT into ``root/database.db`` with one fixed PINHOLE camera; returns (image ids in ``names``
    order, camera id)."""
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = ",".join(f"{p:.17g}" for p in colmap_camera_params(intrinsics))
    opts = pycolmap.FeatureExtractionOptions()
    opts.num_threads = cfg.feature_threads
    opts.sift.max_num_features = cfg.max_features
    opts.sift.first_octave = cfg.first_octave
    # COLMAP numbers new images in the order its extraction threads finish them: registered here
    # first, in ``names`` order, they keep ids 1..K (the one-thread order) whatever the threads do.
    pycolmap.Database.open(root / "database.db").close()
    pycolmap.import_images(root / "database.db", root / "images", camera_mode=pycolmap.CameraMode.SINGLE,
                           image_names=names, options=reader)
    pycolmap.extract_features(root / "database.db", root / "images", image_names=names,
                              camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              extraction_options=opts, device=pycolmap.Device.cpu)
    with pycolmap.Database.open(root / "database.db") as db:
        by_name = {im.name: im for im in db.read_all_images()}
        missing = [n for n in names if n not in by_name]
        if missing:
            raise InputError(src_dir, f"COLMAP could not read key frame {missing[0]!r}", "check the image file")
        cams = db.read_all_cameras()
        counts = np.array([db.num_keypoints_for_image(by_name[n].image_id) for n in names])
    cam = cams[0]
    if (cam.width, cam.height) != (intrinsics.width, intrinsics.height):
        raise InputError(src_dir, f"key frames are {cam.width}x{cam.height}, intrinsics say "
                         f"{intrinsics.width}x{intrinsics.height}", "pass the intrinsics of the key frames")
    if np.sum(counts > 0) < 2:
        raise InputError(src_dir, f"only {int(np.sum(counts > 0))} of {len(names)} key frames have SIFT features",
                         "key frames must show textured, in-focus scene content")
    if np.any(counts == 0):
        log.warning("%d key frames have no SIFT features (blank or blurred?)", int(np.sum(counts == 0)))
    return [int(by_name[n].image_id) for n in names], int(cam.camera_id)



def _match(pycolmap, root: Path, cfg: SfmConfig) -> int:
    """Match the pairs in ``root/pairs.txt`` and verify them; returns the number of verified pairs."""
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = cfg.feature_threads
    matching.sift.max_ratio = cfg.match_max_ratio
    pairing = pycolmap.ImportedPairingOptions()
    pairing.match_list_path = root / "pairs.txt"
    verify = pycolmap.TwoViewGeometryOptions()
    verify.min_num_inliers = cfg.min_num_inliers
    verify.ransac.max_error = cfg.ransac_max_error_px
    verify.ransac.random_seed = cfg.seed
    pycolmap.match_image_pairs(root / "database.db", matching_options=matching, pairing_options=pairing,
                               verification_options=verify, device=pycolmap.Device.cpu)
    with pycolmap.Database.open(root / "database.db") as db:
        num = int(db.num_verified_image_pairs())
    _canonical_file(root / "database.db")
    return num


def _canonical_file(db_path: Path) -> None:
    """Rewrite an SQLite database in key order (``VACUUM``): the threads of extraction and matching
    insert rows in the order they finish (same rows, different pages), so the file is made the same
    bytes for the same content (a rerun's database matches the first run's, bit for bit)."""
    import sqlite3

    con = sqlite3.connect(db_path)
    try:
        con.execute("VACUUM")
    finally:
        con.close()


def _triangulate(pycolmap, root: Path, names: list[str], ids: list[int], cam_id: int, T: NDArray,
                 cfg: SfmConfig):
    """Reconstruction with the database's camera and our fixed poses, then triangulated points."""
    with pycolmap.Database.open(root / "database.db") as db:
        camera = db.read_camera(cam_id)
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(camera)
    cam_from_world = invert_T(T)
    for name, image_id, P in zip(names, ids, cam_from_world):
        image = pycolmap.Image(name=name, camera_id=cam_id, image_id=image_id)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(P[:3, :4]))
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = cfg.num_threads
    opts.random_seed = cfg.seed
    opts.mapper.filter_max_reproj_error = cfg.max_reproj_error_px
    opts.mapper.filter_min_tri_angle = cfg.min_tri_angle_deg
    opts.triangulation.min_angle = cfg.min_tri_angle_deg
    opts.triangulation.merge_max_reproj_error = cfg.max_reproj_error_px
    opts.triangulation.complete_max_reproj_error = cfg.max_reproj_error_px
    opts.triangulation.ignore_two_view_tracks = not cfg.two_view_tracks
    # Poses and intrinsics stay fixed: triangulate_points never refines poses, and intrinsics only
    # with refine_intrinsics=True; the flags below make sure no BA step touches the camera either.
    opts.ba_refine_focal_length = False
    opts.ba_refine_principal_point = False
    opts.ba_refine_extra_params = False
    (root / "sparse").mkdir(exist_ok=True)
    return pycolmap.triangulate_points(rec, root / "database.db", root / "images", root / "sparse",
                                       clear_points=True, options=opts, refine_intrinsics=False)



def _drop_short_tracks(rec, min_track_length: int) -> None:
    # pycolmap exposes points one by one; a model holds at most ~1e5 points, so this loop is cheap.
    short = [pid for pid, p in rec.points3D.items() if p.track.length() < min_track_length]
    for pid in short:
        rec.delete_point3D(pid)
    if short:
        log.debug("removed %d points with tracks shorter than %d", len(short), min_track_length)



def _quiet_colmap(pycolmap):
    """COLMAP's own logging kept to errors unless this module logs at DEBUG (:func:`embodmocap.logs.quiet_colmap`)."""
    return quiet_colmap(pycolmap, log)


#: Bytes per SIFT feature in COLMAP's database (128-byte descriptor, 6 float keypoint, row overhead).
_DB_BYTES_PER_FEATURE = 160
#: Bytes per feature and matched pair (raw and verified matches, 2 x uint32 each).
_DB_BYTES_PER_MATCH = 16


def sfm_disk_estimate(num_images: int, image_bytes: int, cfg: SfmConfig) -> int:
    """An upper estimate of the bytes a sparse model folder takes (key frames, database, model)."""
    pairs = num_images * (num_images - 1) // 2 if cfg.pairing == "exhaustive" else num_images * cfg.num_neighbours
    features = num_images * cfg.max_features
    return image_bytes + features * _DB_BYTES_PER_FEATURE + pairs * cfg.max_features * _DB_BYTES_PER_MATCH + (4 << 20)


def _check_free_space(out_dir: Path, names: list[str], rgbs, src_dir: Path | None, intrinsics: Intrinsics,
                      cfg: SfmConfig) -> None:
    """Refuse to start when the disk cannot hold the model: COLMAP aborts the whole process (no
    error to catch, a C++ stack trace) when its database meets a full disk."""
    if rgbs is not None:
        per_image = intrinsics.width * intrinsics.height * 3 // (4 if cfg.image_format == "jpg" else 1)
        image_bytes = per_image * len(names)
    else:
        image_bytes = sum((src_dir / n).stat().st_size for n in names)
    need = sfm_disk_estimate(len(names), image_bytes, cfg)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    free = shutil.disk_usage(out_dir.parent).free
    if free < need:
        raise InputError(out_dir.parent, f"only {free / 2**20:.0f} MiB free on its disk; the sparse model of "
                         f"{len(names)} key frames needs up to {need / 2**20:.0f} MiB",
                         "free some disk space, then run the same command again to resume")
