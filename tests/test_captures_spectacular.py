"""Spectacular AI recordings: writer -> reader round trips, portrait, time matching, transforms.json."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from embodmocap.geometry.transforms import apply_T, invert_T, make_T, rot_x, rot_z
from embodmocap.io.captures import (
    SpectacularWriter, detect_format, open_capture, read_spectacular, read_transforms_json,
    write_transforms_json,
)
from embodmocap.types import Intrinsics

K = Intrinsics(fx=80.0, fy=81.0, cx=47.3, cy=32.1, width=96, height=64)
DEPTH_WH = (32, 24)


def ground_truth(n: int, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 30.0
    R = rot_z(rng.uniform(-np.pi, np.pi) + 0.6 * np.sin(0.6 * t)) @ rot_x(-np.pi / 2 + 0.15 * np.cos(1.3 * t))
    pos = np.stack([np.cos(0.2 * t) * 2, np.sin(0.2 * t) * 2, 1.4 + 0.05 * np.sin(3 * t)], axis=1)
    rgb = [cv2.resize(rng.uniform(40, 215, (4, 6, 3)).astype(np.float32), (K.width, K.height)).astype(np.uint8)
           for _ in range(n)]
    depth = rng.integers(300, 6000, (n, DEPTH_WH[1], DEPTH_WH[0])).astype(np.uint16)
    return {"T": make_T(R, pos + rng.normal(0, 1, 3)), "rgb": rgb, "depth": depth, "t": 5000.25 + t}


def write_sai(root: Path, gt: dict, portrait: bool = False) -> Path:
    with SpectacularWriter(root, K, 30.0, portrait=portrait) as w:
        for i in range(len(gt["T"])):
            w.add_frame(gt["rgb"][i], gt["depth"][i], None, gt["T"][i], gt["t"][i])
        ti = gt["t"][0] + np.arange(40) / 100.0
        w.add_imu(ti, np.tile([0.0, 0.1, 9.8], (40, 1)), np.column_stack([ti - ti[0], 0 * ti, 0 * ti]))
    return root


@pytest.fixture(scope="module")
def sai(tmp_path_factory):
    gt = ground_truth(12)
    return write_sai(tmp_path_factory.mktemp("sai") / "rec", gt), gt


def test_files_written_like_the_app(sai):
    root, _ = sai
    for name in ("data.jsonl", "data.mov", "calibration.json", "metadata.json", "cameras_sai.jsonl",
                 "frames2/00000000.png", "frames2/00000011.png"):
        assert (root / name).exists(), name
    first_frame = next(json.loads(ln) for ln in (root / "data.jsonl").read_text().splitlines() if "frames" in ln)
    assert first_frame["number"] == 0 and first_frame["frames"][0]["cameraInd"] == 0
    cam = json.loads((root / "calibration.json").read_text())["cameras"][0]
    assert (cam["imageWidth"], cam["imageHeight"], cam["focalLengthX"]) == (96, 64, 80.0)


def test_round_trip(sai):
    root, gt = sai
    assert detect_format(root) == "spectacular"
    cap = open_capture(root)
    assert (cap.format, cap.num_frames) == ("spectacular", 12) and cap.fps == pytest.approx(30.0)
    assert cap.rgb_intrinsics == K and cap.depth_intrinsics == K.scaled(*DEPTH_WH)
    np.testing.assert_allclose(cap.trajectory.T_world_cam, gt["T"], atol=1e-5)
    np.testing.assert_array_equal(cap.trajectory.frame_ids, np.arange(12))
    np.testing.assert_allclose(cap.timestamps_s, gt["t"], atol=1e-9)
    for i in (0, 5, 11):
        f = cap.frame(i)
        assert np.abs(f.depth_m - gt["depth"][i] / 1000.0).max() <= 1e-3
        assert f.confidence is None
        assert np.abs(f.rgb.astype(int) - gt["rgb"][i]).mean() < 4.0
    imu = cap.imu
    assert imu.accel_mps2.shape == (40, 3)
    np.testing.assert_allclose(imu.gyro_radps[:, 0], imu.timestamps_s - imu.timestamps_s[0], atol=1e-9)


def test_poses_matched_by_nearest_time_with_tolerance(tmp_path):
    gt = ground_truth(10, seed=2)
    root = write_sai(tmp_path / "rec", gt)
    lines = [json.loads(ln) for ln in (root / "cameras_sai.jsonl").read_text().splitlines()]
    jitter = np.random.default_rng(0).uniform(-0.004, 0.004, len(lines))  # < 1/4 frame
    for ln, j in zip(lines, jitter):
        ln["time"] += j
    lines[3]["time"] += 0.5  # far from every frame: dropped, so frame 3 has no pose
    lines.append(dict(lines[0], time=lines[0]["time"] + 0.008))  # a worse duplicate for frame 0
    lines = lines[::-1]  # any order
    (root / "cameras_sai.jsonl").write_text("".join(json.dumps(x) + "\n" for x in lines))
    from embodmocap.io.captures.spectacular import scan_spectacular

    scan = scan_spectacular(root)
    keep = np.array([0, 1, 2, 4, 5, 6, 7, 8, 9])
    np.testing.assert_array_equal(scan.trajectory.frame_ids, keep)
    np.testing.assert_allclose(scan.trajectory.T_world_cam, gt["T"][keep], atol=1e-5)
    assert any("only 9 poses for 10 frames" in p.problem for p in scan.problems)


def test_portrait_recording(tmp_path):
    gt = ground_truth(6, seed=4)
    root = write_sai(tmp_path / "rec", gt, portrait=True)
    cap = read_spectacular(root)
    Kp = cap.rgb_intrinsics
    assert (Kp.width, Kp.height) == (64, 96) and (cap.depth_intrinsics.width, cap.depth_intrinsics.height) == (24, 32)
    f = cap.frame(2)
    assert f.rgb.shape == (96, 64, 3)
    assert np.abs(f.rgb.astype(int) - np.rot90(gt["rgb"][2], -1)).mean() < 4.0
    np.testing.assert_allclose(f.depth_m, np.rot90(gt["depth"][2], -1) / 1000.0, atol=1e-6)
    # A world point projects to the same scene content: rotated pixel of the landscape projection.
    X = apply_T(gt["T"][2], np.array([[0.3, -0.2, 2.5]]))  # 2.5 m in front of camera 2
    p_land = K.K @ apply_T(invert_T(gt["T"][2]), X)[0]
    u, v = p_land[:2] / p_land[2]
    p_port = Kp.K @ apply_T(invert_T(f.T_world_cam), X)[0]
    np.testing.assert_allclose(p_port[:2] / p_port[2], [K.height - 1 - v, u], atol=1e-9)
    np.testing.assert_allclose(f.T_world_cam[:3, 3], gt["T"][2][:3, 3], atol=1e-6)


def test_transforms_json_order_and_round_trip(tmp_path):
    gt = ground_truth(16, seed=5)
    path = tmp_path / "transforms.json"
    write_transforms_json(path, K, gt["T"])
    d = json.loads(path.read_text())
    names = [f["file_path"] for f in d["frames"]]
    val = [f"./images/frame_{i + 1:05d}.jpg" for i in range(16) if (i + 3) % 7 == 0]
    assert names[-len(val):] == val and names != sorted(names)  # train first, then val
    # OpenGL camera axes in the file: camera y column is minus ours.
    np.testing.assert_allclose(np.array(d["frames"][0]["transform_matrix"])[:3, 1], -gt["T"][0][:3, 1], atol=1e-12)
    K2, numbers, T = read_transforms_json(path)
    assert K2 == K
    np.testing.assert_array_equal(numbers, np.arange(1, 17))
    np.testing.assert_allclose(T, gt["T"], atol=1e-12)
