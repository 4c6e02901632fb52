"""Typed stage files (embodmocap.io.stage_files) and the checked npz reader: round trips, files
written by older versions, and one clear error per kind of bad file."""

from __future__ import annotations

import json

import numpy as np
import pytest

from embodmocap.errors import InputError
from embodmocap.io import stage_files as sf
from embodmocap.io.npz_file import check_shapes, load_npz

rng = np.random.default_rng(0)
N = 7


def _poses(n: int) -> np.ndarray:
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, 3] = rng.normal(size=(n, 3))
    return T


def _sliced_cameras(fps: float | None = 30.0) -> sf.CameraFile:
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    return sf.CameraFile(version=np.int64(1), K=K, width=np.int64(640), height=np.int64(480), T_world_cam=_poses(N),
                         raw_frames=np.arange(N) + 3, K_depth=K / 4, depth_width=np.int64(160), depth_height=np.int64(120),
                         timestamps_s=np.arange(N) / 30, frame_times_s=np.arange(N) / 30 + 0.001,
                         untracked=np.zeros(N, bool), fps=None if fps is None else np.float64(fps))


def _seq_dir(tmp_path):
    d = tmp_path / "sequences" / "seq0"
    (d / "v1").mkdir(parents=True)
    return d


def test_cameras_round_trip_in_all_three_forms(tmp_path):
    d = _seq_dir(tmp_path)
    cams = _sliced_cameras()
    sf.write_cameras(d / "v1" / "cameras.npz", cams)
    back = sf.read_cameras(d / "v1" / "cameras.npz")
    for k in cams.files:
        np.testing.assert_array_equal(back[k], cams[k])
    assert back.time_offset_s is None and "time_offset_s" not in back and back.num_frames == N
    world = sf.CameraFile(version=np.int64(1), K=cams.K, width=cams.width, height=cams.height,
                          T_world_cam=_poses(N), raw_frames=cams.raw_frames, time_offset_s=np.float64(0.004))
    sf.write_cameras(d / "v1" / "cameras_world.npz", world)
    got = sf.read_cameras(d / "v1" / "cameras_world.npz")
    assert float(got["time_offset_s"]) == 0.004 and got.K_depth is None
    np.testing.assert_array_equal(got.T_world_cam, world.T_world_cam)
    final = sf.CameraFile(version=np.int64(1), K=cams.K, width=cams.width, height=cams.height,
                          T_world_cam=world.T_world_cam, raw_frames=cams.raw_frames)
    sf.write_cameras(d / "v1" / "cameras_final.npz", final)
    assert sorted(sf.read_cameras(d / "v1" / "cameras_final.npz").files) == sorted(
        ["version", "K", "width", "height", "T_world_cam", "raw_frames"])
    # A Stage III file is not a Stage II one: the depth intrinsics are missing.
    with pytest.raises(InputError, match=r"cameras_world\.npz.*keys \['K_depth'.*embodmocap sequence SESSION --seq seq0"):
        sf.read_cameras(d / "v1" / "cameras_world.npz", "cameras")


def test_camera_files_written_by_np_savez_read_like_np_load(tmp_path):
    """The mapping view matches np.load's, so code written against np.load reads the same values."""
    d = _seq_dir(tmp_path)
    cams = _sliced_cameras()
    np.savez(d / "v1" / "cameras.npz", **cams.arrays())
    raw, typed = np.load(d / "v1" / "cameras.npz"), sf.read_cameras(d / "v1" / "cameras.npz")
    assert sorted(raw.files) == sorted(typed.files)
    for k in raw.files:
        np.testing.assert_array_equal(raw[k], typed[k])
    assert dict(typed.items()).keys() == set(raw.files)
    with pytest.raises(KeyError):
        typed["time_offset_s"]


def test_frame_rate_from_the_file_and_from_an_older_files_manifest(tmp_path):
    d = _seq_dir(tmp_path)
    sf.write_cameras(d / "v1" / "cameras.npz", _sliced_cameras(fps=24.0))
    (d / "manifest.json").write_text(json.dumps({"figures": {"fps": 30.0}}))
    assert sf.sequence_fps(d) == 24.0  # the file wins over the report figure
    sf.write_cameras(d / "v1" / "cameras.npz", _sliced_cameras(fps=None))  # written before the key
    assert sf.sequence_fps(d) == 30.0
    (d / "manifest.json").unlink()
    with pytest.raises(InputError, match="no frame rate"):
        sf.sequence_fps(d)


def test_keypoints2d_round_trip_and_old_file_without_layout(tmp_path):
    d = _seq_dir(tmp_path)
    kp = sf.Keypoints2DFile(version=np.int64(1), keypoints=rng.random((N, 17, 3)), boxes=rng.random((N, 4)),
                            raw_frames=np.arange(N), seen=np.ones(N, bool), track_id=np.int64(2),
                            layout=np.array("BODY_25"))
    p = d / "v1" / "keypoints2d.npz"
    sf.write_keypoints2d(p, kp)
    back = sf.read_keypoints2d(p)
    np.testing.assert_array_equal(back.keypoints, kp.keypoints)
    assert str(back.layout) == "BODY_25" and int(back.track_id) == 2
    arrays = kp.arrays()
    del arrays["layout"]
    np.savez(p, **arrays)
    assert str(sf.read_keypoints2d(p).layout) == "COCO17"


def test_registration_version_1_reads_every_frame_accepted(tmp_path):
    d = _seq_dir(tmp_path)
    R, M = 4, 9
    reg = dict(version=np.int64(1), attempted=np.arange(6), attempted_inliers=np.arange(6), t=np.arange(R),
               T_world_cam=_poses(R), inliers=np.full(R, 40), reproj_error_px=np.ones(R), match_frames=np.zeros(M, int),
               match_xy=np.zeros((M, 2)), match_xyz=np.zeros((M, 3)))
    np.savez(d / "v1" / "registration.npz", **reg)
    back = sf.read_registration(d / "v1" / "registration.npz")
    assert back.accepted.all() and back.accepted.shape == (R,) and (back.run == 0).all()
    v2 = sf.RegistrationFile(**{**reg, "version": np.int64(2), "accepted": np.array([1, 0, 1, 1], bool),
                                "run": np.array([0, 1, 2, 2])})
    sf.write_registration(d / "v1" / "registration.npz", v2)
    assert sf.read_registration(d / "v1" / "registration.npz").accepted.tolist() == [True, False, True, True]
    back = sf.read_registration(d / "v1" / "registration.npz")
    assert not back.off_chain.any() and back.off_chain.shape == (R,) and back.T_world_vio_performer is None
    placed = _poses(1)[0]
    v3 = sf.RegistrationFile(**{**v2.arrays(), "version": np.int64(3), "off_chain": np.array([0, 0, 1, 0], bool),
                                "T_world_vio_performer": placed})
    sf.write_registration(d / "v1" / "registration.npz", v3)
    back = sf.read_registration(d / "v1" / "registration.npz")
    assert back.off_chain.tolist() == [False, False, True, False]
    np.testing.assert_array_equal(back.T_world_vio_performer, placed)
    np.savez(d / "v1" / "registration.npz", **{**reg, "version": np.int64(4)})
    with pytest.raises(InputError, match="registration.npz version 4, this reader knows 1, 2, 3"):
        sf.read_registration(d / "v1" / "registration.npz")


def test_keypoints3d_and_world_joints_round_trip(tmp_path):
    d = _seq_dir(tmp_path)
    T, V, G = 5, 2, 5
    k3 = sf.Keypoints3DFile(version=np.int64(1), points=rng.random((T, 17, 3)), conf=rng.random((T, 17)),
                            reproj_err_px=rng.random((T, 17, V)), filled=np.zeros((T, 17), bool),
                            views=np.array(["v1", "v2"]), keypoints2d=rng.random((T, V, 17, 3)),
                            swapped=np.zeros((T, V, G), bool), swap_groups=np.array(["a", "b", "c", "d", "e"]))
    sf.write_keypoints3d(d / "keypoints3d.npz", k3)
    back = sf.read_keypoints3d(d / "keypoints3d.npz")
    for k in k3.files:
        np.testing.assert_array_equal(back[k], k3[k])
    wj = sf.WorldJointsFile(version=np.int64(1), joints=rng.random((T, 24, 3)), coco17=rng.random((T, 17, 3)),
                            frames=np.arange(T))
    sf.write_world_joints(d / "joints_world.npz", wj)
    np.testing.assert_array_equal(sf.read_world_joints(d / "joints_world.npz").coco17, wj.coco17)
    np.savez(d / "joints_world.npz", joints=wj.joints, coco17=wj.coco17)  # no frames, no version
    np.testing.assert_array_equal(sf.read_world_joints(d / "joints_world.npz").frames, np.arange(T))


@pytest.mark.parametrize("problem, match", [
    ("missing", r"keypoints3d.npz not found \(run `embodmocap motion SESSION --seq seq0`"),
    ("not_npz", "not a readable npz file"),
    ("no_conf", r"keys \['conf'\] missing"),
    ("version", "version 9, this reader knows 1"),
    ("shape", r"wrong shapes: conf \(5, 16\) \(expected \(T, 17\)\) with T=5"),
    ("views", r"reproj_err_px \(5, 17, 3\) \(expected \(T, 17, V\)\)|views \(2,\) \(expected \(V,\)\)"),
])
def test_a_bad_file_is_one_error_naming_it(tmp_path, problem, match):
    d = _seq_dir(tmp_path)
    p = d / "keypoints3d.npz"
    good = dict(version=np.int64(1), points=np.zeros((5, 17, 3)), conf=np.zeros((5, 17)))
    if problem == "not_npz":
        p.write_text("hello")
    elif problem == "no_conf":
        np.savez(p, version=good["version"], points=good["points"])
    elif problem == "version":
        np.savez(p, **{**good, "version": np.int64(9)})
    elif problem == "shape":
        np.savez(p, **{**good, "conf": np.zeros((5, 16))})
    elif problem == "views":
        np.savez(p, **good, reproj_err_px=np.zeros((5, 17, 3)), views=np.array(["v1", "v2"]))
    with pytest.raises(InputError, match=match) as err:
        sf.read_keypoints3d(p)
    assert str(p) in str(err.value)


def test_checked_npz_helper_binds_named_dimensions(tmp_path):
    p = tmp_path / "x.npz"
    np.savez(p, a=np.zeros((3, 2)), b=np.zeros(3))
    d = load_npz(p, what="test file", fix="make it again", required=("a", "b"), versions=None)
    assert check_shapes(p, d, {"a": ("T", 2), "b": ("T",), "absent": (4,)}, "x") == {"T": 3}
    with pytest.raises(InputError, match=r"b \(3,\) \(expected \(4,\)\)"):
        check_shapes(p, d, {"b": (4,)}, "x")
    with pytest.raises(InputError, match=r"keys \['version'\] missing"):
        load_npz(p, what="test file", fix="x", default_version=None)
