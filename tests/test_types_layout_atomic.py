"""Frozen data contracts, the layout object and atomic writes."""

import json
from pathlib import Path

import numpy as np
import pytest

from embodmocap.io import atomic
from embodmocap.io.layout import SessionLayout
from embodmocap.types import CameraTrajectory, Keypoints2D, SmplParams


def test_arrays_in_contracts_are_read_only():
    traj = CameraTrajectory(np.arange(3.0), np.arange(3), np.stack([np.eye(4)] * 3))
    with pytest.raises(ValueError):
        traj.T_world_cam[0, 0, 0] = 5.0
    src = np.zeros((2, 17, 3))
    kp = Keypoints2D(src, np.arange(2))
    src[0, 0, 0] = 9.0  # the contract copied its input
    assert kp.data[0, 0, 0] == 0.0
    assert kp.xy.shape == (2, 17, 2) and kp.conf.shape == (2, 17)


def test_contract_shape_checks():
    with pytest.raises(ValueError):
        CameraTrajectory(np.arange(3.0), np.arange(2), np.stack([np.eye(4)] * 3))
    with pytest.raises(ValueError):
        Keypoints2D(np.zeros((2, 18, 3)), np.arange(2))
    with pytest.raises(ValueError):
        SmplParams(np.zeros(10), np.zeros((4, 3)), np.zeros((4, 69)), np.zeros((3, 3)))
    p = SmplParams(np.zeros(10), np.zeros((4, 3)), np.ones((4, 69)), np.zeros((4, 3)))
    assert p.poses.shape == (4, 72) and len(p) == 4


def test_path_length():
    T = np.stack([np.eye(4)] * 3)
    T[1, 0, 3] = 1.0
    T[2, 0, 3] = 1.0
    T[2, 1, 3] = 2.0
    assert CameraTrajectory(np.arange(3.0), np.arange(3), T).path_length_m() == pytest.approx(3.0)


def test_layout_paths_are_under_the_session(tmp_path):
    lay = SessionLayout(tmp_path)
    paths = [
        lay.manifest, lay.scene("room").mesh_raw, lay.sequence("s").view("v1").keypoints,
        lay.perception("s", "v2").keypoints_json(12), lay.ground_truth.sequence("s"),
    ]
    for p in paths:
        assert Path(p).is_relative_to(tmp_path)
    assert lay.perception("s", "v2").keypoints_json(12).name == "000012_keypoints.json"


def test_atomic_write_leaves_no_partial_file(tmp_path):
    target = tmp_path / "out.json"
    atomic.write_json(target, {"a": np.float32(1.5), "b": np.arange(3)})
    assert json.loads(target.read_text()) == {"a": 1.5, "b": [0, 1, 2]}
    with pytest.raises(RuntimeError):
        with atomic.atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("crash while writing")
    # The old complete file is still there and no temporary file is left behind.
    assert json.loads(target.read_text())["a"] == 1.5
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.json"]


def test_atomic_dir_replaces_whole(tmp_path):
    d = tmp_path / "frames"
    with atomic.atomic_dir(d) as tmp:
        (tmp / "a.txt").write_text("1")
    with pytest.raises(RuntimeError):
        with atomic.atomic_dir(d) as tmp:
            (tmp / "b.txt").write_text("2")
            raise RuntimeError("crash")
    assert sorted(p.name for p in d.iterdir()) == ["a.txt"]
    atomic.write_npz(tmp_path / "x.npz", a=np.arange(4))
    assert np.load(tmp_path / "x.npz")["a"].tolist() == [0, 1, 2, 3]
