"""The floor term of Stage IV's fit (motion.floor): known answers, a leg both views lose kept above
the floor, a body that truly stands on the floor left alone, and the floor read from a mesh."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from embodmocap.body.model import load_body_model
from embodmocap.motion.floor import FOOT_CLEARANCE_M, FOOT_JOINTS, floor_term, scene_floor_z
from embodmocap.motion.smplify import SmplifyConfig, ViewObservations, fit_world_smpl
from embodmocap.synth.motion import script_motion
from embodmocap.synth.scene import build_scene
from embodmocap.types import SmplParams

FPS = 30.0
K = np.array([[700.0, 0.0, 360.0], [0.0, 700.0, 480.0], [0.0, 0.0, 1.0]])
#: COCO-17 knees and ankles: the keypoints a chair or a bed hides.
LEGS = [13, 14, 15, 16]
#: SMPL joints the keypoints pin (hips, shoulders, elbows, wrists): unaffected by the floor.
PINNED = [1, 2, 16, 17, 18, 19, 20, 21]


@pytest.fixture(scope="module")
def body():
    return load_body_model(None)


@pytest.fixture(scope="module")
def motion(body):
    """2 s of the studio's scripted motion in a generated room (floor at z = 0)."""
    spec = build_scene("indoor", np.random.default_rng(0)).spec
    betas = np.array([0.5, -0.3, 0.2, 0.0, 0.1, 0, 0, 0, 0, 0])
    params = script_motion(spec, body, betas, 2.0, FPS, np.random.default_rng(0)).params
    out = body.from_params(params, dtype=torch.float64)
    return params, out.joints.numpy(), out.coco17.numpy()


def _views(coco: np.ndarray, hidden: list[int]) -> list[ViewObservations]:
    """Two views 4 m away seeing the exact projections, ``hidden`` keypoints missing in both."""
    from embodmocap.geometry.transforms import invert_T, look_at_T

    T, centre = len(coco), coco.reshape(-1, 3).mean(0)
    views = []
    for name, a in (("v1", 0.3), ("v2", 1.9)):
        cams = np.repeat(look_at_T(centre + [4 * np.cos(a), 4 * np.sin(a), 0.3], centre)[None], T, 0)
        Tcw = invert_T(cams)
        p = np.einsum("tij,tkj->tki", Tcw[:, :3, :3], coco) + Tcw[:, None, :3, 3]
        uv = p @ K.T
        conf = np.ones((T, 17, 1))
        conf[:, hidden] = 0.0
        views.append(ViewObservations(K, cams, np.concatenate([uv[..., :2] / uv[..., 2:], conf], -1), name))
    return views


def _fit(body, params: SmplParams, coco: np.ndarray, hidden: list[int], floor_z: float | None) -> np.ndarray:
    conf = np.ones(coco.shape[:2])
    conf[:, hidden] = 0.0
    init = SmplParams(params.betas, params.global_orient + 0.05, params.body_pose, params.transl + [0.05, -0.05, 0.1], FPS)
    res = fit_world_smpl(body, coco, conf, _views(coco, hidden), init, None,
                         SmplifyConfig(device="cpu", dtype="float64"), floor_z=floor_z)
    return body.from_params(res.params, dtype=torch.float64).joints.numpy()


def test_floor_term_known_answers():
    joints = torch.zeros(2, 24, 3, dtype=torch.float64)
    joints[:, :, 2] = 1.0  # every joint 1 m up: nothing below a floor at 0
    assert float(floor_term(joints, torch.tensor(0.0, dtype=torch.float64))) == 0.0
    joints[0, FOOT_JOINTS[0], 2] = -0.06  # frame 0's left ankle 10 cm under its lowest height
    want = (0.04 + 0.06) ** 2 / 2  # summed over the foot joints, mean over the 2 frames
    assert float(floor_term(joints, torch.tensor(0.0, dtype=torch.float64))) == pytest.approx(want)
    assert FOOT_CLEARANCE_M[0] == 0.04


def test_lost_legs_are_kept_above_the_floor(body, motion):
    """Both views lose both legs (knees and ankles): with a floor 15 cm above the true one, the
    fit lifts every foot joint to its clearance over it; without a floor they stay below it; the
    joints the keypoints pin stay on the truth either way."""
    params, joints, coco = motion
    floor = 0.15
    lifted = _fit(body, params, coco, LEGS, floor)
    free = _fit(body, params, coco, LEGS, None)
    low = floor + np.asarray(FOOT_CLEARANCE_M)
    assert (lifted[:, FOOT_JOINTS, 2] >= low - 0.01).all()
    assert (free[:, FOOT_JOINTS, 2] < low - 0.03).any()
    for fit in (lifted, free):
        assert np.linalg.norm(fit[:, PINNED] - joints[:, PINNED], axis=-1).mean() < 0.02


def test_a_body_on_the_true_floor_is_left_alone(body, motion):
    params, joints, coco = motion
    on_floor = _fit(body, params, coco, [], 0.0)
    without = _fit(body, params, coco, [], None)
    # Adam's path may brush the floor on the way (on a joint no keypoint pins: the right foot of
    # frames 52-59 ends 7 mm higher with the start as given, 15 mm from the start smoothed through
    # time, the default); the fit ends where it would have without it.
    d = np.linalg.norm(on_floor - without, axis=-1)
    assert d.mean() < 0.001 and d.max() < 0.02
    err = [np.linalg.norm(f - joints, axis=-1).mean() for f in (on_floor, without)]
    assert abs(err[0] - err[1]) < 0.0005


def test_floor_read_from_a_mesh(tmp_path):
    from embodmocap.io.mesh_file import write_mesh_ply

    # A 4 x 4 m floor at z = -1.2 (a VIO world) and a 1 m table top: the floor is the low plane.
    def quad(x0, y0, s, z):
        return np.array([[x0, y0, z], [x0 + s, y0, z], [x0 + s, y0 + s, z], [x0, y0 + s, z]], float)

    v = np.concatenate([quad(-2, -2, 4, -1.2), quad(0, 0, 1, -0.45)])
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    write_mesh_ply(tmp_path / "m.ply", v, f)
    assert scene_floor_z(tmp_path / "m.ply", 3.0) == pytest.approx(-1.2, abs=1e-6)
    tilted = v.copy()
    tilted[:4, 2] += tilted[:4, 0] * np.tan(np.deg2rad(8.0))  # an 8 deg slope: not used
    write_mesh_ply(tmp_path / "t.ply", tilted, f)
    assert scene_floor_z(tmp_path / "t.ply", 3.0) is None
    assert scene_floor_z(None, 3.0) is None
