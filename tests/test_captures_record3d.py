"""Record3D exports (folder and .r3d zip): round trip and ARKit convention."""

import json

import cv2
import numpy as np
import pytest

pytest.importorskip("lzfse")

from embodmocap.geometry.transforms import make_T, rot_x, rot_z  # noqa: E402
from embodmocap.io.captures import detect_format, open_capture, read_record3d, write_record3d  # noqa: E402
from embodmocap.types import Intrinsics  # noqa: E402

K = Intrinsics(fx=80.0, fy=81.0, cx=47.3, cy=32.1, width=96, height=64)


def ground_truth(n: int, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 30.0
    R = rot_z(rng.uniform(-np.pi, np.pi) + 0.6 * np.sin(0.6 * t)) @ rot_x(-np.pi / 2 + 0.15 * np.cos(1.3 * t))
    pos = np.stack([np.cos(0.2 * t) * 2, np.sin(0.2 * t) * 2, 1.4 + 0.05 * np.sin(3 * t)], axis=1)
    rgb = [cv2.resize(rng.uniform(40, 215, (4, 6, 3)).astype(np.float32), (96, 64)).astype(np.uint8) for _ in range(n)]
    depth = rng.uniform(0.3, 6.0, (n, 24, 32)).astype(np.float32)
    conf = rng.integers(0, 3, (n, 24, 32)).astype(np.uint8)
    return {"T": make_T(R, pos), "rgb": rgb, "depth": depth, "conf": conf, "t": 77.0 + t}


@pytest.mark.parametrize("name", ["export", "take.r3d"])
def test_round_trip(tmp_path, name):
    gt = ground_truth(8)
    out = write_record3d(tmp_path / name, gt["rgb"], gt["depth"], gt["T"], K, 30.0,
                         confidence=gt["conf"], timestamps_s=gt["t"])
    assert detect_format(out) == "record3d"
    cap = open_capture(out)
    assert (cap.format, cap.num_frames, cap.fps) == ("record3d", 8, 30.0)
    assert cap.rgb_intrinsics == K and cap.depth_intrinsics == K.scaled(32, 24)
    np.testing.assert_allclose(cap.trajectory.T_world_cam, gt["T"], atol=1e-5)
    np.testing.assert_allclose(cap.timestamps_s, gt["t"])
    for i in (0, 4, 7):
        f = cap.frame(i)
        np.testing.assert_array_equal(f.depth_m, gt["depth"][i])
        np.testing.assert_array_equal(f.confidence, gt["conf"][i])
        assert np.abs(f.rgb.astype(int) - gt["rgb"][i]).mean() < 3.0


def test_metadata_K_is_column_major(tmp_path):
    out = write_record3d(tmp_path / "e", ground_truth(2)["rgb"], ground_truth(2)["depth"], ground_truth(2)["T"], K, 30)
    meta = json.loads((out / "metadata").read_text())
    assert meta["K"][2] == 0.0 and meta["K"][6] == pytest.approx(K.cx) and meta["K"][7] == pytest.approx(K.cy)
    assert (meta["w"], meta["h"], meta["dw"], meta["dh"]) == (96, 64, 32, 24)


def test_gravity_arkit_identity_camera(tmp_path):
    """ARKit camera with identity rotation looks along -Z (Y-up), its GL y axis up: our OpenCV
    y axis must point to world -Z and the view direction must be horizontal."""
    gt = ground_truth(2)
    out = write_record3d(tmp_path / "e", gt["rgb"], gt["depth"], gt["T"], K, 30)
    meta = json.loads((out / "metadata").read_text())
    meta["poses"] = [[0, 0, 0, 1, 0.5, 1.6, -1.0]] * 2
    (out / "metadata").write_text(json.dumps(meta))
    T = read_record3d(out).trajectory.T_world_cam[0]
    np.testing.assert_allclose(T[:3, 1], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(T[:3, 2], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [0.5, 1.0, 1.6], atol=1e-12)
