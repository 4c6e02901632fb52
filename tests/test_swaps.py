"""Left/right swaps of 2D keypoints: found with the other views and undone, the right view chosen."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from embodmocap.body.model import load_body_model
from embodmocap.geometry.transforms import R_ZUP_YUP, look_at_T
from embodmocap.geometry.triangulation import projection_matrices
from embodmocap.motion.swaps import COCO17_SWAP_GROUPS, fix_swaps

K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])


@pytest.fixture(scope="module")
def scene():
    """60 frames of a body walking along +x with one arm raised and turning slowly, seen by
    three cameras around it; (coco (T, 17, 3), P (T, 3, 3, 4), keypoints (T, 3, 17, 3))."""
    from scipy.spatial.transform import Rotation

    body = load_body_model(None)
    T = 60
    yaw = np.linspace(0, 0.6, T)
    go = (Rotation.from_euler("z", yaw[:, None]) * Rotation.from_matrix(R_ZUP_YUP)).as_rotvec()
    pose = np.zeros((T, 69))
    # Asymmetric on purpose: with both arms hanging alike, swapping them in one view is almost
    # consistent with the other view (a mirrored body), and nothing can tell (nor does it matter).
    pose[:, 15 * 3 + 0] = -1.2  # left arm raised forwards
    pose[:, 17 * 3 + 1] = -1.0  # left elbow bent
    pose[:, 0] = 0.6 * np.sin(np.linspace(0, 6, T))  # left hip swings (a stride)
    pose[:, 3 * 3 + 0] = 0.8  # left knee bent
    transl = np.column_stack([np.linspace(0, 1.5, T), np.zeros(T), np.full(T, 0.9)])
    with torch.no_grad():
        coco = body.forward(np.zeros(10), go, pose, transl, dtype=torch.float64).coco17.numpy()
    centre = np.array([0.75, 0.0, 1.0])
    # One camera held high: with both at one height the epipolar lines run level and a left/right
    # swap (a sideways shift) slides along them, unseen.
    cams = [look_at_T(centre + 3.5 * np.array([np.cos(a), np.sin(a), h]), centre)
            for a, h in ((0.9, 0.1), (2.2, 0.7), (3.8, 0.3))]
    T_wc = np.broadcast_to(np.stack(cams), (T, 3, 4, 4))
    P = projection_matrices(K, T_wc)
    h = np.concatenate([coco, np.ones((T, 17, 1))], axis=-1)
    uvw = np.einsum("tvab,tjb->tvja", P, h)
    kp = np.concatenate([uvw[..., :2] / uvw[..., 2:], np.full(uvw.shape[:-1] + (1,), 0.9)], axis=-1)
    kp[..., :2] += np.random.default_rng(0).normal(0, 1.0, kp[..., :2].shape)
    return coco, P, kp


def _swapped(kp, view, frames, group):
    out = kp.copy()
    for a, b in COCO17_SWAP_GROUPS[group]:
        out[frames, view, a], out[frames, view, b] = kp[frames, view, b], kp[frames, view, a]
    return out


def test_clean_keypoints_are_left_alone(scene):
    _, P, kp = scene
    fixed, swapped = fix_swaps(P[:, :2], kp[:, :2])
    assert not swapped.any()
    np.testing.assert_array_equal(fixed, kp[:, :2])


@pytest.mark.parametrize("group", ["arms"])  # the legs of this clip are too alike to tell apart
@pytest.mark.parametrize("view", [0, 1])
def test_two_views_swap_undone_in_the_right_view(scene, group, view):
    """A run of frames in the middle (the swapped view's labels jump at its ends) and a run from the
    first frame (only its end tells)."""
    _, P, kp = scene
    g = list(COCO17_SWAP_GROUPS).index(group)
    for frames in (np.arange(20, 31), np.arange(0, 8)):
        bad = _swapped(kp[:, :2], view, frames, group)
        fixed, swapped = fix_swaps(P[:, :2], bad)
        np.testing.assert_array_equal(np.flatnonzero(swapped[:, view, g]), frames)
        assert not swapped[:, 1 - view].any()
        np.testing.assert_array_equal(fixed, kp[:, :2])


def test_three_views_need_no_tie_break(scene):
    _, P, kp = scene
    frames = np.arange(10, 50)
    bad = _swapped(kp, 2, frames, "arms")
    fixed, swapped = fix_swaps(P, bad)
    np.testing.assert_array_equal(np.flatnonzero(swapped[:, 2, list(COCO17_SWAP_GROUPS).index("arms")]), frames)
    np.testing.assert_array_equal(fixed, kp)


def test_a_groups_trial_triangulates_only_its_joints_and_frames_with_the_same_bits(scene):
    # fix_swaps' trials re-triangulate only the swapped group's joints, only on the frames they
    # judge, the other points carried: each equals that point of a full triangulation.
    from embodmocap.geometry.triangulation import TriangulationConfig
    from embodmocap.motion.swaps import _frame_error

    _, P, kp = scene
    kp = kp.copy()
    kp[::7, 1, 9, 2] = 0.0  # some wrists unseen by one view
    trial = _swapped(kp, 1, slice(10, 30), "arms")
    joints = [7, 8, 9, 10]
    tcfg, cap = TriangulationConfig(), 20.0
    err_all, X_all = _frame_error(P, trial[..., :2], trial[..., 2], tcfg, cap, joints)
    _, X_given = _frame_error(P, kp[..., :2], kp[..., 2], tcfg, cap, joints)
    err, X = _frame_error(P, trial[..., :2], trial[..., 2], tcfg, cap, joints, X_given)
    assert np.array_equal(err, err_all) and np.array_equal(X, X_all, equal_nan=True)
    frames = np.arange(5, 40, 3)
    err_f, X_f = _frame_error(P, trial[..., :2], trial[..., 2], tcfg, cap, joints, X_given, frames)
    assert np.array_equal(err_f[frames], err_all[frames]) and np.isinf(np.delete(err_f, frames)).all()
    assert np.array_equal(X_f[frames], X_all[frames], equal_nan=True)
    assert np.array_equal(np.delete(X_f, frames, 0), np.delete(X_given, frames, 0), equal_nan=True)
    # the swap moved the arms' points (the comparison is not between equal arrays)
    assert not np.allclose(X_all[10:30, 7:11], X_given[10:30, 7:11], equal_nan=True)
    assert np.isinf(_frame_error(P, trial[..., :2], trial[..., 2], tcfg, cap, joints, X_given, frames[:0])[0]).all()
