"""Keypoints hidden from their camera by the scene (embodmocap.motion.occlusion), with the shared ray casting."""

from __future__ import annotations

import numpy as np

from embodmocap.geometry.raycast import raycasting_scene
from embodmocap.geometry.transforms import look_at_T
from embodmocap.geometry.triangulation import TriangulationConfig, projection_matrices
from embodmocap.motion.occlusion import OcclusionConfig, drop_scene_hidden, scene_hidden
from embodmocap.synth.scene import box_mesh

K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])


def _cabinet():
    """A 1 x 0.4 x 1 m box centred at (0, 1.5, 0.5) (between camera 1 and the knees), as a raycasting scene."""
    v, f = box_mesh(np.array([[0.0, 1.5, 0.5]]), np.array([[1.0, 0.4, 1.0]]))
    return raycasting_scene(v, f)


def test_a_joint_behind_furniture_is_hidden_only_from_the_camera_it_is_behind():
    scene = _cabinet()
    centres = np.array([[[0.0, 3.5, 0.6], [3.5, 0.0, 0.6]]])  # (T=1, V=2, 3): behind the box, from the side
    points = np.array([[[0.0, 0.0, 0.5], [0.0, 0.0, 1.6]]])  # a knee (behind the box from view 1), the head
    hidden = scene_hidden(scene, centres, points, 0.1)
    np.testing.assert_array_equal(hidden[0], [[True, False], [False, False]])
    # NaN points are never hidden; a point in front of the surface is not hidden.
    assert not scene_hidden(scene, centres, np.full((1, 2, 3), np.nan), 0.1).any()
    assert not scene_hidden(scene, centres, np.array([[[0.0, 2.0, 0.5], [0.0, 2.5, 0.5]]]), 0.1).any()


def test_hidden_detections_lose_their_confidence_before_triangulation():
    scene = _cabinet()
    T = 20
    joints = np.zeros((T, 17, 3))
    joints[:, :, 2] = np.linspace(1.7, 0.1, 17)[None]  # a column of joints from head to ankles at x = y = 0
    cams = np.stack([look_at_T(np.array([0.0, 3.5, 0.6]), np.array([0.0, 0.0, 0.9])),
                     look_at_T(np.array([3.5, 0.0, 0.6]), np.array([0.0, 0.0, 0.9]))])
    Tw = np.broadcast_to(cams, (T, 2, 4, 4))
    P = projection_matrices(K, Tw)
    uvw = np.einsum("tvab,tjb->tvja", P, np.concatenate([joints, np.ones((T, 17, 1))], -1))
    kp = np.concatenate([uvw[..., :2] / uvw[..., 2:], np.full((T, 2, 17, 1), 0.8)], -1)
    out, hidden = drop_scene_hidden(scene, P, Tw, kp, TriangulationConfig(), OcclusionConfig())
    low = joints[0, :, 2] < 0.9  # the box (top at 1.0 m) hides what is well below its top from view 1
    assert hidden[:, 0, low].all() and not hidden[:, 1].any()
    assert (out[hidden][..., 2] == 0).all() and (out[~hidden][..., 2] == 0.8).all()
    off, none = drop_scene_hidden(scene, P, Tw, kp, TriangulationConfig(), OcclusionConfig(enabled=False))
    assert not none.any() and np.array_equal(off, kp)
