"""Stage I drift correction carried from the key frames to every fused frame
(:func:`embodmocap.scene.adjust.propagate_correction`, :func:`corrected_poses`), against a smooth
synthetic VIO drift whose true correction is known at every frame."""

from __future__ import annotations

import json

import numpy as np

from embodmocap.geometry.transforms import invert_T, make_T, rot_z
from embodmocap.scene.adjust import apply_correction, correction_of, corrected_poses, propagate_correction

FPS = 30.0


def _walk(n: int, rng) -> np.ndarray:
    """(n, 4, 4) camera-to-world poses of a slow loop around a room, cameras looking outwards."""
    a = np.linspace(0, 2 * np.pi, n)
    T = np.stack([make_T(rot_z(x) @ np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]]).T,
                         np.array([1.5 * np.cos(x), 1.0 * np.sin(x), 1.4])) for x in a])
    T[:, :3, 3] += rng.normal(0, 0.003, (n, 3))
    return T


def _drift(t: np.ndarray) -> np.ndarray:
    """(n, 4, 4) a slow VIO-like drift D(t) with D(0) = I: yaw about a point plus a bent translation."""
    yaw = np.radians(0.1) * np.sin(t / 6.0)
    p0 = np.array([1.5, 0.0, 1.4])
    d = np.stack([0.012 * np.sin(t / 5.0), 0.008 * (1 - np.cos(t / 4.0)), 0.002 * t / 15], axis=1)
    return np.stack([make_T(rot_z(y), p0 - rot_z(y) @ p0 + dd) for y, dd in zip(yaw, d)])


def test_key_frame_corrections_carried_to_every_frame_recover_the_true_poses():
    rng = np.random.default_rng(3)
    n = 450  # a 15 s scan
    t = np.arange(n) / FPS
    T_true = _walk(n, rng)
    T_vio = _drift(t) @ T_true
    key = np.arange(0, n, 10)  # a key frame every third of a second
    C_key = correction_of(T_vio[key], T_true[key])  # what a perfect adjustment finds
    out = propagate_correction(t[key], C_key, t, T_vio)
    err = np.linalg.norm(out[:, :3, 3] - T_true[:, :3, 3], axis=1)
    before = np.linalg.norm(T_vio[:, :3, 3] - T_true[:, :3, 3], axis=1)
    assert before.max() > 0.01
    assert err[: key[-1] + 1].max() < 2e-4  # between key frames: the drift is smooth, linear interpolation suffices
    np.testing.assert_allclose(out[key], T_true[key], atol=1e-12)  # key frames exactly
    rot_err = np.einsum("nij,nij->n", out[:, :3, :3], T_true[:, :3, :3])  # trace(R^T R_true)
    assert np.degrees(np.arccos(np.clip((rot_err - 1) / 2, -1, 1)))[: key[-1] + 1].max() < 1e-3
    # Frames after the last key frame keep its correction (the drift barely moves in 0.3 s).
    tail = np.arange(key[-1], n)
    assert np.linalg.norm(out[tail, :3, 3] - T_true[tail, :3, 3], axis=1).max() < 2e-3


def test_apply_correction_is_a_world_side_transform_about_the_pivot():
    rng = np.random.default_rng(4)
    T = _walk(5, rng)
    p0 = T[0, :3, 3]
    q = np.zeros((5, 6))
    q[:, 2] = np.radians(0.5)
    q[:, 3:] = [0.01, -0.02, 0.003]
    out = apply_correction(q, T, p0)
    C = make_T(rot_z(np.radians(0.5)), p0 - rot_z(np.radians(0.5)) @ p0 + np.array([0.01, -0.02, 0.003]))
    np.testing.assert_allclose(out, C @ T, atol=1e-12)
    np.testing.assert_allclose(correction_of(T, out), np.broadcast_to(C, (5, 4, 4)), atol=1e-12)


def test_corrected_poses_reads_the_models_correction_and_leaves_poses_alone_without_one(tmp_path):
    rng = np.random.default_rng(5)
    T = _walk(40, rng)
    t = np.arange(40) / FPS
    assert np.array_equal(corrected_poses(tmp_path, t, T), T)  # no model summary: unchanged
    C = _drift(np.array([0.0, 1.0, 2.0]))
    C = invert_T(C)
    summary = {"drift_correction": {"accepted": False, "reason": "x", "times_s": [0.0, 0.6, 1.2],
                                    "T_correction": C.tolist()}}
    (tmp_path / "summary.json").write_text(json.dumps(summary))
    assert np.array_equal(corrected_poses(tmp_path, t, T), T)  # rejected: unchanged
    summary["drift_correction"]["accepted"] = True
    (tmp_path / "summary.json").write_text(json.dumps(summary))
    out = corrected_poses(tmp_path, t, T)
    np.testing.assert_allclose(out, propagate_correction(np.array([0.0, 0.6, 1.2]), C, t, T))
    assert not np.allclose(out, T)
