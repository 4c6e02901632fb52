"""Evaluation metrics: known answers computed by hand, round trips and zero cases."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from embodmocap.evaluate.metrics import (
    depth_err_m2, foot_skating, jitter, mask_iou_pct, mpjpe, pa_mpjpe, reproj_err_px, rte_pct,
    sync_err_frames, umeyama, view_offset_err, w_mpjpe, wa_mpjpe,
)
from embodmocap.geometry.transforms import make_T, rot_z


def _motion(T=10, J=5, seed=0):
    """(T, J, 3) a wandering skeleton-like point set, metres."""
    rng = np.random.default_rng(seed)
    body = rng.normal(scale=0.3, size=(1, J, 3))
    path = np.cumsum(rng.normal(scale=0.05, size=(T, 1, 3)), axis=0)
    return body + path + 0.01 * rng.normal(size=(T, J, 3))


def _similarity(x, s, R, t):
    return s * x @ R.T + t


# ----------------------------------------------------------------------------- umeyama


def test_umeyama_recovers_known_similarity_batched():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(4, 12, 3))
    s_true = np.array([0.5, 1.0, 1.7, 3.0])
    R_true = Rotation.random(4, random_state=2).as_matrix()
    t_true = rng.normal(size=(4, 3))
    dst = s_true[:, None, None] * np.einsum("bij,bnj->bni", R_true, src) + t_true[:, None]
    s, R, t = umeyama(src, dst, with_scale=True)
    assert s.shape == (4,) and R.shape == (4, 3, 3) and t.shape == (4, 3)
    np.testing.assert_allclose(s, s_true, atol=1e-10)
    np.testing.assert_allclose(R, R_true, atol=1e-10)
    np.testing.assert_allclose(t, t_true, atol=1e-10)


def test_umeyama_rigid_keeps_unit_scale_and_never_reflects():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(20, 3))
    R_true = Rotation.random(random_state=4).as_matrix()
    s, R, t = umeyama(src, 2.0 * src @ R_true.T, with_scale=False)
    assert s == 1.0
    np.testing.assert_allclose(R, R_true, atol=1e-10)
    # A mirror image cannot be reached by a rotation: R must stay proper.
    _, R_m, _ = umeyama(src, src * [1, 1, -1], with_scale=True)
    assert np.linalg.det(R_m) == pytest.approx(1.0)


def test_umeyama_rejects_mismatched_shapes():
    with pytest.raises(ValueError):
        umeyama(np.zeros((5, 3)), np.zeros((4, 3)))


# ----------------------------------------------------------------------------- joint errors


def test_identical_inputs_give_zero():
    x = _motion(T=30)
    for f in (mpjpe, pa_mpjpe, w_mpjpe, wa_mpjpe):
        assert f(x, x) == pytest.approx(0.0, abs=1e-9)
    assert rte_pct(x[:, 0], x[:, 0]) == pytest.approx(0.0, abs=1e-9)


def test_rigid_offset_zero_for_aligned_metrics_known_for_unaligned():
    gt = _motion(T=30)
    R = rot_z(np.deg2rad(30.0))
    pred_shift = gt + np.array([0.03, -0.04, 0.0])  # 5 cm everywhere
    assert mpjpe(pred_shift, gt) == pytest.approx(50.0)
    pred = _similarity(gt, 1.0, R, [1.0, 2.0, 0.5])
    for f in (pa_mpjpe, w_mpjpe, wa_mpjpe):
        assert f(pred, gt, **({} if f is pa_mpjpe else {"chunk": 7})) == pytest.approx(0.0, abs=1e-8)
    assert rte_pct(pred[:, 0], gt[:, 0]) == pytest.approx(0.0, abs=1e-8)
    # A similarity (scale 2) is removed by the scaled alignments only.
    pred2 = _similarity(gt, 2.0, R, [1.0, 2.0, 0.5])
    assert wa_mpjpe(pred2, gt) == pytest.approx(0.0, abs=1e-8)
    assert wa_mpjpe(pred2, gt, with_scale=False) > 1.0


def test_w_mpjpe_hand_computed_with_chunks():
    """Frames 0-1 exact, frames 2.. 1 cm off in x; then the whole prediction rotated and moved.

    The first-two-frame alignment undoes the rotation exactly (frames 0-1 match), so each offset
    frame costs 10 mm; a chunk that starts on offset frames is aligned away entirely.
    """
    T, J = 10, 5
    gt = _motion(T=T, J=J)
    pred = gt.copy()
    pred[2:] += [0.01, 0.0, 0.0]
    pred = _similarity(pred, 1.0, Rotation.from_euler("zyx", [20, 5, -3], degrees=True).as_matrix(), [3, -1, 0.2])
    assert w_mpjpe(pred, gt, chunk=100) == pytest.approx(10.0 * 8 / 10)
    assert w_mpjpe(pred, gt, chunk=100, with_scale=False) == pytest.approx(10.0 * 8 / 10)
    # chunk 5: [0..4] has 3 offset frames -> 30 mm*frames; [5..9] all offset alike -> 0.
    assert w_mpjpe(pred, gt, chunk=5) == pytest.approx(30.0 / 10)


def test_w_mpjpe_last_chunk_kept_only_with_two_frames():
    gt = _motion(T=12, J=4)
    pred = gt.copy()
    pred[2:5] += [0.0, 0.01, 0.0]  # 10 mm in frames 2, 3, 4 of the first chunk
    # T = 11: frame 10 alone would be a 1-frame chunk: dropped, so its huge error never counts.
    p11, g11 = pred[:11].copy(), gt[:11]
    p11[10] += 5.0
    assert w_mpjpe(p11, g11, chunk=5) == pytest.approx(30.0 / 10)
    # T = 12: the last chunk (frames 10, 11) is kept; it aligns exactly onto itself (2 frames).
    p12 = pred.copy()
    p12[10:] = _similarity(p12[10:], 1.0, rot_z(0.3), [1, 1, 1])
    assert w_mpjpe(p12, gt, chunk=5) == pytest.approx(30.0 / 12)


def test_pa_mpjpe_hand_computed_saddle():
    """A unit cross in the xy plane; the prediction lifts the x arms by e and drops the y arms by e.

    No rotation helps (the cross-covariance is diag(2, 2, 0)); the best scale is 1/(1+e^2), which
    leaves every point e/sqrt(1+e^2) away.
    """
    e = 0.01
    gt = np.array([[[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]]], dtype=float)
    pred = gt.copy()
    pred[0, :2, 2] = e
    pred[0, 2:, 2] = -e
    expected_mm = 1000 * e / np.sqrt(1 + e * e)
    assert pa_mpjpe(pred, gt) == pytest.approx(expected_mm, rel=1e-9)
    # Per-frame alignment: a different similarity in every frame still gives 0.
    gt2 = _motion(T=6)
    pred2 = np.stack([_similarity(g, 1 + i, rot_z(i * 0.5), [i, 0, 0]) for i, g in enumerate(gt2)])
    assert pa_mpjpe(pred2, gt2) == pytest.approx(0.0, abs=1e-8)


def test_rte_hand_computed_straight_line():
    """Truth walks 1 m along x in 11 frames; the prediction walks 2 m. The rigid alignment
    centres it: errors |x - 0.5| for x = 0, 0.1, .., 1 -> mean 3/11 m, over a 1 m path."""
    x = np.linspace(0.0, 1.0, 11)
    gt = np.stack([x, np.zeros(11), np.zeros(11)], axis=1)
    pred = 2 * gt + [5.0, 1.0, 0.0]
    assert rte_pct(pred, gt) == pytest.approx(100 * 3 / 11)
    assert rte_pct(pred, gt, with_scale=True) == pytest.approx(0.0, abs=1e-9)
    assert np.isnan(rte_pct(np.zeros((5, 3)), np.zeros((5, 3))))


# ----------------------------------------------------------------------------- smoothness


def test_jitter_known_jerk():
    t = np.arange(20, dtype=float)
    c, fps = 1e-3, 30.0
    cubic = np.zeros((20, 2, 3))
    cubic[..., 0] = c * t[:, None] ** 3  # third difference = 6 c per frame^3
    assert jitter(cubic, fps) == pytest.approx(6 * c * fps ** 3 / 10)
    quadratic = np.zeros((20, 2, 3))
    quadratic[..., 1] = 0.5 * t[:, None] ** 2 + t[:, None]
    assert jitter(quadratic, fps) == pytest.approx(0.0, abs=1e-6)
    assert np.isnan(jitter(cubic[:3], fps))


def test_foot_skating_counts_only_truth_contacts():
    T = 6
    gt = np.zeros((T, 2, 3))
    gt[:, 1, 0] = 0.05 * np.arange(T)  # point 1 walks 5 cm/frame: never in contact
    pred = gt.copy()
    pred[:, 0, 1] = 0.002 * np.arange(T)  # point 0 slides 2 mm/frame while planted
    assert foot_skating(pred, gt) == pytest.approx(2.0)
    assert np.isnan(foot_skating(pred[:, 1:], gt[:, 1:]))


# ----------------------------------------------------------------------------- images


def test_mask_iou_hand_computed():
    gt = np.zeros((3, 4, 4), bool)
    pred = np.zeros((3, 4, 4), bool)
    gt[0, :2, :3] = True    # 6 px
    pred[0, :2, :2] = True  # 4 px inside -> 4/6
    gt[1, 0, 0] = True      # disjoint -> 0
    pred[1, 3, 3] = True
    # frame 2: both empty -> left out
    assert mask_iou_pct(pred, gt) == pytest.approx(100 * (4 / 6 + 0) / 2)
    assert mask_iou_pct(gt, gt) == pytest.approx(100.0)
    assert np.isnan(mask_iou_pct(pred[2:], gt[2:]))


def test_reproj_err_weighted_by_confidence():
    kp = np.array([[[10, 10, 1.0], [0, 0, 0.5], [50, 50, 0.0], [7, 7, 0.9]]])
    pred = np.array([[[13, 14], [0, 4], [500, 500], [np.nan, 7]]], dtype=float)
    # errors 5 (w 1) and 4 (w 0.5); the 0-confidence and NaN points do not count.
    assert reproj_err_px(pred, kp) == pytest.approx((5 * 1 + 4 * 0.5) / 1.5)
    assert reproj_err_px(kp[..., :2], kp) == pytest.approx(0.0)
    assert np.isnan(reproj_err_px(pred[:, 2:3], kp[:, 2:3]))


def test_depth_err_hand_computed():
    sensor = np.array([[2.0, 2.0], [0.0, 3.0]])
    pred = np.array([[2.1, 1.8], [1.0, np.nan]])
    mask = np.array([[True, True], [True, True]])
    # valid: (0,0) err 0.1, (0,1) err 0.2; (1,0) no sensor depth; (1,1) no prediction.
    assert depth_err_m2(pred, sensor, mask) == pytest.approx((0.01 + 0.04) / 2)
    assert depth_err_m2(pred, sensor, mask & [[True, False], [True, True]]) == pytest.approx(0.01)
    assert np.isnan(depth_err_m2(pred, sensor, np.zeros((2, 2), bool)))


# ----------------------------------------------------------------------------- cameras, sync


def test_view_offset_err_known_offset():
    T_true = make_T(rot_z(np.deg2rad(40.0)), [1.0, 2.0, 0.0])
    # The estimate differs by a 3 deg yaw about the first centre and a 5 cm shift.
    c0 = np.array([0.5, -0.2, 1.4])
    centres = np.array([c0, c0])
    err = make_T(rot_z(np.deg2rad(3.0)), np.zeros(3))
    p = T_true[:3, :3] @ c0 + T_true[:3, 3]
    T_est = make_T(np.eye(3), p + [0.05, 0, 0]) @ err @ make_T(np.eye(3), -p) @ T_true
    cm, deg = view_offset_err(T_est, T_true, centres)
    assert cm == pytest.approx(5.0)
    assert deg == pytest.approx(3.0)
    assert view_offset_err(T_true, T_true, centres) == pytest.approx((0.0, 0.0), abs=1e-6)


def test_sync_err_frames():
    assert sync_err_frames(103, 100) == 3.0
    np.testing.assert_array_equal(sync_err_frames([10, 20], [12, 20]), [2.0, 0.0])
    with pytest.raises(ValueError):
        sync_err_frames([1, 2], [1])


def test_shape_mismatch_is_rejected():
    with pytest.raises(ValueError):
        w_mpjpe(np.zeros((10, 3, 3)), np.zeros((10, 4, 3)))
    with pytest.raises(ValueError):
        mask_iou_pct(np.zeros((2, 3, 3)), np.zeros((2, 3, 4)))
    with pytest.raises(ValueError):
        w_mpjpe(np.zeros((10, 3, 3)), np.zeros((10, 3, 3)), chunk=1)
