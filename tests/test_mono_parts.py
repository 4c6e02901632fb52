"""Parts of the monocular pipeline against known answers: the body moved into the world, gravity
from VIO and from the floor plane, the camera-space SMPL file checks, the scale summary."""

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from embodmocap.body.model import load_body_model
from embodmocap.errors import InputError
from embodmocap.mono.body import world_motion
from embodmocap.mono.files import HumanSeq, human_from_rows, read_human_npz, write_human_npz
from embodmocap.mono.gravity import floor_plane, plane_alignment, vio_alignment, world_alignment
from embodmocap.mono.scale import summarise


def _rigid(rng, n):
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=int(rng.integers(1 << 30))).as_matrix()
    T[:, :3, 3] = rng.normal(size=(n, 3))
    return T


def test_body_moves_rigidly_with_each_camera():
    rng = np.random.default_rng(0)
    model = load_body_model(None)
    T = 6
    betas = np.tile(rng.normal(size=10) * 0.5, (T, 1))
    hum = HumanSeq(rng.normal(size=(T, 3)) * 0.5, rng.normal(size=(T, 69)) * 0.2, betas,
                   rng.normal(size=(T, 3)) + [0, 0, 3], np.ones(T, bool))
    Twc = _rigid(rng, T)
    params, valid = world_motion(hum, Twc, model, 30.0)
    with torch.no_grad():
        cam = model.forward(hum.betas, hum.global_orient, hum.body_pose, hum.transl, dtype=torch.float64).vertices.numpy()
        world = model.from_params(params, dtype=torch.float64).vertices.numpy()
    want = np.einsum("tij,tvj->tvi", Twc[:, :3, :3], cam) + Twc[:, None, :3, 3]
    assert valid.all() and np.abs(world - want).max() < 1e-6  # metres; float round trips of axis-angle


def test_frames_without_an_estimate_are_filled_and_flagged():
    model = load_body_model(None)
    T = 5
    hum = HumanSeq(np.zeros((T, 3)), np.zeros((T, 69)), np.zeros((T, 10)),
                   np.array([[0, 0, 2.0], [9, 9, 9], [0, 0, 4.0], [9, 9, 9], [9, 9, 9]]),
                   np.array([True, False, True, False, False]))
    params, valid = world_motion(hum, np.tile(np.eye(4), (T, 1, 1)), model, 30.0)
    assert valid.tolist() == [True, False, True, False, False]
    assert np.allclose(params.transl[1], [0, 0, 3.0]) and np.allclose(params.transl[4], [0, 0, 4.0])
    with pytest.raises(ValueError):
        world_motion(HumanSeq(*[np.zeros((2, k)) for k in (3, 69, 10, 3)], np.zeros(2, bool)), np.tile(np.eye(4), (2, 1, 1)),
                     model, 30.0)


def test_vio_alignment_recovers_the_rotation():
    rng = np.random.default_rng(1)
    R_true = Rotation.random(random_state=2).as_matrix()
    R_st = Rotation.random(20, random_state=3).as_matrix()
    T_vio = np.tile(np.eye(4), (20, 1, 1))
    T_vio[:, :3, :3] = R_true @ R_st
    T_vio[:, :3, 3] = rng.normal(size=(20, 3))
    assert np.allclose(vio_alignment(R_st, T_vio)[:3, :3], R_true)
    T_st = np.tile(np.eye(4), (20, 1, 1))
    T_st[:, :3, :3] = R_st
    T_st[:, :3, 3] = (T_vio[:, :3, 3] - 1.0) @ R_true  # any centres: the first is put at its VIO place
    A, src = world_alignment(T_st, np.zeros((0, 3)), T_vio)
    assert src == "vio" and np.allclose(A[:3, :3] @ T_st[0, :3, 3] + A[:3, 3], T_vio[0, :3, 3])


def test_floor_plane_is_found_below_the_cameras_and_put_at_z0():
    rng = np.random.default_rng(4)
    R_tilt = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()  # the stitched frame is tilted
    floor = np.c_[rng.uniform(-3, 3, (3000, 2)), np.zeros(3000) + rng.normal(size=3000) * 0.005]
    wall = np.c_[np.full(2000, 3.0), rng.uniform(-3, 3, 2000), rng.uniform(0, 2.5, 2000)]
    ceiling = np.c_[rng.uniform(-3, 3, (1000, 2)), np.full(1000, 2.6)]
    pts = np.r_[floor, wall, ceiling] @ R_tilt.T
    # upright phones at 1.5 m looking along +Y: camera x = world X, y = world -Z (down), z = world Y
    n = 10
    R_cam = np.einsum("ij,njk->nik", R_tilt, np.tile(np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]), (n, 1, 1)))
    centres = np.c_[rng.uniform(-1, 1, (n, 2)), np.full(n, 1.5)] @ R_tilt.T
    nrm, d, frac = floor_plane(pts, R_cam, centres)
    assert np.allclose(nrm, R_tilt @ [0, 0, 1.0], atol=0.01) and frac > 0.4
    A = plane_alignment(nrm, d, centres[0])
    z = (pts[:3000] @ A[:3, :3].T + A[:3, 3])[:, 2]
    assert abs(np.median(z)) < 0.005
    c = centres @ A[:3, :3].T + A[:3, 3]
    assert np.allclose(c[:, 2], 1.5, atol=0.02) and np.allclose(c[0, :2], 0, atol=1e-9)


def test_human_file_checks_name_the_file(tmp_path):
    rng = np.random.default_rng(5)
    T = 8
    hum = HumanSeq(rng.normal(size=(T, 3)), rng.normal(size=(T, 69)), rng.normal(size=(T, 10)), rng.normal(size=(T, 3)),
                   np.array([1, 1, 0, 1, 1, 1, 1, 1], bool))
    path = tmp_path / "mono_human.npz"
    write_human_npz(path, hum)
    back = read_human_npz(path, T)
    assert np.array_equal(back.valid, hum.valid) and np.allclose(back.transl[hum.valid], hum.transl[hum.valid])
    with pytest.raises(InputError, match="mono_human.npz.*do not match the video's 6"):
        read_human_npz(path, 6)
    with pytest.raises(InputError, match="or repeat"):
        human_from_rows(path, np.array([0, 0]), np.zeros((2, 3)), np.zeros((2, 69)), np.zeros((2, 10)), np.ones((2, 3)), 4)


def test_scale_summary_is_a_median_of_frame_medians():
    frames = [np.full(100, 1.0), np.full(10, 2.0), np.full(10, 2.0), np.full(5, 100.0)]  # the last frame has too few
    s = summarise(frames, min_frame_samples=10)
    assert s["scale"] == 2.0 and s["frames"] == 3 and s["samples"] == 120
    # Frames vote by their mask's size, not by their own sample count.
    s = summarise(frames, np.array([50, 50, 5, 50]), min_frame_samples=10)
    assert s["frames"] == 3 and s["scale"] == 2.0 and s["samples"] == 115
    assert np.isnan(summarise([])["scale"])
