"""Transforms: round trips, reference implementations and the fixed convention changes."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from embodmocap.geometry import transforms as tf
from embodmocap.types import Intrinsics


def random_T(rng, n):
    R = Rotation.random(n, random_state=rng.integers(1 << 31)).as_matrix()
    return tf.make_T(R, rng.normal(size=(n, 3)))


def test_invert_is_inverse_and_matches_numpy():
    rng = np.random.default_rng(0)
    T = random_T(rng, 50)
    Ti = tf.invert_T(T)
    np.testing.assert_allclose(Ti @ T, np.broadcast_to(np.eye(4), T.shape), atol=1e-12)
    np.testing.assert_allclose(Ti, np.linalg.inv(T), atol=1e-12)


def test_apply_matches_homogeneous_loop():
    rng = np.random.default_rng(1)
    T = random_T(rng, 4)
    p = rng.normal(size=(4, 7, 3))
    out = tf.apply_T(T, p)
    for i in range(4):
        for j in range(7):
            ref = T[i] @ np.append(p[i, j], 1.0)
            np.testing.assert_allclose(out[i, j], ref[:3], atol=1e-12)


def test_quaternion_round_trip_and_scipy_reference():
    rng = np.random.default_rng(2)
    q = rng.normal(size=(100, 4))
    R = tf.quat_to_matrix(q)
    np.testing.assert_allclose(R, Rotation.from_quat(q).as_matrix(), atol=1e-12)
    q2 = tf.matrix_to_quat(R)
    assert np.all(q2[:, 3] >= 0)
    np.testing.assert_allclose(tf.quat_to_matrix(q2), R, atol=1e-12)
    with pytest.raises(ValueError):
        tf.quat_to_matrix(np.zeros(4))


def test_zup_from_yup_maps_arkit_up_to_z():
    # ARKit: +Y is up, +Z points toward the viewer. Ours: +Z up.
    T = tf.T_zup_from_yup()
    up = tf.apply_T(T, np.array([[0.0, 1.0, 0.0]]))[0]
    np.testing.assert_allclose(up, [0, 0, 1], atol=1e-12)
    assert np.isclose(np.linalg.det(T[:3, :3]), 1.0)


def test_gl_cv_flip_is_involution_and_keeps_centre():
    rng = np.random.default_rng(3)
    T = random_T(rng, 10)
    G = tf.gl_to_cv_cam(T)
    np.testing.assert_allclose(G[:, :3, 3], T[:, :3, 3])
    np.testing.assert_allclose(tf.gl_to_cv_cam(G), T, atol=1e-12)
    # OpenGL looks down -z: the CV forward axis (+z) is the GL -z axis.
    np.testing.assert_allclose(G[:, :3, 2], -T[:, :3, 2])


def test_rot_z_rot_x_and_angle():
    yaw = np.array([0.0, 0.3, -2.0])
    R = tf.rot_z(yaw)
    np.testing.assert_allclose(R, Rotation.from_euler("z", yaw[:, None]).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(tf.rotation_angle(R), np.abs(yaw), atol=1e-9)
    np.testing.assert_allclose(tf.rot_x(0.7), Rotation.from_euler("x", 0.7).as_matrix(), atol=1e-12)


def test_is_rigid_flags_bad_transforms():
    T = np.stack([np.eye(4)] * 4)
    T[1, 0, 0] = 2.0  # scaled
    T[2, 0, 3] = np.nan
    T[3, :3, :3] = np.diag([1, 1, -1])  # reflection
    assert tf.is_rigid(T).tolist() == [True, False, False, False]


def test_intrinsics_scaling_pixel_centres():
    K = Intrinsics(1450.0, 1450.0, 959.5, 719.5, 1920, 1440)
    d = K.scaled(256, 192)
    assert d.width == 256 and d.height == 192
    assert np.isclose(K.fx / d.fx, 7.5)
    # The principal point at the exact image centre stays at the centre.
    assert np.isclose(d.cx, 127.5) and np.isclose(d.cy, 95.5)
    back = d.scaled(1920, 1440)
    np.testing.assert_allclose(back.K, K.K, atol=1e-9)


def test_look_at_points_the_camera_at_the_target_without_roll():
    from embodmocap.geometry.transforms import look_at_R, look_at_T

    rng = np.random.default_rng(3)
    c = rng.normal(size=(5, 3))
    t = c + rng.normal(size=(5, 3))
    T = look_at_T(c, t)
    R = T[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), (5, 3, 3)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0)
    d = (t - c) / np.linalg.norm(t - c, axis=1, keepdims=True)
    np.testing.assert_allclose(R[:, :, 2], d, atol=1e-12)  # optical axis at the target
    np.testing.assert_allclose(R[:, 2, 0], 0.0, atol=1e-12)  # camera x horizontal: no roll
    assert np.all(R[:, 2, 1] < 0)  # image y points down in the world
    np.testing.assert_allclose(T[:, :3, 3], c)
    np.testing.assert_allclose(look_at_T(c[0], t[0]), T[0])
    np.testing.assert_allclose(look_at_R(c, t), R)
