"""Our triangulation against Pose2Sim's on Pose2Sim's real 4-camera demo (BODY_25B keypoints).

Pose2Sim's raw TRC is a reference triangulation, not ground truth: it comes from the same 2D
keypoints but its own person association, view-subset search and cubic gap interpolation. What
we check:

- the median 3D distance between our points and its points (calibration world frame) is a few
  centimetres (measured 2.9 cm; threshold 4 cm), and a share of the points agree to under 1 mm
  (measured 7.5%; threshold 5%): where both picked the same views, both solve the same
  confidence-weighted DLT, so the formulation, the calibration reading and the axis mapping all
  agree;
- our median reprojection error into the JSONs is no worse than that of Pose2Sim's points
  (measured 6.9 px against 10.7 px), over the same (frame, joint, view) set;
- TRC frame numbers are JSON frame numbers + 1 (Pose2Sim writes frames from 1): that offset
  reprojects the TRC better than offset 0.
"""

from __future__ import annotations

import itertools
import logging
import warnings

import numpy as np
import pytest

from embodmocap.errors import InputError
from embodmocap.geometry.triangulation import TriangulationConfig, projection_matrices, triangulate
from embodmocap.io.openpose import keypoint_files, read_openpose_raw
from embodmocap.io.pose2sim import BODY_25B_MARKERS, R_CALIB_TRC, read_pose2sim_calibration, read_trc
from shared_data import shared_data

cv2 = pytest.importorskip("cv2")
log = logging.getLogger(__name__)

DEMO = shared_data("pose2sim_demo")
TRC = "S00_P00_T01_BalancingTrial_0-100.trc"
MIN_CONF = 0.3

needs_demo = pytest.mark.skipif(not DEMO.is_dir(), reason=f"Pose2Sim demo data not found at {DEMO}")


def read_views(names):
    """JSON frames (T,), undistorted pixels (T, V, Pmax, 25, 2) and confidences (T, V, Pmax, 25)
    for every camera; people missing from a file have confidence 0."""
    cams = read_pose2sim_calibration(DEMO / "Calib_qualisys.toml")
    per_view = []
    for name in names:
        folder = DEMO / "pose" / f"cam{name.split('_')[-1]}_json"
        per_view.append({f: read_openpose_raw(p) for f, p in keypoint_files(folder).items()})
    frames = np.array(sorted(per_view[0]))
    assert all(sorted(v) == list(frames) for v in per_view)
    n_people = max(raw.shape[0] for v in per_view for raw in v.values())
    kp = np.zeros((len(frames), len(names), n_people, 25, 3))
    for v, view in enumerate(per_view):
        for t, f in enumerate(frames):
            kp[t, v, : view[f].shape[0]] = view[f]
    xy = np.empty(kp.shape[:-1] + (2,))
    for v, name in enumerate(names):
        K, dist = cams[name].K, cams[name].dist
        pts = kp[:, v, ..., :2].reshape(-1, 1, 2)
        xy[:, v] = cv2.undistortPoints(pts, K, dist, P=K).reshape(xy[:, v].shape)
    return frames, xy, kp[..., 2]


def associate(P, xy, conf):
    """Pick one person per (frame, view): of every combination of the people in each view, the
    one whose triangulation (no rejection) has the lowest median reprojection error.

    xy (T, V, Pmax, 25, 2), conf (T, V, Pmax, 25) -> xy (T, V, 25, 2), conf (T, V, 25).
    """
    T, V = conf.shape[:2]
    present = (conf.max(-1) > 0).any(0).sum(-1)  # (V,) people ever present in each view
    combos = np.array(list(itertools.product(*[range(max(int(n), 1)) for n in present])))  # (C, V)
    views = np.arange(V)
    # every combination as one batch of C * T frames: (T, C, V, ...) -> (C * T, V, ...)
    xs = xy[:, views, combos].transpose(1, 0, 2, 3, 4).reshape(-1, V, 25, 2)
    cs = conf[:, views, combos].transpose(1, 0, 2, 3).reshape(-1, V, 25)
    res = triangulate(P, xs, cs, TriangulationConfig(min_conf=MIN_CONF, reject_px=np.inf, max_gap_frames=0))
    err = res.reproj_err_px.reshape(len(combos), T, -1)
    with warnings.catch_warnings():  # a combination with no triangulated point: all-NaN slice
        warnings.simplefilter("ignore", RuntimeWarning)
        score = np.nanmedian(err, axis=-1)
    best = np.argmin(np.where(np.isnan(score), np.inf, score), axis=0)  # (T,)
    t = np.arange(T)[:, None]
    return xy[t, views, combos[best]], conf[t, views, combos[best]]


@needs_demo
def test_matches_pose2sim_trc():
    cams = read_pose2sim_calibration(DEMO / "Calib_qualisys.toml")
    names = list(cams)
    assert len(names) == 4 and all(c.size == (1088, 1920) for c in cams.values())
    P = projection_matrices(np.stack([cams[n].K for n in names]), np.stack([cams[n].T_world_cam for n in names]))
    frames, xy_all, conf_all = read_views(names)
    xy, conf = associate(P, xy_all, conf_all)
    res = triangulate(P, xy, conf, TriangulationConfig(min_conf=MIN_CONF))

    markers, times, trc_frames, xyz = read_trc(DEMO / "pose-3d" / TRC)
    assert xyz.shape == (100, 21, 3) and trc_frames[0] == 1
    np.testing.assert_allclose(times, trc_frames / 60.0)
    theirs_all = xyz @ R_CALIB_TRC.T  # TRC Y-up axes -> calibration world
    joints = list(BODY_25B_MARKERS)
    cols = [markers.index(BODY_25B_MARKERS[j]) for j in joints]

    def reproj_trc(offset):
        rows = np.searchsorted(frames, trc_frames - offset)
        ok = (rows < len(frames)) & (frames[np.minimum(rows, len(frames) - 1)] == trc_frames - offset)
        X = theirs_all[ok][:, cols]
        h = np.einsum("vij,tkj->tvki", P[..., :3], X) + P[None, :, None, :, 3]
        err = np.linalg.norm(h[..., :2] / h[..., 2:] - xy[rows[ok]][:, :, joints], axis=-1)  # (n, V, J)
        seen = conf[rows[ok]][:, :, joints] >= MIN_CONF
        return rows[ok], X, err, seen

    rows, theirs, err_trc, seen = reproj_trc(1)
    _, _, err_trc0, seen0 = reproj_trc(0)
    assert np.median(err_trc[seen]) < np.median(err_trc0[seen0])  # frame match: JSON = TRC - 1

    ours = res.points[rows][:, joints]
    dist = np.linalg.norm(ours - theirs, axis=-1)
    err_ours = res.reproj_err_px[rows][:, joints].transpose(0, 2, 1)  # (n, V, J)
    both = seen & np.isfinite(err_ours)
    med_3d = float(np.nanmedian(dist))
    share_same = float(np.nanmean(dist < 1e-3))
    med_ours, med_trc = float(np.median(err_ours[both])), float(np.median(err_trc[both]))
    log.info(
        "Pose2Sim demo: median 3D difference %.1f cm (90th pct %.1f cm), %.1f%% within 1 mm; "
        "median reprojection error ours %.2f px, TRC %.2f px; %d long gaps",
        100 * med_3d, 100 * np.nanpercentile(dist, 90), 100 * share_same, med_ours, med_trc, len(res.long_gaps),
    )
    assert np.isfinite(dist).mean() > 0.9
    assert med_3d < 0.04
    assert share_same > 0.05
    assert med_ours <= med_trc


def test_reader_errors(tmp_path):
    bad = tmp_path / "Calib.toml"
    bad.write_text("[cam_01]\nmatrix = [[1, 0], [0, 1]]\n")
    with pytest.raises(InputError, match="matrix"):
        read_pose2sim_calibration(bad)
    bad.write_text("[metadata]\nadjusted = false\n")
    with pytest.raises(InputError, match="no camera"):
        read_pose2sim_calibration(bad)
    bad.write_text("not = [toml")
    with pytest.raises(InputError, match="TOML"):
        read_pose2sim_calibration(bad)
    trc = tmp_path / "x.trc"
    trc.write_text("hello\n")
    with pytest.raises(InputError, match="not a TRC"):
        read_trc(trc)


def test_calibration_known_answer(tmp_path):
    """A camera 2 m behind the origin on -Y looking along +Y (world Z up), written as Pose2Sim
    would: Rodrigues world -> camera rotation and world -> camera translation."""
    R_cam_world = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # x right, y down, z forward
    centre = np.array([0.0, -2.0, 1.0])
    rvec = cv2.Rodrigues(R_cam_world)[0].ravel()
    tvec = -R_cam_world @ centre
    path = tmp_path / "Calib_test.toml"
    path.write_text(
        f"""[cam_a]\nname = "front"\nsize = [ 640.0, 480.0]\n"""
        f"""matrix = [ [ 500.0, 0.0, 320.0], [ 0.0, 500.0, 240.0], [ 0.0, 0.0, 1.0]]\n"""
        f"""distortions = [ 0.01, -0.02, 0.0, 0.0]\nrotation = {[float(x) for x in rvec]}\n"""
        f"""translation = {[float(x) for x in tvec]}\nfisheye = false\n\n[metadata]\nadjusted = false\n"""
    )
    cams = read_pose2sim_calibration(path)
    assert list(cams) == ["front"]
    K, dist, T_world_cam, size = cams["front"]
    assert size == (640, 480)
    np.testing.assert_allclose(dist, [0.01, -0.02, 0.0, 0.0])
    np.testing.assert_allclose(T_world_cam[:3, 3], centre, atol=1e-12)
    np.testing.assert_allclose(T_world_cam[:3, :3], R_cam_world.T, atol=1e-12)
    # a point 3 m in front of the camera, 0.5 m up, lands above the image centre
    P = projection_matrices(K, T_world_cam[None])[0]
    h = P @ [0.0, 1.0, 1.5, 1.0]
    np.testing.assert_allclose(h[:2] / h[2], [320.0, 240.0 - 500.0 * 0.5 / 3.0])


def test_trc_known_answer(tmp_path):
    """Millimetres are converted to metres; empty cells read as NaN."""
    path = tmp_path / "x.trc"
    lines = [
        "PathFileType\t4\t(X/Y/Z)\tx.trc",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
        "30\t30\t2\t2\tmm\t30\t0\t2",
        "Frame#\tTime\tA\t\t\tB\t\t",
        "\t\tX1\tY1\tZ1\tX2\tY2\tZ2",
        "",
        "1\t0.0\t1000\t2000\t3000\t4\t5\t6",
        "2\t0.0333\t1\t2\t3\t\t\t",
    ]
    path.write_text("\n".join(lines) + "\n")
    names, times, frames, xyz = read_trc(path)
    assert names == ["A", "B"]
    np.testing.assert_array_equal(frames, [1, 2])
    np.testing.assert_allclose(times, [0.0, 0.0333])
    np.testing.assert_allclose(xyz[0], [[1.0, 2.0, 3.0], [0.004, 0.005, 0.006]])
    np.testing.assert_allclose(xyz[1, 0], [0.001, 0.002, 0.003])
    assert np.isnan(xyz[1, 1]).all()
    lines[2] = "30\t30\t2\t3\tmm\t30\t0\t2"  # NumMarkers disagrees with the names
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match="NumMarkers"):
        read_trc(path)
    lines[2] = "30\t30\t2\t2\tmm\t30\t0\t2"
    lines[7] = "2\t0.0333\t1\tx\t3\t\t\t"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match="non-numeric"):
        read_trc(path)
