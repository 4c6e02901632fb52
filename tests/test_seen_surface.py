"""Issue 29, item 5: a wrist fitted 20 cm off along the ray of the one view that sees it (behind the
surface that view measured, so the free-space test says nothing, and on its ray, so the keypoints say
nothing) is flagged ``suspect`` because the person surface the view measured at its detection is far
from the fitted body (and, moved toward the view, because the joint lies in front of that surface);
a right fit is not, nor one whose detections carry exchanged labels."""

from __future__ import annotations

import numpy as np
import pytest

from embodmocap.motion.quality import QualityConfig, frame_quality
from embodmocap.motion.seen_surface import SURFACE_JOINTS, joint_in_front, unexplained_surface
from test_free_space import DEPTH, K, RGB, _cameras, _depth_map, _keypoints, body  # noqa: F401 - fixture

WALL_M = 5.0
CFG = QualityConfig()


def _mask(depth_mm: np.ndarray) -> np.ndarray:
    """(H, ceil(W / 8)) uint8: the person mask at the RGB size, packed as Stage II writes it (the
    depth pixels nearer than the wall, each covering its block of RGB pixels)."""
    w, h = DEPTH
    person = depth_mm < WALL_M * 1000 - 1
    ys = (np.arange(RGB[1]) * h) // RGB[1]
    xs = (np.arange(RGB[0]) * w) // RGB[0]
    return np.packbits(person[ys][:, xs], axis=-1)


def _scene(body, frames: int = 3):
    """The true body seen by two views over ``frames`` frames: depth and masks per view (frames,
    ...), the views' detections (frames, 2, 17, 3) with view 2 blind to the left elbow and wrist,
    the cameras (frames, 2, 4, 4)."""
    verts, kp3, weights = body
    Twc = _cameras(verts.mean(0))
    depth = [np.stack([_depth_map(verts, Twc[v], WALL_M)] * frames) for v in range(2)]
    masks = [np.stack([_mask(d) for d in dv]) for dv in depth]
    kp2 = np.stack([_keypoints(kp3, Twc)] * frames)
    kp2[:, 1, [7, 9], 2] = 0.0
    return depth, masks, kp2, np.stack([Twc] * frames)


@pytest.mark.parametrize("metres", [0.20, -0.20])
def test_a_wrist_off_along_its_only_views_ray_is_suspect_a_right_fit_is_not(body, metres):
    verts, kp3, weights = body
    depth, masks, kp2, Twc = _scene(body)
    Ks = np.stack([K, K])
    # Frames 0 and 1: the left forearm and hand moved ``metres`` along view 1's ray through the wrist
    # (+: away from the camera, behind what it measured; -: toward it); frame 2 is the truth.
    part = np.isin(weights.argmax(1), (18, 20, 22))
    ray = kp3[9] - Twc[0, 0, :3, 3]
    shift = metres * ray / np.linalg.norm(ray)
    fitted_v = np.stack([verts] * 3)
    fitted_v[:2, part] += shift
    fitted_kp = np.stack([kp3] * 3)
    fitted_kp[:2, 9] += shift

    surface = unexplained_surface(fitted_v, Ks, Twc, [RGB, RGB], depth, masks, kp2, CFG.surface_conf,
                                  CFG.surface_window_px, CFG.surface_quantile)
    assert surface.shape == (3, 2, len(SURFACE_JOINTS))
    wrist = SURFACE_JOINTS.index(9)
    assert surface[0, 0, wrist] > CFG.surface_m + 0.01  # view 1 measured the wrist where the fitted body is not
    assert np.isnan(surface[:, 1, wrist]).all()  # view 2 does not detect it: not judged there
    assert np.nanmax(surface[2]) < 0.03  # the right fit explains every measured surface
    assert np.nanmax(np.delete(surface[0, 0], wrist)) < 0.03  # and view 1's other detections

    # The keypoints alone cannot tell (view 1 sees the wrist on its ray, view 2 not at all) ...
    args = (fitted_kp, Ks, Twc, kp2, kp2, np.stack([kp3] * 3), None, ("v1", "v2"), CFG)
    assert not frame_quality(*args).suspect.any()
    # ... the measured surface can: the two wrong frames are suspect, the right one not.
    q = frame_quality(*args, surface=surface)
    assert q.suspect.tolist() == [True, True, False]
    # A wrist moved toward the camera also lies in front of the surface view 1 measured around it;
    # one moved away does not (it may be hidden: that says nothing).
    front = joint_in_front(fitted_kp, Ks, Twc, [RGB, RGB], depth, masks, kp2, kp2, CFG.front_conf, CFG.front_window_px)
    assert front.shape == (3, 2, len(SURFACE_JOINTS))
    assert np.isnan(front[:, 1, wrist]).all()  # view 2 does not see it
    assert (front[0, 0, wrist] > 0.15) == (metres < 0)
    assert np.nanmax(front[2]) < 0.03 and np.nanmax(np.delete(front[0, 0], wrist)) < 0.03
    q = frame_quality(*args, front=front)
    assert q.suspect.tolist() == ([True, True, False] if metres < 0 else [False] * 3)
    # Off (surface_m 0) or in one frame alone: not suspect.
    from dataclasses import replace

    assert not frame_quality(*args[:-1], replace(CFG, surface_m=0.0), surface=surface).suspect.any()
    one = surface.copy()
    one[1] = 0.0
    assert not frame_quality(*args, surface=one).suspect.any()


def test_exchanged_labels_and_missing_inputs_say_nothing(body):
    verts, kp3, _ = body
    depth, masks, kp2, Twc = _scene(body, frames=2)
    Ks = np.stack([K, K])
    # The detector exchanged left and right everywhere: the fitted body still has a limb at every
    # measured surface, so nothing is unexplained (exchanged limbs are not this test's to find).
    swapped = kp2.copy()
    for a, b in ((5, 6), (7, 8), (9, 10), (11, 12), (13, 14), (15, 16)):
        swapped[..., [a, b], :] = kp2[..., [b, a], :]
    v2 = np.stack([verts] * 2)
    s = unexplained_surface(v2, Ks, Twc, [RGB, RGB], depth, masks, swapped, 0.7)
    assert np.nanmax(s) < 0.03
    # A view without masks or depth, detections under the confidence, or no measured depth: not judged.
    none = unexplained_surface(v2, Ks, Twc, [RGB, RGB], [depth[0], None], [None, masks[1]], kp2, 0.7)
    assert np.isnan(none).all()
    low = kp2.copy()
    low[..., 2] = 0.5
    assert np.isnan(unexplained_surface(v2, Ks, Twc, [RGB, RGB], depth, masks, low, 0.7)).all()
    zero = [np.zeros_like(d) for d in depth]
    assert np.isnan(unexplained_surface(v2, Ks, Twc, [RGB, RGB], zero, masks, kp2, 0.7)).all()
    kp = np.stack([kp3] * 2)
    assert np.isnan(joint_in_front(kp, Ks, Twc, [RGB, RGB], [depth[0], None], [None, masks[1]], kp2, kp2, 0.8)).all()
    assert np.isnan(joint_in_front(kp, Ks, Twc, [RGB, RGB], zero, masks, kp2, kp2, 0.8)).all()
    # The right fit with exchanged labels: the joints lie on no ray of their own label's detection
    # (the wrists are far apart), so nothing is judged in front of anything.
    assert np.nanmax(np.nan_to_num(joint_in_front(kp, Ks, Twc, [RGB, RGB], depth, masks, swapped, swapped, 0.8))) < 0.03
