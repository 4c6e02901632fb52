"""Stray Scanner: write synthetic ground truth with the writer, read it back, check conventions."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from embodmocap.geometry.transforms import make_T, rot_x, rot_z
from embodmocap.io.captures import StrayScannerWriter, detect_format, open_capture, read_strayscanner
from embodmocap.types import Intrinsics

K = Intrinsics(fx=80.0, fy=81.0, cx=47.3, cy=32.1, width=96, height=64)
DEPTH_WH = (32, 24)


def ground_truth(n: int, seed: int = 0) -> dict:
    """A smooth handheld-like trajectory, smooth images, depth in mm, confidence, times."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 30.0  # seconds: a walk at ~0.4 m/s, turning at ~20 deg/s
    yaw = rng.uniform(-np.pi, np.pi) + 0.6 * np.sin(0.6 * t)
    tilt = -np.pi / 2 + 0.15 * np.cos(1.3 * t)  # roughly horizontal view, slight pitch
    R = rot_z(yaw) @ rot_x(tilt)
    pos = np.stack([np.cos(0.2 * t) * 2, np.sin(0.2 * t) * 2, 1.4 + 0.05 * np.sin(3 * t)], axis=1)
    pos = pos + rng.normal(0, 1, 3)
    rgb = []
    for _ in range(n):
        small = rng.uniform(40, 215, (4, 6, 3)).astype(np.float32)
        rgb.append(cv2.resize(small, (K.width, K.height), interpolation=cv2.INTER_LINEAR).astype(np.uint8))
    depth = rng.integers(300, 6000, (n, DEPTH_WH[1], DEPTH_WH[0])).astype(np.uint16)
    conf = rng.integers(0, 3, (n, DEPTH_WH[1], DEPTH_WH[0])).astype(np.uint8)
    times = 1234.5 + np.arange(n) / 30.0
    return {"T": make_T(R, pos), "rgb": rgb, "depth": depth, "conf": conf, "t": times}


def write_stray(root: Path, gt: dict, header: bool = True, imu: bool = True) -> Path:
    with StrayScannerWriter(root, K, 30.0, header=header) as w:
        for i in range(len(gt["T"])):
            w.add_frame(gt["rgb"][i], gt["depth"][i], gt["conf"][i], gt["T"][i], gt["t"][i])
        if imu:
            ti = gt["t"][0] + np.arange(50) / 100.0
            w.add_imu(ti, np.tile([0.1, -9.7, 0.3], (50, 1)), np.tile([0.01, 0.02, -0.03], (50, 1)))
    return root


@pytest.fixture(scope="module")
def stray(tmp_path_factory):
    gt = ground_truth(15)
    return write_stray(tmp_path_factory.mktemp("stray") / "cap", gt), gt


def test_round_trip(stray):
    root, gt = stray
    assert detect_format(root) == "strayscanner"
    cap = open_capture(root)
    assert cap.format == "strayscanner" and cap.num_frames == 15 and cap.fps == pytest.approx(30.0)
    assert cap.rgb_intrinsics == K
    assert cap.depth_intrinsics == K.scaled(*DEPTH_WH)
    np.testing.assert_allclose(cap.trajectory.T_world_cam, gt["T"], atol=1e-5)
    np.testing.assert_array_equal(cap.trajectory.frame_ids, np.arange(15))
    np.testing.assert_allclose(cap.timestamps_s, gt["t"], atol=1e-6)
    for i in (0, 7, 14, 3):
        f = cap.frame(i)
        assert np.abs(f.depth_m - gt["depth"][i] / 1000.0).max() <= 1e-3
        np.testing.assert_array_equal(f.confidence, gt["conf"][i])
        assert np.abs(f.rgb.astype(int) - gt["rgb"][i]).mean() < 4.0
        np.testing.assert_allclose(f.T_world_cam, gt["T"][i], atol=1e-5)


def test_depth_mm_is_the_stored_millimetres_and_what_the_metres_round_back_to(stray):
    from embodmocap.io.frame_stack import depth_mm

    root, gt = stray
    cap = open_capture(root)
    for i in (0, 7, 14):
        mm = cap.frames.depth_mm(i)
        assert mm.dtype == np.uint16
        np.testing.assert_array_equal(mm, gt["depth"][i])
        np.testing.assert_array_equal(depth_mm(cap.frames.depth_m(i)), mm)
    # Every stored value: metres as read_depth_image makes them (float32 / 1000) round back exactly,
    # so Stage II's integer path writes the stack the float path wrote.
    every = np.arange(65536, dtype=np.uint16)
    np.testing.assert_array_equal(depth_mm(every.astype(np.float32) / 1000.0), every)


def test_imu_read_in_mps2(stray):
    root, gt = stray
    imu = read_strayscanner(root).imu
    assert imu.accel_mps2.shape == (50, 3)
    np.testing.assert_allclose(imu.accel_mps2[0], [0.1, -9.7, 0.3], atol=1e-6)
    np.testing.assert_allclose(imu.gyro_radps[0], [0.01, 0.02, -0.03], atol=1e-6)


def test_imu_in_g_is_converted(tmp_path):
    root = write_stray(tmp_path / "cap", ground_truth(3), imu=False)
    rows = "".join(f"{10 + i * 0.01:.3f}, 0.01, -0.99, 0.02, 0.1, 0.2, 0.3\n" for i in range(20))
    (root / "imu.csv").write_text("timestamp, a_x, a_y, a_z, alpha_x, alpha_y, alpha_z\n" + rows)
    imu = read_strayscanner(root).imu
    np.testing.assert_allclose(imu.accel_mps2[0], np.array([0.01, -0.99, 0.02]) * 9.80665, rtol=1e-9)
    np.testing.assert_allclose(imu.timestamps_s[:2], [10.0, 10.01])


def test_old_headerless_odometry(tmp_path):
    gt = ground_truth(6, seed=3)
    root = write_stray(tmp_path / "old", gt, header=False)
    assert not (root / "odometry.csv").read_text().startswith("timestamp")
    cap = read_strayscanner(root)
    np.testing.assert_allclose(cap.trajectory.T_world_cam, gt["T"], atol=1e-5)
    np.testing.assert_array_equal(cap.trajectory.frame_ids, np.arange(6))
    # No time column: frame times come from the video.
    np.testing.assert_allclose(cap.timestamps_s, np.arange(6) / 30.0, atol=1e-6)


def test_odometry_padding_spacing_and_column_order(tmp_path):
    gt = ground_truth(4, seed=1)
    root = write_stray(tmp_path / "cap", gt)
    lines = (root / "odometry.csv").read_text().splitlines()
    assert lines[1].split(",")[1] == " 000000"  # zero-padded frame, space after comma
    # Reorder columns: the reader goes by header names.
    rows = [[c.strip() for c in ln.split(",")] for ln in lines]
    perm = [2, 3, 4, 5, 6, 7, 8, 1, 0]
    (root / "odometry.csv").write_text("\n".join(",".join(r[j] for j in perm) for r in rows) + "\n")
    cap = read_strayscanner(root)
    np.testing.assert_allclose(cap.trajectory.T_world_cam, gt["T"], atol=1e-5)
    np.testing.assert_allclose(cap.timestamps_s, gt["t"], atol=1e-6)


def test_gravity_horizontal_arkit_camera_points_y_down(tmp_path):
    """A camera looking horizontally in ARKit: OpenCV y axis along ARKit -Y -> world -Z."""
    root = write_stray(tmp_path / "cap", ground_truth(2), imu=False)
    # q = 180 deg about x: the app's q_WA * q_AC with ARKit's identity camera (looking along -Z).
    rows = "".join(f"{i / 30:.6f}, {i:06d}, 1.0, 1.5, -2.0, 1.0, 0.0, 0.0, 0.0\n" for i in range(2))
    (root / "odometry.csv").write_text("timestamp, frame, x, y, z, qx, qy, qz, qw\n" + rows)
    T = read_strayscanner(root).trajectory.T_world_cam[0]
    np.testing.assert_allclose(T[:3, 1], [0, 0, -1], atol=1e-12)  # camera y (down) -> world -Z
    np.testing.assert_allclose(T[:3, 2], [0, 1, 0], atol=1e-12)  # forward: ARKit -Z -> world +Y
    np.testing.assert_allclose(T[:3, 3], [1.0, 2.0, 1.5], atol=1e-12)  # ARKit height y=1.5 -> z
