"""``embodmocap evaluate``: quality metrics of every sequence, and errors against ground truth.

Always (no ground truth needed), per sequence, from the final outputs of Stage IV:
``mask_iou_pct`` (rendered SMPL silhouette vs the person mask), ``reproj_err_px`` (SMPL COCO-17
joints vs the 2D keypoints), ``depth_err_m2`` (rendered SMPL depth vs sensor depth on the person,
mean squared) and ``jitter`` (of the world joints). Rendering is done on ``frames_per_view``
frames spread evenly over the sequence.

With ``SESSION/ground_truth/`` (synthetic sessions): ``w_mpjpe_mm`` / ``wa_mpjpe_mm`` (100-frame
chunks, plus ``_c500`` and ``_c1000``), ``pa_mpjpe_mm``, ``rte_pct``, per view
``view_translation_err_cm``, ``view_yaw_err_deg`` and ``sync_err_frames``; for the scene
``mesh_accuracy_cm`` and ``mesh_completeness_pct`` (5 cm). Everything is compared in Stage I's
world (the scene capture's VIO world): the truth is moved there with the scene capture's true
``T_scene_vio``.

Definitions of every metric: :mod:`embodmocap.evaluate.metrics` and docs/formats.md.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.evaluate import metrics as M
from embodmocap.evaluate.mono import mono_metrics
from embodmocap.evaluate.truth import SequenceTruth, sequence_truth  # noqa: F401 (public here)
from embodmocap.geometry.transforms import invert_T
from embodmocap.io.atomic import write_json
from embodmocap.io.layout import VIEWS, SessionLayout
from embodmocap.io.manifest import load_manifest
from embodmocap.io.ground_truth import read_truth_info, read_truth_scene_device, read_truth_sequence
from embodmocap.io.stage_files import (
    SYNC_RECORD_VERSION, read_calibration, read_cameras, read_final_sync, read_keypoints2d, read_keypoints3d,
    read_stage_record,
)
from embodmocap.io.stage_manifest import require_sequence_stages

log = logging.getLogger(__name__)

EVALUATION_VERSION = 1
CHUNKS = (100, 500, 1000)


@dataclass(frozen=True)
class EvaluateConfig:
    """What ``embodmocap evaluate`` computes."""

    frames_per_view: int = 30
    """Frames per view rendered for mask IoU and depth error (evenly spread)."""
    mesh_samples: int = 100_000
    """Surface samples for the scene mesh accuracy / completeness."""
    completeness_threshold_m: float = 0.05
    """A true surface sample closer than this to the reconstruction counts as complete."""


def evaluate_session(session: str | Path, cfg: EvaluateConfig = EvaluateConfig()) -> dict:
    """Evaluate every fitted sequence (and the scenes) of ``session``; writes ``evaluation.json``.

    Sequences without Stage IV outputs are listed with ``"missing"`` naming the stage to run.
    """
    lay = SessionLayout(Path(session))
    manifest = load_manifest(lay.manifest)
    has_gt = lay.ground_truth.info.is_file()
    result: dict = {"version": EVALUATION_VERSION, "session": str(lay.root.resolve()), "ground_truth": has_gt,
                    "scene": {}, "sequences": {}}
    for name in manifest.scenes:
        if has_gt and lay.scene(name).mesh_raw.is_file() and lay.scene(name).keyframes.is_file():
            result["scene"][name] = scene_errors(lay, name, cfg)
    for name, entry in manifest.sequences.items():
        sl = lay.sequence(name)
        if not sl.smpl_world.is_file():
            hint = (f"the manifest marks it failed: run `embodmocap run {lay.root} --include-failed`" if entry.failed
                    else f"no fitted motion: run `embodmocap run {lay.root}` first")
            result["sequences"][name] = {"missing": hint, **mono_metrics(lay, entry.scene, name, manifest.body_model)}
            continue
        try:  # never evaluate outputs that a failed or out-of-date stage left behind
            require_sequence_stages(lay, entry)
        except InputError as err:
            log.warning("%s not evaluated: %s", name, err)
            result["sequences"][name] = {"missing": str(err)}
            continue
        log.info("evaluating %s", name)
        metrics = sequence_quality(lay, name, manifest.body_model, cfg)
        if has_gt:
            metrics.update(sequence_errors(lay, entry.scene, name, manifest.body_model))
        metrics.update(mono_metrics(lay, entry.scene, name, manifest.body_model))
        result["sequences"][name] = metrics
    write_json(lay.evaluation, result)
    return result


def _fitted(lay: SessionLayout, seq: str, body_model_path):
    """(model, params, frames, body output in float64) of the final Stage IV motion."""
    import torch

    from embodmocap.body.model import load_body_model
    from embodmocap.io.smpl_file import read_smpl_npz

    model = load_body_model(body_model_path)
    params, frames = read_smpl_npz(lay.sequence(seq).smpl_world)
    with torch.no_grad():
        body = model.from_params(params, dtype=torch.float64)
    return model, params, frames, body


def sequence_quality(lay: SessionLayout, seq: str, body_model_path=None, cfg: EvaluateConfig = EvaluateConfig()) -> dict:
    """The paper's quality metrics of one fitted sequence (no ground truth needed)."""
    from embodmocap.body.model import load_body_model
    from embodmocap.io.smpl_file import read_smpl_npz

    params, _ = read_smpl_npz(lay.sequence(seq).smpl_world)
    cams = {v: read_cameras(lay.sequence(seq).view(v).cameras_final).T_world_cam for v in lay.sequence(seq).views()}
    out = quality_metrics(lay, seq, load_body_model(body_model_path), params, cams, cfg)
    out.update(flag_counts(lay.sequence(seq).smpl_world))
    return out


def flag_counts(path: Path) -> dict:
    """How many frames of a world SMPL motion file are flagged (no ground truth needed):
    ``invalid_frames`` (``valid`` False), ``suspect_frames`` (placeable but ``suspect``:
    a limb far from every view that sees it) and the worst limb's median / largest distance from
    the views (``limb_off_mm_median`` / ``_max``, when the file has the quality keys)."""
    from embodmocap.io.smpl_file import read_smpl_quality, read_smpl_valid

    valid = read_smpl_valid(path)
    q = read_smpl_quality(path)
    out = {"invalid_frames": int((~valid).sum())}
    if q:
        off = q["limb_off_m"][valid & np.isfinite(q["limb_off_m"])]
        out.update({"suspect_frames": int((q["suspect"] & valid).sum()),
                    "limb_off_mm_median": round(1000 * float(np.median(off)), 1) if off.size else None,
                    "limb_off_mm_max": round(1000 * float(off.max()), 1) if off.size else None})
    return out


def quality_metrics(lay: SessionLayout, seq: str, model, params, T_world_cam: dict[str, NDArray],
                    cfg: EvaluateConfig = EvaluateConfig()) -> dict:
    """Quality metrics of a motion ``params`` (world, one row per sequence frame) seen by the views'
    cameras ``T_world_cam`` (view -> (T, 4, 4)), against the sequence's Stage II observations
    (keypoints, masks, depth). Used for the stage's own outputs and for benchmark variants."""
    import torch

    from embodmocap.geometry.raycast import depth_map
    from embodmocap.io.frame_stack import read_depth_m, read_mask
    from embodmocap.types import Intrinsics

    with torch.no_grad():
        body = model.from_params(params, dtype=torch.float64)
    verts = body.vertices.numpy()
    coco = body.coco17.numpy()
    out: dict = {"frames": int(len(params)), "fps": float(params.fps),
                 "jitter": round(float(M.jitter(body.joints.numpy(), params.fps)), 4)}
    ious, reps, derrs = [], [], []
    for v in T_world_cam:
        vl = lay.sequence(seq).view(v)
        cams = read_cameras(vl.cameras)
        K = Intrinsics.from_K(cams["K"], int(cams["width"]), int(cams["height"]))
        T_wc = T_world_cam[v]
        kp = read_keypoints2d(vl.keypoints).keypoints
        n = min(len(kp), len(coco), len(T_wc))
        proj = _project(K, T_wc[:n], coco[:n])
        reps.append(M.reproj_err_px(proj, kp[:n]))
        sample = np.unique(np.linspace(0, n - 1, min(cfg.frames_per_view, n)).astype(np.int64))
        pred_masks, true_masks, d_pred, d_true, d_mask = [], [], [], [], []
        has_masks, has_depth = vl.masks.is_file(), vl.depth.is_file()
        Kd = Intrinsics.from_K(cams["K_depth"], int(cams["depth_width"]), int(cams["depth_height"])) if has_depth else None
        for t in sample:
            if has_masks:
                pred_masks.append(np.isfinite(depth_map(verts[t], model.faces, K, T_wc[t])))
                true_masks.append(read_mask(vl.masks, int(t), K.width))
            if has_depth:
                dp = depth_map(verts[t], model.faces, Kd, T_wc[t])
                ds = read_depth_m(vl.depth, int(t))
                if ds.shape != dp.shape:  # depth stored at another size than K_depth says: not comparable
                    log.warning("%s %s: depth frame %d is %s, K_depth says %s; depth error skipped", seq, v, t,
                                ds.shape, dp.shape)
                    continue
                d_pred.append(dp)
                d_true.append(ds)
                d_mask.append(np.isfinite(dp) & (ds > 0))
        if pred_masks:
            iou = M.mask_iou_pct(np.stack(pred_masks), np.stack(true_masks))
            ious.append(iou)
            out[f"{v}_mask_iou_pct"] = round(float(iou), 2)
        if d_pred:
            de = M.depth_err_m2(np.stack(d_pred), np.stack(d_true), np.stack(d_mask))
            derrs.append(de)
            out[f"{v}_depth_err_m2"] = round(float(de), 5)
        out[f"{v}_reproj_err_px"] = round(float(reps[-1]), 3)
    out["reproj_err_px"] = round(float(np.mean(reps)), 3)
    if ious:
        out["mask_iou_pct"] = round(float(np.mean(ious)), 2)
    if derrs:
        out["depth_err_m2"] = round(float(np.mean(derrs)), 5)
    return out


def _project(K, T_world_cam: NDArray, points: NDArray) -> NDArray:
    """(T, J, 2) pixels of world points (T, J, 3) seen by per-frame cameras (T, 4, 4)."""
    R = T_world_cam[:, :3, :3]
    c = T_world_cam[:, None, :3, 3]
    cam = np.einsum("tba,tjb->tja", R, points - c)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.stack([K.fx * cam[..., 0] / cam[..., 2] + K.cx, K.fy * cam[..., 1] / cam[..., 2] + K.cy], axis=-1)


def sequence_errors(lay: SessionLayout, scene: str, seq: str, body_model_path=None) -> dict:
    """Errors of one fitted sequence against the synthetic truth (Stage I's world)."""
    from embodmocap.io.smpl_file import read_smpl_valid

    from embodmocap.io.smpl_file import read_smpl_suspect

    _, params, frames, body = _fitted(lay, seq, body_model_path)
    truth = sequence_truth(lay, scene, seq)
    out = motion_errors(body.joints.numpy(), frames, truth, read_smpl_valid(lay.sequence(seq).smpl_world),
                        read_smpl_suspect(lay.sequence(seq).smpl_world))
    if lay.sequence(seq).keypoints3d.is_file():
        out.update(keypoint_errors(lay, scene, seq, body_model_path))
    sl = lay.sequence(seq)
    calib = read_calibration(sl.calibration).record if sl.calibration.is_file() else None
    sync = read_final_sync(sl).views if sl.final_sync.is_file() or sl.sync.is_file() else {}
    mm = sl.motion_manifest
    motion_fig = read_stage_record(mm).figures if mm.is_file() else {}
    T_align = np.asarray(motion_fig.get("T_align", np.eye(4).tolist()))
    out["one_view"] = len(lay.sequence(seq).views()) == 1
    for v in lay.sequence(seq).views():
        if calib is not None:
            T_est = T_align @ np.asarray(calib["views"][v]["T_world_vio"])
            centres = read_cameras(lay.sequence(seq).view(v).cameras).T_world_cam[:, :3, 3]
            cm, deg = M.view_offset_err(T_est, truth.T_world_vio[v], centres)
            out[f"{v}_view_translation_err_cm"] = round(float(cm), 3)
            out[f"{v}_view_yaw_err_deg"] = round(float(deg), 4)
        if v in sync:
            out[f"{v}_sync_err_frames"] = int(M.sync_err_frames(sync[v]["frame"], truth.sync_frame[v]))
    sub = subframe_sync_err_frames(lay, seq)
    if sub is not None:
        out["sync_subframe_err_frames"] = sub
    return out


def subframe_sync_err_frames(lay: SessionLayout, seq: str) -> float | None:
    """Error of the offset Stage IV applies between the views (slicing + ``chosen.residual_s`` of
    the final version-2 sync record, ``final_sync.json``), in frames, against the studio's truth, which knows each
    phone's sub-frame phase: raw frame ``j`` of view ``v`` is the motion's instant
    ``view_motion_start[v] + j + view_time_offset_frames[v]``. None without such a record."""
    sl = lay.sequence(seq)
    if not ((sl.final_sync.is_file() or sl.sync.is_file()) and sl.manifest.is_file()):
        return None
    sync = read_final_sync(sl)
    rec = sync.record
    if sync.version != SYNC_RECORD_VERSION or not sync.final or len(rec["views"]) < 2:
        return None  # (one view: no offset between views)
    gt = read_truth_info(lay.ground_truth.info)
    start = gt["view_motion_start"]
    phase = gt.get("view_time_offset_frames", {v: 0.0 for v in VIEWS})
    a, b = VIEWS
    # View 2's sequence frame minus view 1's at the same instant, as the slicing left them.
    true_residual = (start[a] + rec["views"][a]["frame"] + phase[a]) - (start[b] + rec["views"][b]["frame"] + phase[b])
    fps = float(read_stage_record(sl.manifest).figures["fps"])
    return round(sync.residual_s * fps - true_residual, 4)


#: Edge frames: the first (last) this many evaluated frames of a sequence are its start (end).
EDGE_FRAMES = 5
#: A frame with a joint further than this from the truth (no alignment), metres, is wrong; one that
#: is neither flagged invalid nor suspect is wrong silently.
WRONG_FRAME_M = 0.15


def motion_errors(joints: NDArray, frames: NDArray, truth: SequenceTruth, valid: NDArray | None = None,
                  suspect: NDArray | None = None) -> dict:
    """W-/WA-MPJPE (chunks 100, 500, 1000), PA-MPJPE and RTE of world joints (T, 24, 3) at sequence
    ``frames`` against the truth (frames outside the scripted motion are left out). Frames the fit
    flagged invalid (``valid`` (T,) False: the body could not be placed) are left out too and
    counted in ``invalid_frames``, so nothing is dropped silently.

    The edges of the sequence, over the evaluated frames (issue 29): W-MPJPE at chunk 100 with a
    chunk starting at every frame (``w_mpjpe_mm_all_starts_median`` / ``_worst``); the mean
    unaligned joint error of the first and last :data:`EDGE_FRAMES` frames (``first5_frame_mm``,
    ``last5_frame_mm``) beside the median frame's (``median_frame_mm``); frames with a joint more
    than :data:`WRONG_FRAME_M` from the truth (``wrong_frames``) and those of them the fit did not
    flag, neither invalid nor ``suspect`` (T,) bool (``wrong_unflagged_frames``, and its percentage
    of the frames inside the motion ``wrong_unflagged_pct``); ``suspect_frames`` counts the flag."""
    ok = truth.valid[frames]
    valid = np.ones(len(frames), dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    suspect = np.zeros(len(frames), dtype=bool) if suspect is None else np.asarray(suspect, dtype=bool)
    out: dict = {"invalid_frames": int((~valid).sum()), "evaluated_frames": int((ok & valid).sum()),
                 "suspect_frames": int((suspect & valid).sum())}
    if ok.any():
        d = np.linalg.norm(np.asarray(joints)[ok] - truth.joints[frames][ok], axis=-1).max(axis=-1)
        wrong = d > WRONG_FRAME_M
        silent = wrong & valid[ok] & ~suspect[ok]
        out.update({"wrong_frames": int(wrong.sum()), "wrong_unflagged_frames": int(silent.sum()),
                    "wrong_unflagged_pct": round(100.0 * float(silent.mean()), 3)})
    if not valid.all() and ok.sum() >= 2:
        # The same figures with the flagged frames kept (what the fit interpolated there), so that
        # leaving them out is never silent. Chunks are cut over the evaluated frames in order, so
        # each chunk's alignment uses its first two *valid* frames.
        a, b = np.asarray(joints)[ok], truth.joints[frames][ok]
        out["w_mpjpe_mm_incl_invalid"] = round(float(M.w_mpjpe(a, b, chunk=100)), 2)
        out["pa_mpjpe_mm_incl_invalid"] = round(float(M.pa_mpjpe(a, b)), 2)
    ok = ok & valid
    pred, gt = np.asarray(joints)[ok], truth.joints[frames][ok]
    for c in CHUNKS:
        suffix = "" if c == 100 else f"_c{c}"
        out[f"w_mpjpe_mm{suffix}"] = round(float(M.w_mpjpe(pred, gt, chunk=c)), 2)
        out[f"wa_mpjpe_mm{suffix}"] = round(float(M.wa_mpjpe(pred, gt, chunk=c)), 2)
    out["pa_mpjpe_mm"] = round(float(M.pa_mpjpe(pred, gt)), 2)
    out["rte_pct"] = round(float(M.rte_pct(pred[:, 0], gt[:, 0])), 3)
    out.update(edge_errors(pred, gt))
    return out


def edge_errors(pred: NDArray, gt: NDArray) -> dict:
    """The sequence-edge figures of :func:`motion_errors` for the evaluated frames' joints
    pred, gt (T, J, 3) metres, in order (NaN where there are too few frames)."""
    nan = float("nan")
    starts = M.w_mpjpe_all_starts(pred, gt, chunk=100) if len(pred) >= 2 else np.zeros(0)
    per_frame = M.frame_errors_mm(pred, gt) if len(pred) else np.zeros(0)
    r = lambda x: round(float(x), 2)  # noqa: E731
    return {"w_mpjpe_mm_all_starts_median": r(np.median(starts)) if starts.size else nan,
            "w_mpjpe_mm_all_starts_worst": r(starts.max()) if starts.size else nan,
            "first5_frame_mm": r(per_frame[:EDGE_FRAMES].mean()) if per_frame.size else nan,
            "last5_frame_mm": r(per_frame[-EDGE_FRAMES:].mean()) if per_frame.size else nan,
            "median_frame_mm": r(np.median(per_frame)) if per_frame.size else nan}


def keypoint_errors(lay: SessionLayout, scene: str, seq: str, body_model_path=None, smpl_path: Path | None = None) -> dict:
    """The fitted body's keypoints against the triangulated ones they were fitted to, both against
    the truth, on the (frame, joint) pairs that were triangulated (not gap-filled):

    ``kp3d_triangulation_err_mm`` (median |triangulated - true|), ``kp3d_fit_err_mm`` (median
    |fitted - true|, the fitted body's points of the keypoints' layout) and
    ``fit_vs_triangulation`` (their ratio: below 1, the fit is closer to the truth than its input).
    Keypoints are compared with the truth of the detector's own definition (its hips) when the
    ground truth has it (``joints_keypoints``), else with the true COCO-17 points. Frames are the
    motion's (``smpl_path``, default ``smpl_world.npz``): the contact alignment moves the body,
    so compare before it (``smpl_fit.npz``) when it was applied."""
    import torch

    from embodmocap.body.joints import smpl_to_coco17
    from embodmocap.body.model import load_body_model
    from embodmocap.io.smpl_file import read_smpl_npz
    from embodmocap.motion.stage import keypoint_layout

    sl = lay.sequence(seq)
    gt = lay.ground_truth
    g = read_truth_sequence(gt.sequence(seq))
    T_world_scene = invert_T(read_truth_scene_device(gt.scene_device(scene))["T_scene_vio"])
    raw = read_cameras(sl.view(sl.views()[0]).cameras).raw_frames.astype(np.int64)
    motion = int(g[f"{sl.views()[0]}_motion_start"]) + raw
    true_kp = g["joints_keypoints"] if "joints_keypoints" in g.files else g["joints_coco17"]
    M_frames = len(true_kp)
    k3 = read_keypoints3d(sl.keypoints3d)
    tri, filled = k3["points"], k3["filled"]
    model = load_body_model(body_model_path)
    params, frames = read_smpl_npz(smpl_path or sl.smpl_world)
    with torch.no_grad():
        out = model.from_params(params, dtype=torch.float64)
        fit = smpl_to_coco17(out.joints, out.vertices, model.vertex_ids, keypoint_layout(sl, seq)).numpy()
    T = min(len(tri), len(frames))
    m = motion[frames[:T]]
    inside = (m >= 0) & (m < M_frames)
    truth = true_kp[np.clip(m, 0, M_frames - 1)] @ T_world_scene[:3, :3].T + T_world_scene[:3, 3]
    seen = np.isfinite(tri[:T]).all(-1) & ~filled[:T].astype(bool) & inside[:, None]
    if not seen.any():
        return {}
    e_tri = np.linalg.norm(tri[:T] - truth, axis=-1)[seen]
    e_fit = np.linalg.norm(fit[:T] - truth, axis=-1)[seen]
    return {"kp3d_triangulation_err_mm": round(1000 * float(np.median(e_tri)), 2),
            "kp3d_fit_err_mm": round(1000 * float(np.median(e_fit)), 2),
            "fit_vs_triangulation": round(float(np.median(e_fit) / max(np.median(e_tri), 1e-9)), 3)}


def scene_errors(lay: SessionLayout, scene: str, cfg: EvaluateConfig = EvaluateConfig()) -> dict:
    """Accuracy and completeness of the Stage I mesh against the true scene surface."""
    import trimesh

    from embodmocap.evaluate.mesh_metrics import scene_mesh_metrics
    from embodmocap.geometry.transforms import apply_T
    from embodmocap.io.captures import open_capture
    from embodmocap.scene.config import SceneConfig
    from embodmocap.io.mesh_file import read_mesh_ply
    from embodmocap.io.stage_files import read_keyframes

    gt = lay.ground_truth
    true_mesh = trimesh.load(gt.scene_mesh(scene), force="mesh")
    dev = read_truth_scene_device(gt.scene_device(scene))
    info = read_truth_info(gt.info)
    indoor = info.get("config", {}).get("preset", "indoor") == "indoor"
    kf = read_keyframes(lay.scene(scene).keyframes)
    cap = open_capture(lay.scene_capture(scene))
    v, f, _ = read_mesh_ply(lay.scene(scene).mesh_raw)
    if len(f) == 0:
        raise InputError(lay.scene(scene).mesh_raw, "the scene mesh has no triangles", "re-run the scene stage")
    m = scene_mesh_metrics(apply_T(dev["T_scene_vio"], v), f, np.asarray(true_mesh.vertices), np.asarray(true_mesh.faces),
                           dev["T_scene_cam"][kf["frame_ids"]], cap.depth_intrinsics,
                           SceneConfig().depth_trunc_m(indoor), threshold=cfg.completeness_threshold_m,
                           n_samples=cfg.mesh_samples)
    return {"mesh_accuracy_cm": round(100 * m["accuracy_m"], 3),
            "mesh_completeness_pct": round(100 * m["completeness"], 2)}
