"""``embodmocap export SESSION --to training``: per-frame training data for monocular models.

For every sequence and view, the frames as a camera saw them with the dual-view system's answers
attached: RGB, metric depth, intrinsics, the camera pose, the fitted body in that camera's frame,
the person mask, 2D keypoints and a per-frame validity flag. Layout (``docs/training.md``, keys in
``docs/formats.md``, section "Training export")::

    DIR/
      manifest.json                 the dataset's index: format, views, frame counts, files
      export_manifest.json          resumability (stage manifest, stage ``training``)
      <seq>/<view>/
        labels.npz                  per-frame arrays (cameras, camera-space SMPL, keypoints, flags)
        rgb/<frame:06d>.jpg         RGB, one JPEG per sequence frame
        depth.npy                   (T, h, w) uint16 millimetres, 0 = invalid (memory-mappable)
        masks.npy                   (T, H, ceil(W/8)) uint8 bit-packed person masks (if Stage II wrote them)

Why these formats: a training loader reads frames in random order from several worker processes.
A JPEG per frame decodes on its own (about 1-2 ms at 640x480 with OpenCV) wherever the frame
lies, where a frame of an H.264 video needs a seek to the previous key frame and the decoding of
every frame after it; depth and masks stay in NumPy stacks like Stage II's (``io.frame_stack``),
which a memory map reads without any decoding (a 16-bit PNG costs milliseconds a frame).

Camera-space SMPL: the world fit ``(global_orient, body_pose, betas, transl)`` is moved into each
frame's camera by ``T_cam_world`` with SMPL's rotation pivot, the rest pelvis ``J_0(betas)``
(:meth:`BodyModel.pelvis_offset`)::

    global_orient_cam = R_cw * global_orient
    transl_cam        = R_cw (transl + J_0) + t_cw - J_0

so the body model posed with the camera-space parameters gives exactly ``T_cam_world`` applied to
the world body. View 2's frames are not taken at view 1's instants (the sub-frame sync of
``sync.json``): its body is the world fit resampled at its own frame times (rotations by slerp,
``transl`` linearly), as Stage IV resamples its observations.

Each view is one step of a stage manifest (``export_manifest.json``): it is written into a
temporary folder and renamed into place, and a rerun redoes only views whose inputs or settings
changed; unchanged views keep their bytes.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap import __version__
from embodmocap.errors import InputError
from embodmocap.export.config import ExportConfig
from embodmocap.io.atomic import atomic_dir, write_json, write_npz
from embodmocap.io.layout import VIEWS, SequenceLayout, SessionLayout
from embodmocap.io.stage_files import read_final_sync, read_frame_map
from embodmocap.io.stage_manifest import StageManifest, fingerprint, path_fingerprint, tracked_stage
from embodmocap.progress import progress

log = logging.getLogger(__name__)

#: The dataset's format name (``manifest.json`` ``format``); the reader checks it.
TRAINING_FORMAT = "embodmocap.training/1"
#: Version of ``labels.npz``.
LABELS_VERSION = 2  # 2: smpl_suspect
#: Bumped when the written bytes change for the same inputs (invalidates earlier exports).
EXPORT_VERSION = 1


def rgb_name(frame: int) -> str:
    """File name of a frame's JPEG inside ``<seq>/<view>/rgb/``."""
    return f"{int(frame):06d}.jpg"


# ------------------------------------------------------------------------------------------------
# Geometry: the world fit in a camera's frame


def params_in_camera(global_orient: NDArray, transl: NDArray, betas: NDArray, T_cam_world: NDArray,
                     model) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Camera-space ``global_orient`` and ``transl`` of world SMPL parameters, frame by frame.

    Args:
        global_orient: (T, 3) axis-angle, world frame.
        transl: (T, 3) SMPL ``transl``, world metres.
        betas: (B,) shape shared by the frames.
        T_cam_world: (T, 4, 4) rigid world-to-camera per frame.
        model: the :class:`~embodmocap.body.model.BodyModel` (its rest pelvis is the pivot).

    Returns:
        ``(global_orient_cam (T, 3), transl_cam (T, 3))``; body pose and betas do not change.
        The rotation is about the rest pelvis ``J_0(betas)``, not the origin, so the translation
        picks up ``R_cw J_0 - J_0`` besides ``R_cw transl + t_cw``.
    """
    from scipy.spatial.transform import Rotation

    T = np.asarray(T_cam_world, dtype=np.float64)
    R, t = T[:, :3, :3], T[:, :3, 3]
    p = model.pelvis_offset(betas)
    # np.array copies: scipy refuses read-only arrays (SmplParams' are).
    go = (Rotation.from_matrix(R) * Rotation.from_rotvec(np.array(global_orient, np.float64))).as_rotvec()
    tr = np.einsum("tij,tj->ti", R, np.asarray(transl, np.float64) + p) + t - p
    return go, tr


def resample_motion(poses: NDArray, transl: NDArray, times_s: NDArray, query_s: NDArray
                    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64], NDArray[np.int64],
                               NDArray[np.float64], NDArray[np.bool_]]:
    """SMPL rotations and translation at other instants.

    Args:
        poses: (N, 72) axis-angle of the 24 joints (global orient first) at ``times_s``.
        transl: (N, 3) at ``times_s``.
        times_s: (N,) strictly increasing.
        query_s: (M,) the instants wanted.

    Returns:
        ``(poses (M, 72), transl (M, 3), i0 (M,), i1 (M,), w (M,), inside (M,))``: every joint's
        rotation by slerp between the bracketing rows ``i0``, ``i1`` (weight ``w`` of ``i1``),
        ``transl`` linearly; a query on a row (within 1e-9 s) takes that row exactly (``i0 == i1``);
        outside the span the nearest end row, ``inside`` False.
    """
    from embodmocap.geometry.interpolate import TIME_EPS_S, bracket
    from embodmocap.geometry.rotations import quat_to_rotvec, rotvec_to_quat, slerp

    poses = np.array(poses, np.float64)  # a writable copy: scipy refuses read-only arrays
    transl = np.asarray(transl, np.float64)
    times_s = np.asarray(times_s, np.float64)
    query_s = np.asarray(query_s, np.float64)
    i0, w, inside = bracket(times_s, query_s)
    i1 = np.minimum(i0 + 1, len(times_s) - 1)
    # Snap queries that fall on a row to that row, so view 1 (and a perfectly synced view 2) keeps
    # the world fit's numbers exactly instead of a slerp's rounding.
    on0 = np.abs(query_s - times_s[i0]) <= TIME_EPS_S
    on1 = np.abs(query_s - times_s[i1]) <= TIME_EPS_S
    w = np.where(on0, 0.0, np.where(on1, 1.0, w))
    i0 = np.where(w >= 1.0, i1, i0)
    i1 = np.where(w <= 0.0, i0, i1)
    w = np.where(i0 == i1, 0.0, w)
    M, J = len(query_s), poses.shape[1] // 3
    q = rotvec_to_quat(poses.reshape(len(poses), J, 3))
    out = quat_to_rotvec(slerp(q[i0], q[i1], np.repeat(w[:, None], J, axis=1))).reshape(M, J * 3)
    exact = i0 == i1
    out[exact] = poses[i0[exact]]
    tr = (1.0 - w)[:, None] * transl[i0] + w[:, None] * transl[i1]
    return out, tr, i0, i1, w, inside


# ------------------------------------------------------------------------------------------------
# One view


@dataclass(frozen=True)
class _ViewInputs:
    """The files one view's export reads."""

    seq: str
    view: str
    smpl_world: Path
    cameras_final: Path
    cameras: Path
    keypoints: Path
    depth: Path
    masks: Path
    frame_map: Path
    sync: Path
    capture: Path

    def all(self) -> list[Path]:
        return [self.smpl_world, self.cameras_final, self.cameras, self.keypoints, self.depth, self.masks,
                self.frame_map, self.sync, self.capture]


def _motion_fix(session: Path, seq: str) -> str:
    return f"run `embodmocap motion {session} --seq {seq}` first"


def _need(path: Path, what: str, fix: str) -> Path:
    if not path.exists():
        raise InputError(path, f"missing {what} needed for the training export", fix)
    return path


def _view_times(seq_root: Path, view: str, n: int, fps: float) -> NDArray[np.float64]:
    """(n,) the view's frame times on its own clock (``cameras.npz``; k / fps without it)."""
    from embodmocap.io.stage_files import read_cameras
    from embodmocap.sequence.subframe import frame_times

    path = SequenceLayout(seq_root).view(view).cameras
    if not path.is_file():
        return np.arange(n) / fps
    t = frame_times(read_cameras(path, "cameras"), fps)
    if len(t) < n:  # a view whose cameras file is shorter: continue at the frame rate
        t = np.concatenate([t, t[-1] + np.arange(1, n - len(t) + 1) / fps]) if len(t) else np.arange(n) / fps
    return t[:n]


def _body_times(layout: SessionLayout, seq: str, view: str, n: int, fps: float) -> NDArray[np.float64]:
    """(n,) the instant of each of the view's frames on view 1's clock (the world fit's clock).

    View 2's frame ``k`` is taken at its own time ``t2[k]``, which Stage IV puts at view 1's
    ``t2[k] - residual_s`` (the final sync record; see :mod:`embodmocap.sequence.subframe`).
    """
    sl = layout.sequence(seq)
    t = _view_times(sl.root, view, n, fps)
    if view == VIEWS[0]:
        return t
    off = 0.0
    if sl.final_sync.is_file() or sl.sync.is_file():
        off = read_final_sync(sl).residual_s
    return t - off


def _dropped(path: Path, n: int) -> NDArray[np.bool_]:
    """(n,) frames Stage II sliced onto a dropped raw frame (``frame_map.json``; none without it)."""
    if not path.is_file():
        return np.zeros(n, bool)
    fm = read_frame_map(path)
    out = np.zeros(n, bool)
    m = min(n, len(fm.dropped))
    out[:m] = fm.dropped[:m]
    return out


def _depth_intrinsics(cams_stage2, K: NDArray, width: int, height: int, shape: tuple[int, int]) -> NDArray[np.float64]:
    """K of the depth stack: Stage II's depth camera when the stack has its size, K when it has the
    RGB size (refined depth), else K rescaled (pixel-centre convention)."""
    from embodmocap.types import Intrinsics

    h, w = shape
    if (h, w) == (height, width):
        return np.asarray(K, np.float64)
    if cams_stage2 is not None and cams_stage2.K_depth is not None and \
            (int(cams_stage2.depth_height), int(cams_stage2.depth_width)) == (h, w):
        return np.asarray(cams_stage2.K_depth, np.float64)
    return Intrinsics.from_K(K, width, height).scaled(w, h).K


def _write_view(layout: SessionLayout, inp: _ViewInputs, model, params, frames: NDArray, smpl_flags: tuple[NDArray, NDArray],
                out_dir: Path, config: ExportConfig) -> dict:
    """Write one view's folder (into ``out_dir``, a temporary folder); returns its frame counts."""
    import cv2
    import torch

    from embodmocap.geometry.transforms import invert_T
    from embodmocap.io.captures import open_capture
    from embodmocap.io.frame_stack import pack_mask, write_stack
    from embodmocap.io.stage_files import read_cameras, read_keypoints2d
    from embodmocap.types import Intrinsics

    fix = _motion_fix(layout.root, inp.seq)
    cams = read_cameras(inp.cameras_final, "cameras_final")
    N = cams.num_frames
    K, W, H = np.asarray(cams.K, np.float64), int(cams.width), int(cams.height)
    stage2 = read_cameras(inp.cameras, "cameras") if inp.cameras.is_file() else None
    kp = read_keypoints2d(inp.keypoints)
    depth = np.load(inp.depth, mmap_mode="r")
    masks = np.load(inp.masks, mmap_mode="r") if inp.masks.is_file() else None
    for name, path, have in (("keypoints2d.npz", inp.keypoints, len(kp.keypoints)), ("depth.npy", inp.depth, len(depth)),
                             ("masks.npy", inp.masks, None if masks is None else len(masks))):
        if have is not None and have < N:
            raise InputError(path, f"{name} holds {have} frames, cameras_final.npz {N}",
                             f"run `embodmocap sequence {layout.root} --seq {inp.seq} --force` and the later stages again")
    if masks is not None and masks.shape[1:] != (H, (W + 7) // 8):
        raise InputError(inp.masks, f"masks are {masks.shape[1:]}, expected ({H}, {(W + 7) // 8}) for {W}x{H} RGB",
                         f"run `embodmocap sequence {layout.root} --seq {inp.seq} --force`")

    # The body at each of this view's frames (view 1's clock), moved into its camera.
    fps = float(params.fps)
    body_t = _body_times(layout, inp.seq, inp.view, N, fps)
    fit_t = _view_times(layout.sequence(inp.seq).root, VIEWS[0], int(frames.max()) + 1, fps)[frames]
    if np.any(np.diff(fit_t) <= 0):
        raise InputError(inp.smpl_world, "its frames do not increase in time", fix)
    poses = np.concatenate([params.global_orient, params.body_pose], axis=1)
    poses_v, transl_v, i0, i1, w, inside = resample_motion(poses, params.transl, fit_t, body_t)
    # Between two rows that are not neighbouring sequence frames (a gap in the fit) nothing was fitted.
    smpl_valid, smpl_suspect = smpl_flags
    has_smpl = inside & smpl_valid[i0] & smpl_valid[i1] & (frames[i1] - frames[i0] <= 1)
    T_world_cam = np.asarray(cams.T_world_cam, np.float64)
    T_cam_world = invert_T(T_world_cam)
    betas = np.asarray(params.betas, np.float64)
    go_c, tr_c = params_in_camera(poses_v[:, :3], transl_v, betas, T_cam_world, model)
    joints_c = np.zeros((N, 24, 3))
    coco_c = np.zeros((N, 17, 3))
    with torch.no_grad():
        for s in range(0, N, 256):
            out = model.forward(betas, go_c[s:s + 256], poses_v[s:s + 256, 3:], tr_c[s:s + 256], dtype=torch.float64)
            joints_c[s:s + 256], coco_c[s:s + 256] = out.joints.numpy(), out.coco17.numpy()
    K_depth = _depth_intrinsics(stage2, K, W, H, depth.shape[1:])
    # The stored RGB size: the capture's, or --training-rgb-width (every pixel quantity follows it).
    W2, H2 = _stored_size(W, H, config.training_rgb_width)
    sx, sy = W2 / W, H2 / H
    K2 = Intrinsics.from_K(K, W, H).scaled(W2, H2).K if (W2, H2) != (W, H) else K
    z = np.where(np.abs(coco_c[..., 2:]) > 1e-9, coco_c[..., 2:], 1e-9)
    kp_fit = np.einsum("ij,tkj->tki", K2, coco_c / z)[..., :2]
    keypoints = np.asarray(kp.keypoints[:N], np.float64).copy()
    keypoints[..., 0], keypoints[..., 1] = (keypoints[..., 0] + 0.5) * sx - 0.5, (keypoints[..., 1] + 0.5) * sy - 0.5
    boxes = np.asarray(kp.boxes[:N], np.float64).copy()
    boxes[:, 0::2], boxes[:, 1::2] = (boxes[:, 0::2] + 0.5) * sx - 0.5, (boxes[:, 1::2] + 0.5) * sy - 0.5

    depth_present = np.array([bool(np.any(depth[t])) for t in range(N)])
    in_sync = inside & ~_dropped(inp.frame_map, N)
    valid = in_sync & has_smpl & depth_present

    labels = dict(
        version=np.int64(LABELS_VERSION), fps=np.float64(fps), frames=np.arange(N, dtype=np.int64),
        raw_frames=np.asarray(cams.raw_frames, np.int64), K=K2, width=np.int64(W2), height=np.int64(H2),
        K_depth=K_depth, depth_width=np.int64(depth.shape[2]), depth_height=np.int64(depth.shape[1]),
        T_world_cam=T_world_cam, global_orient=go_c, body_pose=poses_v[:, 3:], transl=tr_c, betas=betas,
        gender=np.array(params.gender), joints_cam=joints_c, keypoints_fit=kp_fit,
        keypoints=keypoints, boxes=boxes,
        seen=np.asarray(kp.seen[:N], bool), valid=valid, smpl_valid=has_smpl, in_sync=in_sync,
        smpl_suspect=smpl_suspect[i0] | smpl_suspect[i1],
        depth_present=depth_present, body_time_s=body_t, body_rows=np.stack([i0, i1], axis=1), body_weight=w)
    write_npz(out_dir / "labels.npz", **labels)
    with write_stack(out_dir / "depth.npy", (N,) + depth.shape[1:], np.uint16) as stack:
        stack[:] = depth[:N]
    if masks is not None:
        with write_stack(out_dir / "masks.npy", (N, H2, (W2 + 7) // 8), np.uint8) as stack:
            if (W2, H2) == (W, H):
                stack[:] = masks[:N]
            else:
                for t in range(N):
                    m = np.unpackbits(masks[t], axis=-1, count=W).astype(np.uint8)
                    stack[t] = pack_mask(cv2.resize(m, (W2, H2), interpolation=cv2.INTER_NEAREST))

    # RGB: the raw video decoded forward once (sequence frames map to increasing raw frames).
    rgb_dir = out_dir / "rgb"
    rgb_dir.mkdir()
    capture = open_capture(inp.capture)
    quality = [int(cv2.IMWRITE_JPEG_QUALITY), int(config.training_jpeg_quality)]
    try:
        for t in progress(range(N), f"training export {out_dir.name}: RGB", unit="frame"):
            rgb = np.asarray(capture.frames.rgb(int(cams.raw_frames[t])))
            if rgb.shape != (H, W, 3):
                raise InputError(inp.capture, f"raw frame {int(cams.raw_frames[t])} is {rgb.shape[1]}x{rgb.shape[0]}, "
                                 f"cameras_final.npz says {W}x{H}", fix)
            if (W2, H2) != (W, H):
                rgb = cv2.resize(rgb, (W2, H2), interpolation=cv2.INTER_AREA)
            ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), quality)
            if not ok:
                raise OSError(f"JPEG encoding of frame {t} failed")
            (rgb_dir / rgb_name(t)).write_bytes(buf.tobytes())
    finally:
        close = getattr(capture.frames, "close", None)
        if close is not None:
            close()
    log.info("training export %s/%s: %d frames, %d valid", inp.seq, inp.view, N, int(valid.sum()))
    return {"frames": int(N), "valid_frames": int(valid.sum())}


def _stored_size(width: int, height: int, want_width: int) -> tuple[int, int]:
    """RGB size written: the capture's (``want_width`` 0 or the same), else ``want_width`` wide with
    the aspect kept (height rounded to an even number of pixels, as video sizes are)."""
    if want_width <= 0 or want_width == width:
        return width, height
    if want_width > width:
        raise InputError(None, f"training_rgb_width {want_width} is larger than the capture's {width} pixels",
                         "choose a smaller width (or 0 for the capture's size)")
    return int(want_width), max(2, 2 * round(height * want_width / width / 2))


def _view_entry(out: Path, seq: str, view: str) -> dict:
    """A view's entry of ``manifest.json``, from its written folder (also when the step was skipped)."""
    d = out / seq / view
    with np.load(d / "labels.npz") as z:
        lab = {k: z[k] for k in ("fps", "width", "height", "depth_width", "depth_height", "valid")}
    return {"sequence": seq, "view": view, "path": f"{seq}/{view}", "frames": int(len(lab["valid"])),
            "valid_frames": int(lab["valid"].sum()), "fps": float(lab["fps"]), "width": int(lab["width"]),
            "height": int(lab["height"]), "depth_width": int(lab["depth_width"]),
            "depth_height": int(lab["depth_height"]), "masks": (d / "masks.npy").is_file()}


# ------------------------------------------------------------------------------------------------
# The session


@tracked_stage
def export_training(session: str | Path, seq: str | None = None, out: str | Path | None = None, *,
                    config: ExportConfig = ExportConfig(), force: bool = False) -> Path:
    """Write the training export of ``session`` (every sequence, or only ``seq``) into ``out``.

    ``out`` defaults to ``SESSION/training/``. Sequences marked ``failed`` in ``session.toml`` are
    left out (with a warning) unless named. Returns ``out``.

    Raises:
        InputError: a needed Stage II-IV file is missing or does not match (named, with the
            command to run), or a stage of the sequence failed / is out of date.
    """
    from embodmocap.body.model import load_body_model
    from embodmocap.io.manifest import load_manifest
    from embodmocap.io.smpl_file import read_smpl_npz, read_smpl_suspect, read_smpl_valid
    from embodmocap.io.stage_manifest import require_sequence_stages

    if not 1 <= int(config.training_jpeg_quality) <= 100:
        raise InputError(None, f"training_jpeg_quality {config.training_jpeg_quality} is outside 1..100",
                         "give a JPEG quality from 1 to 100 (95 by default)")
    layout = SessionLayout(Path(session))
    manifest = load_manifest(layout.manifest)
    if seq is not None:
        entries = [manifest.sequence(seq)]
    else:
        entries = [e for e in manifest.sequences.values() if not e.failed]
        for e in manifest.sequences.values():
            if e.failed:
                log.warning("training export: sequence %s is marked failed in %s; left out", e.name, layout.manifest)
    if not entries:
        raise InputError(layout.manifest, "no sequence to export", "name one with --seq")
    out = Path(out) if out is not None else layout.training_dir
    out.mkdir(parents=True, exist_ok=True)
    model_fp = path_fingerprint(manifest.body_model) if manifest.body_model is not None else "test-model"
    cfg = {"training_jpeg_quality": config.training_jpeg_quality, "training_rgb_width": config.training_rgb_width}
    sm = StageManifest(out / "export_manifest.json", "training", cfg, root=out)
    model = load_body_model(manifest.body_model)

    views = []
    for entry in entries:
        require_sequence_stages(layout, entry)
        sl = layout.sequence(entry.name)
        fix = _motion_fix(layout.root, entry.name)
        _need(sl.smpl_world, "world SMPL motion (smpl_world.npz)", fix)
        params, frames = read_smpl_npz(sl.smpl_world)
        smpl_flags = (read_smpl_valid(sl.smpl_world), read_smpl_suspect(sl.smpl_world))
        if len(frames) == 0:
            raise InputError(sl.smpl_world, "the motion has no frame", fix)
        for v in entry.view_names:
            vl = sl.view(v)
            inp = _ViewInputs(entry.name, v, sl.smpl_world, _need(vl.cameras_final, "Stage IV cameras", fix), vl.cameras,
                              _need(vl.keypoints, "Stage II keypoints",
                                    f"run `embodmocap sequence {layout.root} --seq {entry.name}` first"),
                              _need(vl.depth, "Stage II depth", f"run `embodmocap sequence {layout.root} --seq {entry.name}` first"),
                              vl.masks, vl.frame_map, sl.sync, _need(entry.views[v].capture, "raw capture",
                                                                      "check the capture path in session.toml"))
            fp = fingerprint("training-view", EXPORT_VERSION, cfg, entry.name, v, model_fp,
                             *[path_fingerprint(p) for p in inp.all()])
            view_dir = out / entry.name / v
            with sm.step(f"{entry.name}/{v}", fp, force=force, label="training export") as step:
                if step.run:
                    with atomic_dir(view_dir) as tmp:
                        info = _write_view(layout, inp, model, params, frames, smpl_flags, tmp, config)
                    step.record([view_dir], {f"{entry.name}_{v}_frames": info["frames"],
                                             f"{entry.name}_{v}_valid_frames": info["valid_frames"]})
            views.append(_view_entry(out, entry.name, v))

    index = {"format": TRAINING_FORMAT, "package_version": __version__, "session": layout.root.resolve().name,
             "body_model": None if manifest.body_model is None else manifest.body_model.name,
             "body_model_fingerprint": model_fp, "gender": manifest.gender,
             "rgb": {"format": "jpeg", "quality": config.training_jpeg_quality, "files": "rgb/{frame:06d}.jpg"},
             "depth": {"file": "depth.npy", "dtype": "uint16", "unit": "mm", "invalid": 0},
             "masks": {"file": "masks.npy", "packing": "np.packbits(axis=-1)"},
             "labels": {"file": "labels.npz", "version": LABELS_VERSION},
             "views": views, "frames": sum(v["frames"] for v in views),
             "valid_frames": sum(v["valid_frames"] for v in views), "config": cfg}
    write_json(out / "manifest.json", index)
    log.info("training export of %s: %d views, %d frames (%d valid) -> %s", layout.root, len(views), index["frames"],
             index["valid_frames"], out)
    return out


def read_training_index(root: str | Path) -> dict:
    """The ``manifest.json`` of a training export, checked (format, views, files present).

    Raises:
        InputError: not a folder, no or unreadable manifest, another format, a view's files missing.
    """
    root = Path(root)
    fix = "run `embodmocap export SESSION --to training --out DIR` to write it"
    if not root.is_dir():
        raise InputError(root, "training export folder not found", fix)
    path = root / "manifest.json"
    if not path.is_file():
        raise InputError(path, "not a training export (no manifest.json)", fix)
    try:
        index = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise InputError(path, f"unreadable manifest ({err})", fix) from err
    if not isinstance(index, dict) or index.get("format") != TRAINING_FORMAT:
        got = index.get("format") if isinstance(index, dict) else type(index).__name__
        raise InputError(path, f"format {got!r}, this reader knows {TRAINING_FORMAT!r}",
                         "update embodmocap, or " + fix[0].lower() + fix[1:])
    views = index.get("views")
    if not isinstance(views, list) or not views:
        raise InputError(path, "the manifest lists no view", fix)
    for v in views:
        d = root / str(v.get("path", ""))
        for name in ("labels.npz", "depth.npy", "rgb") + (("masks.npy",) if v.get("masks") else ()):
            if not (d / name).exists():
                raise InputError(d / name, "missing file of the training export", fix)
    return index
