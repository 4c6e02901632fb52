"""Bad captures: one clear InputError naming the file; inputs untouched; inspect lists everything."""

import hashlib
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from embodmocap.errors import InputError
from embodmocap.geometry.transforms import make_T, rot_x, rot_z
from embodmocap.io.captures import SpectacularWriter, StrayScannerWriter, open_capture, write_record3d
from embodmocap.io.inspect_capture import check_capture, format_report
from embodmocap.types import Intrinsics

K = Intrinsics(fx=80.0, fy=80.0, cx=47.5, cy=31.5, width=96, height=64)
N = 10


def _gt(seed: int = 0):
    rng = np.random.default_rng(seed)
    t = np.arange(N) / 30.0
    T = make_T(rot_z(0.5 * np.sin(t)) @ rot_x(np.full(N, -np.pi / 2)), np.stack([0.3 * t, 0 * t, 1.4 + 0 * t], 1))
    rgb = [cv2.resize(rng.uniform(40, 215, (4, 6, 3)).astype(np.float32), (96, 64)).astype(np.uint8) for _ in range(N)]
    depth = rng.integers(300, 5000, (N, 24, 32)).astype(np.uint16)
    return T, rgb, depth, 10.0 + t


@pytest.fixture(scope="module")
def clean_stray(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("clean") / "stray"
    T, rgb, depth, t = _gt()
    with StrayScannerWriter(root, K, 30.0) as w:
        for i in range(N):
            w.add_frame(rgb[i], depth[i], np.full((24, 32), 2, np.uint8), T[i], t[i])
    return root


@pytest.fixture
def stray(clean_stray, tmp_path) -> Path:
    root = tmp_path / "stray"
    shutil.copytree(clean_stray, root)
    return root


def folder_hash(root: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(root.rglob("*")):
        h.update(str(p.relative_to(root)).encode())
        if p.is_file():
            h.update(p.read_bytes())
    return h.hexdigest()


def assert_input_error(root: Path, expected_file: Path, match: str) -> InputError:
    before = folder_hash(root)
    with pytest.raises(InputError, match=match) as e:
        cap = open_capture(root)
        for f in cap.iter_frames():  # errors found only when a frame is read also count
            pass
    assert e.value.path == expected_file, str(e.value)
    assert str(expected_file) in str(e.value) and "\n" not in str(e.value)
    assert folder_hash(root) == before
    return e.value


def _odometry_rows(root: Path) -> tuple[str, list[list[str]]]:
    header, *rows = (root / "odometry.csv").read_text().splitlines()
    return header, [r.split(",") for r in rows]


def _write_odometry(root: Path, header: str, rows: list[list[str]]) -> None:
    (root / "odometry.csv").write_text(header + "\n" + "".join(",".join(r) + "\n" for r in rows))


def test_clean_capture_reads(clean_stray):
    assert open_capture(clean_stray).num_frames == N
    report = check_capture(clean_stray)
    assert report.ok and report.pose_count == N and report.format == "strayscanner"
    assert report.path_length_m == pytest.approx(0.3 * (N - 1) / 30.0, rel=1e-6)
    assert "problems  none" in format_report(report)


def test_truncated_video(stray):
    data = (stray / "rgb.mp4").read_bytes()
    (stray / "rgb.mp4").write_bytes(data[: len(data) // 2])
    assert_input_error(stray, stray / "rgb.mp4", "video")


def test_missing_depth_png(stray):
    (stray / "depth" / "000004.png").unlink()
    assert_input_error(stray, stray / "depth" / "000004.png", "missing")


def test_fewer_pose_rows_than_frames(stray):
    header, rows = _odometry_rows(stray)
    _write_odometry(stray, header, rows[:-3])
    assert_input_error(stray, stray / "odometry.csv", f"only {N - 3} poses for {N} frames")


def test_nan_pose(stray):
    header, rows = _odometry_rows(stray)
    rows[5][2] = " nan"
    _write_odometry(stray, header, rows)
    assert_input_error(stray, stray / "odometry.csv", "NaN")


def test_jumping_pose(stray):
    header, rows = _odometry_rows(stray)
    rows[6][2] = f" {float(rows[6][2]) + 2.0:.6f}"  # 2 m in one frame
    _write_odometry(stray, header, rows)
    assert_input_error(stray, stray / "odometry.csv", "jump")


def test_wrong_depth_shape(stray):
    cv2.imwrite(str(stray / "depth" / "000003.png"), np.zeros((20, 30), np.uint16))
    assert_input_error(stray, stray / "depth" / "000003.png", "30x20")


def test_wrong_depth_dtype(stray):
    cv2.imwrite(str(stray / "depth" / "000000.png"), np.zeros((24, 32), np.uint8))
    assert_input_error(stray, stray / "depth" / "000000.png", "uint16")


def test_missing_camera_matrix(stray):
    (stray / "camera_matrix.csv").unlink()
    assert_input_error(stray, stray / "camera_matrix.csv", "camera_matrix.csv not found")


def test_intrinsics_for_another_resolution(stray):
    (stray / "camera_matrix.csv").write_text("1400,0,960\n0,1400,720\n0,0,1\n")
    assert_input_error(stray, stray / "camera_matrix.csv", "do not fit")


def test_malformed_old_headerless_odometry(stray):
    _, rows = _odometry_rows(stray)
    body = [r[2:] for r in rows]  # header-less x..qw
    body[4] = body[4][:5]  # a cut row
    (stray / "odometry.csv").write_text("".join(",".join(r) + "\n" for r in body))
    assert_input_error(stray, stray / "odometry.csv", "row 5 .* 5 columns, expected 7")


def test_unknown_folder_lists_expected_formats(tmp_path):
    (tmp_path / "x.txt").write_text("hi")
    with pytest.raises(InputError, match="Stray Scanner export: rgb.mp4") as e:
        open_capture(tmp_path)
    assert e.value.path == tmp_path and "Record3D EXR + JPG export: metadata.json" in str(e.value)


def test_inspect_lists_every_problem_at_once(stray):
    (stray / "camera_matrix.csv").unlink()
    (stray / "depth" / "000002.png").unlink()
    header, rows = _odometry_rows(stray)
    rows[1][3] = " nan"
    _write_odometry(stray, header, rows[:-1])
    before = folder_hash(stray)
    report = check_capture(stray)
    text = "\n".join(report.problems)
    assert len(report.problems) == 4, text
    for needle in ("camera_matrix.csv not found", "000002.png", f"only {N - 1} poses", "NaN"):
        assert needle in text
    assert folder_hash(stray) == before
    assert "problems  4" in format_report(report)


def test_inspect_reports_timestamp_gaps(stray):
    header, rows = _odometry_rows(stray)
    for r in rows[6:]:
        r[0] = f"{float(r[0]) + 0.2:.6f}"
    _write_odometry(stray, header, rows)
    report = check_capture(stray)
    assert report.ok and [g[0] for g in report.timestamp_gaps] == [6]
    assert report.timestamp_gaps[0][1] == pytest.approx(0.2 + 1 / 30, abs=1e-5)


def test_spectacular_missing_pose_file(tmp_path):
    T, rgb, depth, t = _gt()
    root = tmp_path / "sai"
    with SpectacularWriter(root, K, 30.0) as w:
        for i in range(N):
            w.add_frame(rgb[i], depth[i], None, T[i], t[i])
    (root / "cameras_sai.jsonl").unlink()
    assert_input_error(root, root / "cameras_sai.jsonl", "not found")


def test_record3d_missing_depth_and_short_poses(tmp_path):
    pytest.importorskip("lzfse")
    T, rgb, depth, t = _gt()
    root = write_record3d(tmp_path / "r3d", rgb, depth.astype(np.float32) / 1000, T, K, 30.0)
    (root / "rgbd" / "3.depth").unlink()
    assert_input_error(root, root / "rgbd" / "3.depth", "missing")
    report = check_capture(root)
    assert len(report.problems) == 1
