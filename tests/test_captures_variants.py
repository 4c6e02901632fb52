"""Every app version's export, written by the test in that version's layout from the studio's room:
inspect finds no problem and names the version; the reader gives back the true poses (so gravity),
intrinsics at the frames' size, depth and times; incomplete exports say what is missing."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("lzfse")

from capture_variants import VARIANTS, render_walk, write_variant  # noqa: E402
from embodmocap.errors import InputError  # noqa: E402
from embodmocap.io.captures import open_capture  # noqa: E402
from embodmocap.check.inspect import inspect_path  # noqa: E402
from embodmocap.io.inspect_capture import check_capture  # noqa: E402

#: Words each variant's ``inspect`` line must hold.
NAMED = {
    "stray7": "header-less odometry.csv", "stray9": "9-column odometry.csv",
    "stray15": "15-column odometry.csv with per-frame intrinsics", "r3d_new_zip": ".r3d file, newer metadata",
    "r3d_new_dir": "unzipped .r3d), newer metadata", "r3d_old_zip": "put in ARKit's world with initPose",
    "r3d_old_dir": "depth size from the depth data; times from fps", "r3d_exr": "EXR + JPG export (9 frames, 3 dropped",
    "spectacular": "Spectacular AI recording (ios iPhone14,3), data.mov (Spectacular Rec app)",
    "spectacular_sdk": "Spectacular AI recording, data.mp4 (SDK recorder)",
}


@pytest.fixture(scope="module")
def walks():
    return {
        30: render_walk(64, 48, (32, 24), 0.4, 30.0),
        60: render_walk(64, 48, (32, 24), 0.2, 60.0),
        "portrait": render_walk(64, 48, (32, 24), 0.4, 30.0, portrait=True),
    }


def _walk_for(name, walks):
    if VARIANTS[name][1]:
        return walks["portrait"]
    return walks[60] if name == "stray15" else walks[30]


def _angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1, 1)))


@pytest.mark.parametrize("name", sorted(VARIANTS))
def test_every_variant_reads_with_true_gravity(tmp_path, walks, name):
    walk = _walk_for(name, walks)
    path = write_variant(name, tmp_path / name, walk, big_video=(256, 192) if name == "stray15" else None)
    report = check_capture(path)
    assert report.problems == [], report.problems
    assert NAMED[name] in report.variant, report.variant
    text, problems = inspect_path(path)
    assert problems == [] and f"version   {report.variant}" in text

    cap = open_capture(path)
    keep = np.array([i for i in range(len(walk.T_vio_cam)) if not (name == "r3d_exr" and i in (3, 4, 9))])
    T_true = walk.T_vio_cam[keep]
    T = cap.trajectory.T_world_cam
    assert cap.num_frames == len(keep) and len(T) == len(keep)
    # Gravity: the world's down seen from each camera is the true one (the yaw and offset of the
    # VIO world are the capture's own and kept as written).
    down_true = np.swapaxes(T_true[:, :3, :3], 1, 2) @ np.array([0, 0, -1.0])
    down = np.swapaxes(T[:, :3, :3], 1, 2) @ np.array([0, 0, -1.0])
    assert _angle_deg(down, down_true).max() < 1e-3
    np.testing.assert_allclose(T, T_true, atol=1e-5)

    # Intrinsics at the size the frames come in, whatever size the app wrote them for.
    rgb = cap.frame(0).rgb
    K_true = walk.K.scaled(rgb.shape[1], rgb.shape[0])
    K = cap.rgb_intrinsics
    assert (K.width, K.height) == (rgb.shape[1], rgb.shape[0])
    np.testing.assert_allclose([K.fx, K.fy, K.cx, K.cy], [K_true.fx, K_true.fy, K_true.cx, K_true.cy],
                               rtol=2e-3 if name == "stray15" else 1e-5)
    assert cap.fps == pytest.approx(walk.fps, rel=1e-3)
    # Depth in metres, per frame (the frames kept after dropped ones are the right ones).
    last = len(keep) - 1
    np.testing.assert_allclose(cap.frame(last).depth_m, walk.depth_mm[keep[last]] / 1000.0, atol=1e-6)
    expected_t = walk.times[keep] if name not in ("r3d_old_zip", "r3d_old_dir", "stray7") else None
    if expected_t is not None:
        np.testing.assert_allclose(cap.timestamps_s, expected_t, atol=1e-6)
    elif name.startswith("r3d_old"):
        np.testing.assert_allclose(cap.timestamps_s, np.arange(len(keep)) / walk.fps)


def test_stray15_uses_the_per_frame_intrinsics_over_a_stale_camera_matrix(tmp_path, walks):
    walk = walks[60]
    path = write_variant("stray15", tmp_path / "s", walk)
    (path / "camera_matrix.csv").write_text("500,0,20\n0,500,20\n0,0,1\n")  # wrong on purpose
    K = open_capture(path).rgb_intrinsics
    assert K.fx == pytest.approx(walk.K.fx, rel=2e-3) and K.cx == pytest.approx(walk.K.cx, rel=2e-3)


def test_older_record3d_without_init_pose_is_refused(tmp_path, walks):
    path = write_variant("r3d_old_dir", tmp_path / "r", walks["portrait"])
    meta = json.loads((path / "metadata").read_text())
    del meta["initPose"]
    (path / "metadata").write_text(json.dumps(meta))
    with pytest.raises(InputError, match="relative to the first camera.*no initPose") as e:
        open_capture(path)
    assert e.value.path == path / "metadata"


# --------------------------------------------------------------------------- bad input


def test_stray_without_video_is_named_as_such(tmp_path, walks):
    path = write_variant("stray9", tmp_path / "s", walks[30])
    (path / "rgb.mp4").unlink()
    with pytest.raises(InputError, match="Stray Scanner export holds its RGB video as rgb.mp4") as e:
        open_capture(path)
    assert e.value.path == path / "rgb.mp4"
    text, problems = inspect_path(path)
    assert "format    strayscanner" in text and any("rgb.mp4" in p for p in problems)


def test_stray_with_fewer_depth_maps_than_poses(tmp_path, walks):
    path = write_variant("stray15", tmp_path / "s", walks[60])
    n = len(walks[60].T_vio_cam)
    for i in range(n - 3, n):
        (path / "depth" / f"{i:06d}.png").unlink()
    with pytest.raises(InputError, match="3 of 12 files missing.*Stray Scanner writes one depth/NNNNNN.png") as e:
        open_capture(path)
    assert e.value.path == path / "depth" / f"{n - 3:06d}.png"


def test_exr_that_does_not_decode(tmp_path, walks):
    path = write_variant("r3d_exr", tmp_path / "x", walks["portrait"])
    bad = path / "depth" / "7.exr"
    bad.write_bytes(bad.read_bytes()[:40])  # truncated
    report = check_capture(path)
    assert any(str(bad) in p and "EXR does not decode" in p for p in report.problems), report.problems
    cap = open_capture(path)  # the quick scan decodes the first EXR only; the frame read says which
    with pytest.raises(InputError, match="EXR does not decode") as e:
        cap.frame(5).depth_m  # frame 5 of the capture is file 7 (3 and 4 were dropped)
    assert e.value.path == bad


def test_exr_export_missing_a_depth_file(tmp_path, walks):
    path = write_variant("r3d_exr", tmp_path / "x", walks["portrait"])
    (path / "depth" / "10.exr").unlink()
    with pytest.raises(InputError, match="EXR \\+ JPG export writes depth/N.exr") as e:
        open_capture(path)
    assert e.value.path == path / "depth" / "10.exr"


def test_truncated_r3d_depth(tmp_path, walks):
    path = write_variant("r3d_old_dir", tmp_path / "r", walks["portrait"])
    f = path / "rgbd" / "0.depth"
    f.write_bytes(f.read_bytes()[: len(f.read_bytes()) // 3])
    with pytest.raises(InputError) as e:
        open_capture(path)
    assert e.value.path == f


def test_unknown_folder_names_the_closest_layout(tmp_path, walks):
    path = write_variant("stray9", tmp_path / "s", walks[30])
    for name in ("rgb.mp4", "camera_matrix.csv"):
        (path / name).unlink()
    shutil.rmtree(path / "depth")
    with pytest.raises(InputError, match="closest to a Stray Scanner export: has odometry.csv, confidence/; "
                                         "lacks rgb.mp4, camera_matrix.csv, depth/, imu.csv"):
        open_capture(path)
    text, problems = inspect_path(path)
    assert "closest to a Stray Scanner export" in text and len(problems) == 1
    exr = write_variant("r3d_exr", tmp_path / "x", walks["portrait"])
    (exr / "metadata.json").unlink()
    with pytest.raises(InputError, match="closest to a Record3D EXR \\+ JPG export: has rgb/, depth/; "
                                         "lacks metadata.json"):
        open_capture(exr)


@pytest.mark.parametrize("matrix_size, frames, expect", [
    ((960, 720), (1920, 1440), (960, 720)),     # a matrix for half the video's size
    ((1920, 1440), (1920, 1440), None),         # for the video itself
    ((4032, 3024), (1920, 1440), (4032, 3024)),  # for the sensor's full size
    ((1440, 1920), (720, 960), (1440, 1920)),   # portrait
])
def test_intrinsics_written_for_another_size(matrix_size, frames, expect):
    from embodmocap.io.captures.common import intrinsics_for_image
    from embodmocap.types import Intrinsics

    w, h = matrix_size
    # A phone's principal point: a few pixels off the centre.
    K_app = Intrinsics(1.1 * w, 1.1 * w, (w - 1) / 2 + 0.011 * w, (h - 1) / 2 - 0.008 * h, w, h)
    K, other = intrinsics_for_image(K_app.K, *frames)
    assert other == expect
    truth = K_app.scaled(*frames)
    np.testing.assert_allclose([K.fx, K.fy, K.cx, K.cy], [truth.fx, truth.fy, truth.cx, truth.cy], rtol=1e-12)
    assert (K.width, K.height) == frames


def test_a_zipped_recording_says_to_unzip_it(tmp_path, walks):
    import zipfile

    rec = write_variant("spectacular", tmp_path / "recording_1", walks[30])
    zpath = tmp_path / "recording_1.zip"
    with zipfile.ZipFile(zpath, "w") as z:
        for f in rec.rglob("*"):
            z.write(f, f.relative_to(tmp_path))
    with pytest.raises(InputError, match="a zip archive: unzip it"):
        open_capture(zpath)


@pytest.mark.parametrize("name, depth_file, says", [
    ("spectacular", "frames2/00000010.png", "one frames2/NNNNNNNN.png \\(uint16 mm\\) per video frame"),
    ("r3d_new_dir", "rgbd/10.depth", "the app writes rgbd/N.depth beside every rgbd/N.jpg"),
])
def test_fewer_depth_frames_than_frames_names_what_the_app_writes(tmp_path, walks, name, depth_file, says):
    path = write_variant(name, tmp_path / name, _walk_for(name, walks))
    (path / depth_file).unlink()
    with pytest.raises(InputError, match=says) as e:
        open_capture(path)
    assert e.value.path == path / depth_file
