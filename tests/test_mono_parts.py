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


def test_block_standard_error_covers_the_median_of_a_drifting_error():
    """A regressor's depth error drifts (correlated over ~0.5 s), so 600 frames are far fewer
    independent votes: the block standard error must match the median's real spread over many
    sequences, where the per-frame formula would be several times too small."""
    from scipy.ndimage import gaussian_filter1d

    from embodmocap.mono.scale import block_se_rel

    rng = np.random.default_rng(0)
    T, fps, true = 600, 30.0, 2.5
    z, z_naive = [], []
    for _ in range(300):
        e = gaussian_filter1d(rng.normal(size=T), 15.0, mode="reflect")  # 0.5 s correlation
        v = true * (1 + 0.1 * e / e.std())
        med = np.median(v)
        se = block_se_rel(v, np.arange(T), fps, 2.0)
        naive = 1.2533 * 1.4826 * np.median(np.abs(v - med)) / np.sqrt(T) / med
        z.append((med / true - 1) / se)
        z_naive.append((med / true - 1) / naive)
    assert 0.7 < np.std(z) < 1.4, np.std(z)
    assert np.std(z_naive) > 2.5, np.std(z_naive)
    # Too few blocks: no standard error.
    assert np.isnan(block_se_rel(np.ones(50), np.arange(50), fps, 2.0))


def test_combined_cue_weights_each_cue_by_its_own_standard_error():
    from embodmocap.mono.scale import combine_cues

    c = combine_cues({"body": {"scale": 2.0, "se_rel": 0.02}, "feet": {"scale": 2.2, "se_rel": 0.01}})
    w_body = (1 / 0.02**2) / (1 / 0.02**2 + 1 / 0.01**2)
    assert c["weights"] == {"body": round(w_body, 4), "feet": round(1 - w_body, 4)}
    assert np.isclose(c["scale"], np.exp(w_body * np.log(2.0) + (1 - w_body) * np.log(2.2)))
    assert np.isclose(c["se_rel"], 1 / np.sqrt(1 / 0.02**2 + 1 / 0.01**2))
    # An exact cue (zero spread) takes all the weight; a cue without a scale is left out.
    c = combine_cues({"body": {"scale": 2.0, "se_rel": 0.0}, "feet": {"scale": 2.2, "se_rel": 0.01}})
    assert np.isclose(c["scale"], 2.0) and c["weights"]["body"] == 1.0
    c = combine_cues({"body": {"scale": float("nan"), "se_rel": 0.01}, "feet": {"scale": 2.2, "se_rel": 0.01}})
    assert np.isclose(c["scale"], 2.2) and c["weights"] == {"feet": 1.0}
    # No standard error anywhere (too short): equal weights (geometric mean); a cue with one wins.
    c = combine_cues({"body": {"scale": 2.0, "se_rel": float("nan")}, "feet": {"scale": 8.0, "se_rel": float("nan")}})
    assert np.isclose(c["scale"], 4.0) and np.isnan(c["se_rel"])
    c = combine_cues({"body": {"scale": 2.0, "se_rel": float("nan")}, "feet": {"scale": 8.0, "se_rel": 0.05}})
    assert np.isclose(c["scale"], 8.0)
    assert np.isnan(combine_cues({})["scale"])


def test_scale_summary_reports_a_block_standard_error():
    rng = np.random.default_rng(1)
    frames = [1 + 0.05 * rng.normal(size=20) for _ in range(300)]
    s = summarise(frames, min_frame_samples=10, frames=np.arange(300), fps=30.0, block_s=1.0)
    assert 0 < s["se_rel"] < 0.01  # 10 blocks of frame medians each ~1 % off
    assert np.isnan(summarise(frames[:20], min_frame_samples=10, frames=np.arange(20))["se_rel"])
