"""Issue 29, item 5: a limb fitted on one view's ray at the wrong depth is flagged ``suspect`` by the
views' depth maps (the space the sensor saw empty), where the keypoints alone cannot tell; a right
fit is not flagged."""

from __future__ import annotations

import numpy as np
import pytest

from embodmocap.body.model import load_body_model
from embodmocap.geometry.transforms import invert_T, look_at_T
from embodmocap.motion.free_space import LIMB_PARTS, free_space_limbs, vertex_parts
from embodmocap.motion.quality import QualityConfig, frame_quality

K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
RGB = (640, 480)
DEPTH = (160, 120)  # (w, h): a quarter of the RGB size, as a phone's LiDAR map is coarser than its video
#: COCO-17 from the SMPL joints (the face points on the head joint): enough for the ray test.
COCO_FROM_SMPL = [15, 15, 15, 15, 15, 16, 17, 18, 19, 20, 21, 1, 2, 4, 5, 7, 8]


@pytest.fixture(scope="module")
def body():
    """A standing body (the T pose) in the Z-up world, 1 m in front of the origin: vertices (N, 3),
    COCO-17 points (17, 3), skinning weights."""
    model = load_body_model(None)
    y_to_z = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    v = model.v_template @ y_to_z.T
    j = model.rest_joints() @ y_to_z.T
    lift = np.array([0.0, 1.0, -v[:, 2].min()])
    return v + lift, j[COCO_FROM_SMPL] + lift, model.lbs_weights


def _cameras(centre: np.ndarray) -> np.ndarray:
    """(2, 4, 4) two views 3 m from ``centre``, in front of the body and at its side."""
    return np.stack([look_at_T(centre + [3.0 * np.cos(a), 3.0 * np.sin(a), 0.3], centre) for a in (-np.pi / 2, 0.0)])


def _depth_map(vertices: np.ndarray, T_world_cam: np.ndarray, wall_m: float = 5.0) -> np.ndarray:
    """(h, w) uint16 millimetres: the body's vertices splatted 3x3 depth pixels each with a z-buffer,
    in front of a wall ``wall_m`` from the camera (what a phone's depth sees of the true body)."""
    w, h = DEPTH
    cam = (vertices - T_world_cam[:3, 3]) @ T_world_cam[:3, :3]
    x = np.floor((K[0, 0] * cam[:, 0] / cam[:, 2] + K[0, 2]) * w / RGB[0]).astype(int)
    y = np.floor((K[1, 1] * cam[:, 1] / cam[:, 2] + K[1, 2]) * h / RGB[1]).astype(int)
    d = np.full((h, w), wall_m)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            xi, yi = np.clip(x + dx, 0, w - 1), np.clip(y + dy, 0, h - 1)
            np.minimum.at(d, (yi, xi), cam[:, 2])
    return np.round(d * 1000).astype(np.uint16)


def _keypoints(points: np.ndarray, Twc: np.ndarray) -> np.ndarray:
    """(2, 17, 3) each view's pixels of ``points`` (17, 3), confidence 0.9."""
    Tcw = invert_T(Twc)
    cam = np.einsum("vab,jb->vja", Tcw[:, :3, :3], points) + Tcw[:, None, :3, 3]
    uv = np.einsum("ab,vjb->vja", K, cam)
    return np.concatenate([uv[..., :2] / uv[..., 2:], np.full(uv.shape[:-1] + (1,), 0.9)], -1)


def test_a_forearm_30cm_off_along_one_views_ray_is_suspect_a_right_fit_is_not(body):
    verts, kp3, weights = body
    Twc = _cameras(verts.mean(0))
    depth = [np.stack([_depth_map(verts, Twc[v])] * 3) for v in range(2)]  # 3 frames, (3, h, w) per view
    kp2 = np.stack([_keypoints(kp3, Twc)] * 3)  # (3, 2, 17, 3)
    kp2[:, 1, [7, 9], 2] = 0.0  # view 2 does not see the left elbow and wrist (hidden behind the body)
    Twc_t = np.stack([Twc] * 3)

    # Frames 0 and 1: the left forearm (and hand) fitted 30 cm nearer view 1, on its rays.
    forearm = np.isin(weights.argmax(1), (18, 20, 22))
    toward_v1 = Twc[0, :3, 3] - kp3[9]
    shift = 0.30 * toward_v1 / np.linalg.norm(toward_v1)
    fitted_v = np.stack([verts] * 3)
    fitted_v[:2, forearm] += shift
    fitted_kp = np.stack([kp3] * 3)
    fitted_kp[:2, 9] += shift
    Ks = np.stack([K, K])

    # The keypoints alone cannot tell: view 1 sees the wrist on the fitted wrist's ray, view 2 not at all.
    keypoints_only = frame_quality(fitted_kp, Ks, Twc_t, kp2, kp2, np.stack([kp3] * 3), None, ("v1", "v2"))
    assert not keypoints_only.suspect.any()
    assert np.nanmax(keypoints_only.limb_off_m) < 0.01

    free = free_space_limbs(fitted_v, weights, Ks, Twc_t, [RGB, RGB], depth, QualityConfig().free_space_m)
    assert free.shape == (3, len(LIMB_PARTS))
    left_forearm = list(LIMB_PARTS).index("left_forearm")
    assert free[0, left_forearm] > 0.8  # its vertices lie in space both views saw empty
    assert np.nanmax(np.delete(free, left_forearm, axis=1)) < 0.05  # the rest of the body is where it was seen
    assert np.nanmax(free[2]) < 0.05  # the right fit: nothing in empty space
    q = frame_quality(fitted_kp, Ks, Twc_t, kp2, kp2, np.stack([kp3] * 3), None, ("v1", "v2"), free_space=free)
    assert q.suspect.tolist() == [True, True, False]
    np.testing.assert_array_equal(q.free_space, free)

    # Off (free_space_m 0 is what solve.fit_quality reads to skip the test) or one frame alone: not suspect.
    one = free.copy()
    one[1] = 0.0
    assert not frame_quality(fitted_kp, Ks, Twc_t, kp2, kp2, np.stack([kp3] * 3), None, ("v1", "v2"),
                             free_space=one).suspect.any()


def test_a_limb_behind_the_measured_surface_or_unmeasured_says_nothing(body):
    verts, _, weights = body
    Twc = _cameras(verts.mean(0))[:1]
    d = _depth_map(verts, Twc[0])[None]
    forearm = np.isin(weights.argmax(1), (18,))
    away = verts[forearm].mean(0) - Twc[0, :3, 3]
    moved = verts.copy()
    moved[forearm] += 0.3 * away / np.linalg.norm(away)  # pushed behind what the view measured: maybe hidden
    free = free_space_limbs(moved[None], weights, K[None], Twc[None], [RGB], [d], 0.10)
    assert np.nanmax(free) < 0.05
    # No depth measured (0 everywhere): nothing judged.
    assert np.isnan(free_space_limbs(moved[None], weights, K[None], Twc[None], [RGB], [np.zeros_like(d)], 0.10)).all()
    # A view without depth is left out.
    assert np.isnan(free_space_limbs(moved[None], weights, K[None], Twc[None], [RGB], [None], 0.10)).all()
    assert (vertex_parts(weights) >= 0).sum() > len(LIMB_PARTS) * 20
