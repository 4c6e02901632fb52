"""The ``colmap`` scene model: structure from motion (``pycolmap``, CPU) on each chunk's frames.

Runs on any machine (no model weights, no GPU): per chunk, every ``stride``-th frame (by sequence
frame number, so consecutive chunks share the same SfM frames in their overlap) is downscaled to
``image_width``, the person (Stage II's mask, dilated) is masked out of SIFT extraction (a moving
body breaks the static-scene assumption), images are matched sequentially (each with its
``seq_neighbours`` successors), verified, and mapped incrementally with the phone's intrinsics held
fixed. The result is up to scale and in a frame of its own, like Pi3's.

Per chunk frame the backend returns (``ChunkPrediction``):

- ``T_world_cam``: the SfM pose of a registered frame; frames between registered ones (stride,
  or SfM could not register them) are interpolated (slerp of the rotation, linear centre), frames
  before the first / after the last registered one take the nearest registered pose;
- ``local_points`` / ``conf``: *sparse* maps of ``map_width`` x ``map_height``: the 3D points the
  frame observes (its own SIFT features with a triangulated track), in its camera frame, splatted
  at the map pixel of their keypoint (the nearest point wins a pixel), ``conf = 1 - 1/L`` for a
  track of length ``L`` (0.5 for two views); every other pixel, and every frame SfM did not
  register, has ``conf = 0``. There are no points on the person (masked out), so the body-depth
  scale has no samples here: the metric scale comes from the feet on the SfM floor
  (:mod:`embodmocap.mono.feet`).

A chunk SfM cannot reconstruct (no model, or fewer than ``min_registered`` of its images
registered) is tried again with half the stride (``retry_denser``), down to every frame; if it
still fails it comes back with ``failure`` set: the stitching starts a new segment there with a
warning (never a silent jump).
"""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import binary_dilation
from scipy.spatial.transform import Rotation, Slerp

from embodmocap.logs import quiet_colmap
from embodmocap.mono.config import ColmapSceneConfig
from embodmocap.mono.files import ChunkPrediction

log = logging.getLogger(__name__)


def interpolate_poses(t_known: NDArray, T_known: NDArray, t: NDArray) -> NDArray[np.float64]:
    """(n, 4, 4) rigid poses at times ``t`` from (k, 4, 4) poses at sorted times ``t_known``: slerp
    between known ones, the nearest known pose outside their range."""
    t_known = np.asarray(t_known, dtype=np.float64)
    tq = np.clip(np.asarray(t, dtype=np.float64), t_known[0], t_known[-1])
    out = np.tile(np.eye(4), (len(tq), 1, 1))
    if len(t_known) == 1:
        out[:] = T_known[0]
        return out
    out[:, :3, :3] = Slerp(t_known, Rotation.from_matrix(T_known[:, :3, :3]))(tq).as_matrix()
    for k in range(3):
        out[:, k, 3] = np.interp(tq, t_known, T_known[:, k, 3])
    return out


class ColmapScene:
    """SfM per chunk (see the module).

    Args:
        read_rgb: sequence frame -> (H_rgb, W_rgb, 3) uint8 RGB.
        masks: sequence frame -> (H_rgb, W_rgb) bool person mask (None: nothing masked).
        K: (3, 3) RGB intrinsics (the phone's; held fixed in SfM).
        rgb_size: (W_rgb, H_rgb).
        cfg: settings.
    """

    name = "colmap"

    def __init__(self, read_rgb, masks, K: NDArray, rgb_size: tuple[int, int], cfg: ColmapSceneConfig) -> None:
        self.read_rgb = read_rgb
        self.masks = masks
        self.K = np.asarray(K, dtype=np.float64)
        self.W_rgb, self.H_rgb = rgb_size
        self.cfg = cfg
        f = min(1.0, cfg.image_width / self.W_rgb)
        self.w, self.h = int(round(self.W_rgb * f)), int(round(self.H_rgb * f))
        self.map_w = cfg.map_width
        self.map_h = max(1, int(round(cfg.map_width * self.H_rgb / self.W_rgb)))
        self._cache: dict[int, tuple[NDArray, NDArray]] = {}  # frame -> (image, feature mask), overlap reuse

    def _image(self, f: int) -> tuple[NDArray, NDArray]:
        import cv2

        if f not in self._cache:
            rgb = np.asarray(self.read_rgb(f))
            img = cv2.resize(rgb, (self.w, self.h), interpolation=cv2.INTER_AREA) if rgb.shape[1] != self.w else rgb
            keep = np.full((self.h, self.w), 255, np.uint8)
            if self.masks is not None:
                m = np.asarray(self.masks(f), dtype=np.uint8)
                m = cv2.resize(m, (self.w, self.h), interpolation=cv2.INTER_NEAREST).astype(bool)
                if self.cfg.mask_dilate_px > 0:
                    m = binary_dilation(m, iterations=self.cfg.mask_dilate_px)
                keep[m] = 0  # COLMAP extracts no feature where the mask is 0
            self._cache[f] = (img, keep)
        return self._cache[f]

    def predict(self, frames: NDArray[np.int64]) -> ChunkPrediction:
        import pycolmap

        frames = np.asarray(frames, dtype=np.int64)
        sel = frames[frames % self.cfg.stride == 0]
        if len(sel) < 3:  # a short last chunk: keep its frames all
            sel = frames
        stride = self.cfg.stride
        with quiet_colmap(pycolmap, log):
            while True:
                with tempfile.TemporaryDirectory(prefix="embodmocap_mono_sfm_") as tmp:
                    rec, failure = self._sfm(pycolmap, Path(tmp), sel)
                    if rec is not None or not self.cfg.retry_denser or stride == 1 or len(sel) == len(frames):
                        pred = self._prediction(rec, frames, sel, failure)
                        break
                # Denser frames give longer tracks (a 4-frame step lost SfM on 2 of 37 chunks of a
                # 60 s studio view; a 2-frame step reconstructed them). The SfM frames of the
                # coarser step stay a subset, so the overlap with the neighbours keeps them.
                log.debug("chunk %d..%d: %s at stride %d; retrying at %d", frames[0], frames[-1], failure, stride,
                          stride // 2)
                stride //= 2
                sel = frames[frames % stride == 0]
        self._cache = {f: v for f, v in self._cache.items() if f > frames[-1] - len(frames)}  # keep the overlap's
        return pred

    def _sfm(self, pycolmap, root: Path, sel: NDArray):
        import cv2

        cfg = self.cfg
        (root / "images").mkdir()
        (root / "masks").mkdir()
        names = [f"{int(f):06d}.jpg" for f in sel]
        for f, name in zip(sel, names):
            img, keep = self._image(int(f))
            cv2.imwrite(str(root / "images" / name), np.ascontiguousarray(img[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, 95])
            cv2.imwrite(str(root / "masks" / f"{name}.png"), keep)
        s = self.w / self.W_rgb
        fx, fy = self.K[0, 0] * s, self.K[1, 1] * s
        # this package puts the top-left pixel's centre at (0, 0), COLMAP at (0.5, 0.5)
        cx, cy = (self.K[0, 2] + 0.5) * s, (self.K[1, 2] + 0.5) * s
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        reader.camera_params = f"{fx:.10g},{fy:.10g},{cx:.10g},{cy:.10g}"
        reader.mask_path = str(root / "masks")
        ext = pycolmap.FeatureExtractionOptions()
        ext.num_threads = cfg.num_threads
        ext.sift.max_num_features = cfg.max_features
        db = root / "database.db"
        pycolmap.extract_features(db, root / "images", image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=ext, device=pycolmap.Device.cpu)
        match = pycolmap.FeatureMatchingOptions()
        match.num_threads = cfg.num_threads
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = cfg.seq_neighbours
        pairing.quadratic_overlap = False
        pairing.loop_detection = False  # needs a vocabulary tree (a download): never
        verify = pycolmap.TwoViewGeometryOptions()
        verify.ransac.random_seed = cfg.seed
        pycolmap.match_sequential(db, matching_options=match, pairing_options=pairing, verification_options=verify,
                                  device=pycolmap.Device.cpu)
        opts = pycolmap.IncrementalPipelineOptions()
        opts.num_threads = cfg.num_threads
        opts.random_seed = cfg.seed
        opts.multiple_models = False
        opts.ba_refine_focal_length = False  # the phone's intrinsics are known
        opts.ba_refine_principal_point = False
        opts.ba_refine_extra_params = False
        opts.mapper.init_min_tri_angle = cfg.init_min_tri_angle_deg  # short chunks: small baselines
        opts.mapper.init_min_num_inliers = cfg.init_min_inliers
        # a chunk of handheld video turns more than it travels: keep points of small parallax
        # (they still register the next image; their depth is weak but the bundle adjustment weighs it)
        opts.mapper.filter_min_tri_angle = cfg.min_tri_angle_deg
        opts.triangulation.min_angle = cfg.min_tri_angle_deg
        opts.mapper.abs_pose_refine_focal_length = False
        opts.mapper.abs_pose_refine_extra_params = False
        (root / "sparse").mkdir()
        try:
            recs = pycolmap.incremental_mapping(db, root / "images", root / "sparse", options=opts)
        except Exception as err:  # noqa: BLE001 - any SfM failure is a segment break, reported
            return None, f"SfM failed ({type(err).__name__}: {err})"
        if not recs:
            return None, "SfM found no initial pair"
        rec = max(recs.values(), key=lambda r: r.num_reg_images())
        n = rec.num_reg_images()
        if n < max(2, int(np.ceil(cfg.min_registered * len(sel)))):
            return None, f"SfM registered {n} of {len(sel)} images"
        if rec.num_points3D() < cfg.min_points:
            return None, f"SfM triangulated {rec.num_points3D()} points"
        return rec, ""

    def _prediction(self, rec, frames: NDArray, sel: NDArray, failure: str) -> ChunkPrediction:
        N, H, W = len(frames), self.map_h, self.map_w
        pts = np.zeros((N, H, W, 3), np.float32)
        conf = np.zeros((N, H, W), np.float32)
        if rec is None:
            return ChunkPrediction(frames, np.tile(np.eye(4), (N, 1, 1)), pts, conf, failure=failure)
        reg_t, reg_T = [], []
        for image in rec.images.values():
            if not image.has_pose:
                continue
            f = int(Path(image.name).stem)
            i = int(np.searchsorted(frames, f))
            P = image.cam_from_world().matrix()  # (3, 4) world -> camera
            R, t = P[:, :3], P[:, 3]
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R.T, -R.T @ t
            reg_t.append(f)
            reg_T.append(T)
            xy, xyz, L = [], [], []
            for p2 in image.points2D:
                if p2.has_point3D():
                    pt = rec.points3D[p2.point3D_id]
                    xy.append(p2.xy)
                    xyz.append(pt.xyz)
                    L.append(pt.track.length())
            if not xy:
                continue
            xy, xyz, L = np.asarray(xy), np.asarray(xyz), np.asarray(L, dtype=np.float64)
            pc = xyz @ R.T + t
            # COLMAP keypoints: the image's top-left corner at (0, 0), so floor(x W / w) is the map pixel
            c = np.clip(np.floor(xy[:, 0] * W / self.w).astype(np.int64), 0, W - 1)
            r = np.clip(np.floor(xy[:, 1] * H / self.h).astype(np.int64), 0, H - 1)
            ok = pc[:, 2] > 0
            order = np.argsort(-pc[:, 2])  # far first, so the nearest point is written last and wins
            order = order[ok[order]]
            pts[i, r[order], c[order]] = pc[order]
            conf[i, r[order], c[order]] = 1.0 - 1.0 / np.maximum(L[order], 1.0)
        o = np.argsort(reg_t)
        T_all = interpolate_poses(np.asarray(reg_t)[o], np.asarray(reg_T)[o], frames)
        return ChunkPrediction(frames, T_all, pts, conf, registered=np.isin(frames, reg_t))
