"""Rigid transforms, quaternions and the fixed convention changes.

Conventions (the package's one convention):

- World: right-handed, **Z up**, metres.
- Cameras: **OpenCV** axes (x right, y down, z forward).
- ``T_a_b`` is a (..., 4, 4) homogeneous matrix mapping points in frame ``b`` into frame ``a``:
  ``p_a = T_a_b @ p_b``. So ``T_world_cam`` is camera-to-world and its translation is the camera
  centre in the world.
- Quaternions are stored **(x, y, z, w)** (scalar last), as in scipy and in the capture apps' CSVs;
  every rotation conversion lives in :mod:`embodmocap.geometry.rotations` (``quat_to_matrix`` and
  ``matrix_to_quat`` are re-exported here for the modules that import them from this one).

All functions accept any leading batch shape and are vectorised (no Python loops over frames).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from embodmocap.geometry.rotations import matrix_to_quat, quat_to_matrix  # noqa: F401 (re-exported)

F = NDArray[np.floating]

#: Rotation taking ARKit's Y-up world axes to our Z-up world axes: x stays, old y (up) becomes z,
#: old z (towards the viewer) becomes -y. A +90 degree rotation about x.
R_ZUP_YUP: F = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

#: Flips between OpenGL camera axes (x right, y up, z backward) and OpenCV axes; its own inverse.
R_CV_GL: F = np.diag([1.0, -1.0, -1.0])


def make_T(R: F, t: F) -> F:
    """Stack rotations (..., 3, 3) and translations (..., 3) into (..., 4, 4) transforms."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    shape = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    T = np.zeros(shape + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def look_at_R(centres: F, targets: F) -> F:
    """Camera-to-world rotations (..., 3, 3), OpenCV axes, looking from ``centres`` at ``targets``
    (both (..., 3), broadcast) with no roll in a Z-up world (camera x horizontal, y pointing
    down-ish). Undefined when looking straight up or down."""
    z = np.asarray(targets, dtype=np.float64) - np.asarray(centres, dtype=np.float64)
    z = z / np.linalg.norm(z, axis=-1, keepdims=True)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x = x / np.linalg.norm(x, axis=-1, keepdims=True)
    return np.stack([x, np.cross(z, x), z], axis=-1)


def look_at_T(centres: F, targets: F) -> F:
    """Camera-to-world transforms (..., 4, 4) of :func:`look_at_R` cameras at ``centres``."""
    return make_T(look_at_R(centres, targets), np.broadcast_to(np.asarray(centres, dtype=np.float64),
                                                                np.broadcast_shapes(np.shape(centres), np.shape(targets))))


def invert_T(T: F) -> F:
    """Inverse of rigid transforms (..., 4, 4), using R^T rather than a general inverse."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Rt = np.swapaxes(R, -1, -2)
    return make_T(Rt, -np.einsum("...ij,...j->...i", Rt, t))


def apply_T(T: F, points: F) -> F:
    """Apply transforms (..., 4, 4) to points (..., N, 3); batch shapes broadcast."""
    T = np.asarray(T, dtype=np.float64)
    p = np.asarray(points, dtype=np.float64)
    return np.einsum("...ij,...nj->...ni", T[..., :3, :3], p) + T[..., None, :3, 3]


def rot_z(yaw: F) -> F:
    """Rotations (..., 3, 3) about +Z by ``yaw`` radians (...)."""
    yaw = np.asarray(yaw, dtype=np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    o, i = np.zeros_like(yaw), np.ones_like(yaw)
    return np.stack([c, -s, o, s, c, o, o, o, i], axis=-1).reshape(yaw.shape + (3, 3))


def rot_x(angle: F) -> F:
    """Rotations (..., 3, 3) about +X by ``angle`` radians (...)."""
    a = np.asarray(angle, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    o, i = np.zeros_like(a), np.ones_like(a)
    return np.stack([i, o, o, o, c, -s, o, s, c], axis=-1).reshape(a.shape + (3, 3))


def rotation_angle(R: F) -> F:
    """Angle in radians (...) of rotations (..., 3, 3); robust near 0 and pi."""
    R = np.asarray(R, dtype=np.float64)
    cos = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arccos(np.clip(cos, -1.0, 1.0))


def T_zup_from_yup() -> F:
    """``T_zup_yup``: the 4x4 change of world frame from a Y-up (ARKit) world to our Z-up one."""
    return make_T(R_ZUP_YUP, np.zeros(3))


def gl_to_cv_cam(T_world_glcam: F) -> F:
    """Camera-to-world poses with OpenGL camera axes (..., 4, 4) -> OpenCV camera axes.

    Right-multiplying by diag(1, -1, -1, 1) re-labels the camera's own axes; the camera centre and
    the world are unchanged. The operation is its own inverse, so it also converts CV -> GL.
    """
    T = np.array(T_world_glcam, dtype=np.float64, copy=True)
    T[..., :3, :3] = T[..., :3, :3] @ R_CV_GL
    return T


def is_rigid(T: F, atol: float = 1e-4) -> NDArray[np.bool_]:
    """True where (..., 4, 4) is a finite proper rigid transform (orthonormal R, det +1)."""
    T = np.asarray(T, dtype=np.float64)
    finite = np.all(np.isfinite(T), axis=(-2, -1))
    R = np.nan_to_num(T[..., :3, :3])
    eye = np.eye(3)
    ortho = np.all(np.abs(np.swapaxes(R, -1, -2) @ R - eye) < atol, axis=(-2, -1))
    det = np.abs(np.linalg.det(R) - 1.0) < atol
    bottom = np.all(np.abs(np.nan_to_num(T[..., 3, :]) - [0, 0, 0, 1]) < atol, axis=-1)
    return finite & ortho & det & bottom
