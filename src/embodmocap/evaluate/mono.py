"""Errors of ``embodmocap mono``'s outputs, per view, for ``embodmocap evaluate``.

Against the ground truth when the session has one (synthetic sessions), otherwise against the
dual-view result (Stage IV's ``smpl_world.npz`` and the view's ``cameras_final.npz``); the key
``<v>_mono_reference`` says which. Keys (``<v>`` = ``v1``, ``v2``):

- ``<v>_mono_w_mpjpe_mm``, ``<v>_mono_wa_mpjpe_mm``: W-/WA-MPJPE (100-frame chunks) of the 24
  SMPL joints; ``<v>_mono_rte_pct``: RTE of the pelvis (``evaluate.metrics``);
- ``<v>_mono_camera_err_cm``: mean camera-centre distance after one rigid alignment per segment
  (the metric claim: a wrong scale shows);
- ``<v>_mono_scale_err_pct``: ``100 |s - 1|`` with ``s`` the scale of the similarity between the
  camera centres and the reference's (frame-weighted over segments);
- ``<v>_mono_segments``: number of segments (1 when every chunk was aligned).
"""

from __future__ import annotations

import numpy as np

from embodmocap.evaluate import metrics as M
from embodmocap.evaluate.truth import sequence_truth
from embodmocap.io.layout import VIEWS, SessionLayout


def mono_metrics(lay: SessionLayout, scene: str, seq: str, body_model_path=None) -> dict:
    """The ``<v>_mono_*`` keys of every view of ``seq`` that has monocular outputs (empty dict if none)."""
    import torch

    from embodmocap.body.model import load_body_model
    from embodmocap.io.smpl_file import read_smpl_npz, read_smpl_valid
    from embodmocap.io.stage_files import read_cameras
    from embodmocap.mono.files import read_mono_cameras

    sl = lay.sequence(seq)
    views = [v for v in VIEWS if sl.mono(v).smpl_world.is_file() and sl.mono(v).cameras_world.is_file()]
    if not views:
        return {}
    model = load_body_model(body_model_path)
    has_gt = lay.ground_truth.info.is_file()
    truth = None
    if has_gt:
        truth = sequence_truth(lay, scene, seq)
    elif not sl.smpl_world.is_file():
        return {f"{v}_mono_reference": "none (no ground truth and no dual-view result)" for v in views}
    else:
        ref_params, _ = read_smpl_npz(sl.smpl_world)
        with torch.no_grad():
            ref_joints = model.from_params(ref_params, dtype=torch.float64).joints.numpy()
    out: dict = {}
    for v in views:
        ml = sl.mono(v)
        params, frames = read_smpl_npz(ml.smpl_world)
        valid = read_smpl_valid(ml.smpl_world)
        with torch.no_grad():
            joints = model.from_params(params, dtype=torch.float64).joints.numpy()
        mc = read_mono_cameras(ml.cameras_world)
        if truth is not None:
            ref_j, ok_ref = truth.joints, truth.valid
            ref_cam = truth.T_world_cam[v]
            out[f"{v}_mono_reference"] = "ground truth"
        else:
            ref_j, ok_ref = ref_joints, np.ones(len(ref_joints), bool)
            ref_cam = read_cameras(sl.view(v).cameras_final).T_world_cam
            out[f"{v}_mono_reference"] = "dual view"
        n = min(len(frames), len(ref_j), len(mc["T_world_cam"]), len(ref_cam))
        ok = ok_ref[frames[:n]] & valid[:n]
        pred, gt = joints[:n][ok], ref_j[frames[:n]][ok]
        out[f"{v}_mono_w_mpjpe_mm"] = round(float(M.w_mpjpe(pred, gt, chunk=100)), 2)
        out[f"{v}_mono_wa_mpjpe_mm"] = round(float(M.wa_mpjpe(pred, gt, chunk=100)), 2)
        out[f"{v}_mono_rte_pct"] = round(float(M.rte_pct(pred[:, 0], gt[:, 0])), 3)
        cam_err, scale_err = camera_errors(mc["T_world_cam"][:n, :3, 3], ref_cam[:n, :3, 3], mc["segment"][:n],
                                            mc["metric_scale"][:n])
        out[f"{v}_mono_camera_err_cm"] = round(100 * cam_err, 3)
        out[f"{v}_mono_scale_err_pct"] = round(100 * scale_err, 3)
        out[f"{v}_mono_segments"] = int(mc["segment"].max()) + 1
    return out


def camera_errors(centres, ref_centres, segment, metric_scale=None) -> tuple[float, float]:
    """(mean distance after a rigid alignment per segment, frame-weighted ``|s - 1|`` of the
    similarity per segment) of camera centres (T, 3) against reference centres (T, 3); frames
    without a metric scale (``metric_scale`` NaN: flagged invalid) are left out."""
    errs, sc, w = [], [], []
    for g in np.unique(segment):
        m = segment == g
        if metric_scale is not None:
            m &= np.isfinite(metric_scale)
        if m.sum() < 3:
            continue
        p, q = centres[m], ref_centres[m]
        s1, R1, t1 = M.umeyama(p, q, with_scale=False)
        errs.append(np.linalg.norm(p @ R1.T + t1 - q, axis=1))
        s, _, _ = M.umeyama(p, q, with_scale=True)
        sc.append(abs(float(s) - 1.0))
        w.append(m.sum())
    if not errs:
        return float("nan"), float("nan")
    return float(np.concatenate(errs).mean()), float(np.average(sc, weights=w))
