"""Issue 29, parts 5 and 6: the benchmark measures the sequence's edges (W-MPJPE with a chunk at
every start, the first five frames beside the median frame, silently wrong frames), and each frame
of the motion says when a view contradicts it (the ``suspect`` flag and quality figures, carried
into the exports)."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from embodmocap.evaluate.metrics import frame_errors_mm, w_mpjpe, w_mpjpe_all_starts
from embodmocap.evaluate.session import SequenceTruth, motion_errors
from embodmocap.geometry.transforms import invert_T, look_at_T
from embodmocap.motion.quality import QualityConfig, frame_quality

K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])


def _rot_z(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


def _walk(T: int, J: int = 24, seed: int = 0) -> np.ndarray:
    """(T, J, 3) a rigid joint cloud walking 3 m along x while turning 90 degrees."""
    rng = np.random.default_rng(seed)
    body = rng.normal(scale=[0.15, 0.15, 0.45], size=(J, 3))
    t = np.arange(T) / T
    pelvis = np.stack([3.0 * t, 0.3 * np.sin(20 * t), np.full(T, 0.9)], -1)
    return np.stack([body @ _rot_z(90.0 * s).T for s in t]) + pelvis[:, None]


def test_w_mpjpe_all_starts_sees_a_bad_start_the_fixed_chunks_hide_in_the_middle():
    T = 180
    gt = _walk(T)
    pred = gt.copy()
    # A whole-body offset everywhere is aligned away; a limb 30 cm off in frames 60-61 only matters
    # for the chunks those two frames anchor (start 60, and 59 and 61 which use one of them).
    pred += [0.5, -0.2, 0.0]
    pred[60:62, 5] += [0.3, 0.0, 0.0]
    starts = w_mpjpe_all_starts(pred, gt, chunk=100)
    assert starts.shape == (T - 100 + 1,)
    assert w_mpjpe(pred, gt, chunk=100) < 1.0  # the fixed chunks start at 0 and 100: never anchored there
    assert np.median(starts) < 1.0 and starts.max() > 10.0
    assert set(np.flatnonzero(starts > 1.0)) <= {59, 60, 61}
    # Start 0 is the fixed first chunk exactly; a sequence shorter than the chunk is one chunk.
    np.testing.assert_allclose(w_mpjpe_all_starts(pred[:100], gt[:100]), [w_mpjpe(pred[:100], gt[:100])])
    np.testing.assert_allclose(w_mpjpe_all_starts(pred[:40], gt[:40]), [w_mpjpe(pred[:40], gt[:40])])
    # Batching does not change a value.
    np.testing.assert_allclose(w_mpjpe_all_starts(pred, gt, batch=7), starts)
    assert w_mpjpe_all_starts(pred[:1], gt[:1]).shape == (0,)


def test_edge_figures_and_silently_wrong_frames():
    T = 150
    gt = _walk(T)
    truth = SequenceTruth(joints=gt, T_world_vio={}, T_world_cam={}, sync_frame={}, valid=np.ones(T, dtype=bool))
    pred = gt + [0.02, 0.0, 0.0]  # 20 mm everywhere
    pred[:3, 20] += [0.0, 0.3, 0.0]  # the first three frames: one wrist 30 cm off
    pred[100, 21] += [0.0, 0.0, 0.2]  # and one frame in the middle
    np.testing.assert_allclose(frame_errors_mm(pred, gt)[5:10], 20.0)
    suspect = np.zeros(T, dtype=bool)
    suspect[[0, 1]] = True  # the fit flagged two of the four wrong frames
    e = motion_errors(pred, np.arange(T), truth, suspect=suspect)
    assert e["median_frame_mm"] == pytest.approx(20.0, abs=0.01)
    wrist_frame = (23 * 20.0 + 1000 * np.hypot(0.02, 0.3)) / 24
    assert e["first5_frame_mm"] == pytest.approx((3 * wrist_frame + 2 * 20.0) / 5, abs=0.01)
    assert e["last5_frame_mm"] == pytest.approx(20.0, abs=0.01)
    assert e["wrong_frames"] == 4 and e["wrong_unflagged_frames"] == 2 and e["suspect_frames"] == 2
    assert e["wrong_unflagged_pct"] == pytest.approx(100 * 2 / T, abs=1e-3)
    assert e["w_mpjpe_mm_all_starts_worst"] > 3 * e["w_mpjpe_mm_all_starts_median"]
    # A frame flagged invalid is not silently wrong (and not evaluated).
    valid = np.ones(T, dtype=bool)
    valid[100] = False
    e2 = motion_errors(pred, np.arange(T), truth, valid, suspect)
    assert e2["wrong_unflagged_frames"] == 1 and e2["evaluated_frames"] == T - 1


def _two_views(points: np.ndarray):
    """Cameras 4 m away at 0 and 90 degrees about the points' centre, and the points' pixels."""
    T = len(points)
    centre = points.reshape(-1, 3).mean(0)
    Twc = np.stack([np.repeat(look_at_T(centre + [4 * np.cos(a), 4 * np.sin(a), 0.2], centre)[None], T, 0)
                    for a in (0.0, np.pi / 2)], axis=1)  # (T, 2, 4, 4)
    Tcw = invert_T(Twc)
    cam = np.einsum("tvab,tjb->tvja", Tcw[..., :3, :3], points) + Tcw[..., None, :3, 3]
    uv = np.einsum("ab,tvjb->tvja", K, cam)
    kp = np.concatenate([uv[..., :2] / uv[..., 2:], np.full(uv.shape[:-1] + (1,), 0.9)], -1)
    return np.stack([K, K]), Twc, kp


def test_a_limb_far_from_both_views_is_suspect_a_wrong_detection_is_not():
    T = 6
    truth = _walk(T, J=17, seed=3)
    Ks, Twc, kp = _two_views(truth)
    fitted = truth.copy()
    fitted[:2, 9] += [0.0, 0.0, 0.3]  # left wrist 30 cm off in frames 0-1 (both views see it elsewhere)
    raw = kp.copy()
    used = kp.copy()
    used[:2, 0, [7, 9], 2] = 0.0  # Stage IV dropped view 1's left arm there: the raw detection still counts
    raw[2, 0, 9, :2] += 150.0  # frame 2: view 1's wrist detection is a blunder (view 2 agrees with the fit)
    raw[3, 1, [9, 10]] = raw[3, 1, [10, 9]]  # frame 3: view 2 swapped the wrists
    used[3, 1, [9, 10]] = used[3, 1, [10, 9]]
    q = frame_quality(fitted, Ks, Twc, used, raw, truth, None, ("v1", "v2"))
    assert q.suspect.tolist() == [True, True, False, False, False, False]
    assert q.limb_off_m[0] > 0.25 and np.nanmax(q.limb_off_m[2:]) < 1e-6
    assert q.kp3d_err_m[0] == pytest.approx(0.0, abs=1e-9)  # the median over the 17 points
    assert np.all(q.reproj_px[4:] < 1e-6) and q.reproj_px[2, 0] < 1e-6  # median per view
    # Only what the views see: a wrist no view detects says nothing.
    raw[:2, :, [9, 10], 2] = 0.0
    used[:2, :, [9, 10], 2] = 0.0
    q = frame_quality(fitted, Ks, Twc, used, raw, truth, None, ("v1", "v2"))
    assert not q.suspect[:2].any()
    # The threshold is the config's; one frame off alone is a detector's blunder, two in a row are not.
    fitted[4, 9] += [0.0, 0.0, 0.06]
    low = QualityConfig(suspect_m=0.04)
    assert not frame_quality(fitted, Ks, Twc, used, raw, truth, None, ("v1", "v2"), low).suspect[4]
    fitted[5, 9] += [0.0, 0.0, 0.06]
    assert not frame_quality(fitted, Ks, Twc, used, raw, truth, None, ("v1", "v2")).suspect[4:].any()
    assert frame_quality(fitted, Ks, Twc, used, raw, truth, None, ("v1", "v2"), low).suspect[4:].all()
    # Evidence below the config's confidence is none.
    raw[..., 2] = used[..., 2] = 0.5
    fitted[:2, 9] += [0.0, 0.0, 0.3]
    assert not frame_quality(fitted, Ks, Twc, used, raw, truth, None, ("v1", "v2")).suspect.any()


def test_a_wrong_start_and_the_frames_beside_a_flagged_run_are_suspect():
    """Issue 29 (hard studio seed 3, one phone): the right wrist 66 cm off its detection's ray in
    frame 0, undetected in frame 1, off again from frame 2: the two-frame rule (the frame and a
    neighbour) let frames 0 and 1 pass, and the frames after the flagged run whose arm each
    contradicted a different detection. At the sequence's edges the nearest judged frame is the
    neighbour; a suspect run grows over contradicted frames beside it (two at most). In the middle
    of the sequence a one-frame blunder still does not count."""
    from dataclasses import replace

    T = 30
    truth = _walk(T, J=17, seed=3)
    Ks, Twc, kp = _two_views(truth)
    Ks, Twc, kp = Ks[:1], Twc[:, :1], kp[:, :1]  # one phone
    side = np.cross(truth[0, 10] - Twc[0, 0, :3, 3], [0.0, 0.0, 1.0])
    side /= np.linalg.norm(side)
    fitted = truth.copy()
    fitted[:7, 10] += 0.3 * side  # right wrist 30 cm off the view's ray in frames 0-6
    fitted[[20, 22, 23], 10] += 0.3 * side  # and in frames 20, 22, 23
    for t, j in ((7, 7), (8, 14), (9, 15)):  # then the left elbow, the right knee, the left ankle
        fitted[t, j] += 0.3 * side
    kp[[1, 21], 0, 10, 2] = 0.0  # the view does not detect the right wrist in frames 1 and 21

    def flagged(cfg):
        return np.flatnonzero(frame_quality(fitted, Ks, Twc, kp, kp, truth, None, ("v1",), cfg).suspect).tolist()

    old = QualityConfig(edge_gap_frames=0, grow_frames=0)  # the frame and a neighbour
    assert flagged(old) == [2, 3, 4, 5, 6, 22, 23]
    assert flagged(replace(old, edge_gap_frames=4)) == [0, 1, 2, 3, 4, 5, 6, 22, 23]
    assert flagged(replace(old, grow_frames=2)) == [2, 3, 4, 5, 6, 7, 8, 22, 23]
    assert flagged(QualityConfig()) == [0, 1, 2, 3, 4, 5, 6, 7, 8, 22, 23]


def test_quality_round_trips_through_the_motion_file_and_the_exports(tmp_path):
    from embodmocap.io.amass import write_amass
    from embodmocap.export.csv_joints import write_joints_csv
    from embodmocap.io.smpl_file import read_smpl_quality, read_smpl_suspect, write_smpl_npz
    from embodmocap.types import SmplParams

    T = 5
    rng = np.random.default_rng(0)
    params = SmplParams(np.zeros(10), rng.normal(size=(T, 3)) * 0.1, rng.normal(size=(T, 69)) * 0.1,
                        rng.normal(size=(T, 3)), 30.0)
    suspect = np.array([True, False, False, True, False])
    quality = {"suspect": suspect, "limb_off_m": np.array([0.3, 0.01, np.nan, 0.2, 0.02]),
               "reproj_px": rng.random((T, 2)), "kp3d_err_m": rng.random(T), "quality_views": np.array(["v1", "v2"])}
    path = write_smpl_npz(tmp_path / "m.npz", params, valid=np.ones(T, bool), quality=quality)
    back = read_smpl_quality(path)
    for k, v in quality.items():
        np.testing.assert_array_equal(back[k], v)
    np.testing.assert_array_equal(read_smpl_suspect(path), suspect)
    old = write_smpl_npz(tmp_path / "old.npz", params)  # written without: none suspect, no keys
    assert read_smpl_quality(old) == {} and not read_smpl_suspect(old).any()
    with pytest.raises(ValueError, match="quality needs"):
        write_smpl_npz(tmp_path / "bad.npz", params, quality={"suspect": suspect})
    valid = np.array([False, True, True, True, True])
    with np.load(write_amass(tmp_path / "a.npz", params, flags=(valid, suspect))) as z:
        np.testing.assert_array_equal(z["valid"], valid)
        np.testing.assert_array_equal(z["suspect"], suspect)
    joints = rng.normal(size=(T, 24, 3))
    with open(write_joints_csv(tmp_path / "j.csv", joints, 30.0, flags=(valid, suspect)), newline="") as f:
        rows = list(csv.reader(f))
    assert rows[0][-2:] == ["valid", "suspect"] and len(rows[0]) == 2 + 72 + 2
    table = np.array(rows[1:], dtype=np.float64)
    np.testing.assert_array_equal(table[:, -2:], np.stack([valid, suspect], 1).astype(float))
    np.testing.assert_allclose(table[:, 2:-2].reshape(T, 24, 3), joints, atol=1e-6)


def test_edge_repair_carries_a_contradicted_limb_from_the_first_frame_that_fits():
    from embodmocap.motion.edge_repair import edge_stretches, repair_edges
    from embodmocap.types import SmplParams

    T = 20
    rng = np.random.default_rng(2)
    pose = rng.normal(scale=0.05, size=(T, 69))
    col = 3 * (18 - 1)  # the left elbow's first rotation value (SMPL joint 18)
    pose[:3, col] += 1.0  # the first three frames: the left arm bent far off
    pose[17:, col] -= 1.0  # and the last three
    pose[9, col] += 1.0  # and one frame in the middle (not an edge: left to the fit)
    params = SmplParams(np.zeros(10), np.zeros((T, 3)), pose, np.zeros((T, 3)), 30.0)
    ref = pose[:, col].copy()
    ref[:3], ref[17:], ref[9] = ref[3], ref[16], ref[9] - 1.0  # the truth: as the neighbours

    def offsets(p):  # the views see the left elbow and wrist where the truth puts them
        off = np.full((T, 17), 0.01)
        off[:, [7, 9]] = 0.3 * np.abs(p.body_pose[:, col] - ref)[:, None] + 0.01
        return off

    valid = np.ones(T, dtype=bool)
    out, n = repair_edges(params, valid, offsets, 0.1, 10)
    assert n == 6
    arm = np.concatenate([np.arange(3 * (j - 1), 3 * j) for j in (13, 16, 18, 20, 22)])  # collar to hand
    rest = np.setdiff1d(np.arange(69), arm)
    np.testing.assert_array_equal(out.body_pose[:3][:, arm], np.repeat(pose[3:4, arm], 3, 0))
    np.testing.assert_array_equal(out.body_pose[:3][:, rest], pose[:3, rest])
    np.testing.assert_array_equal(out.body_pose[17:, col], pose[16, col])
    np.testing.assert_array_equal(out.body_pose[3:17], pose[3:17])  # the middle is the fit's
    assert np.all(np.abs(offsets(out)[[0, 1, 2, 17, 18, 19]][:, 9]) < 0.1)
    # A carry that the views do not prefer is not kept; nothing fine within reach, nothing carried.
    worse = lambda p: offsets(params) + (np.abs(p.body_pose - pose).sum(1) > 0)[:, None]  # noqa: E731
    assert repair_edges(params, valid, worse, 0.1, 10) == (params, 0)
    assert edge_stretches(np.full(T, 0.5), valid, 0.1, 10) == []
    # Runs of placeable frames each have their own edges.
    valid[10] = False
    got = edge_stretches(np.where(np.isin(np.arange(T), [0, 11, 12, 19]), 0.5, 0.0), valid, 0.1, 10)
    assert got == [([0], 1), ([11, 12], 13), ([19], 18)]


def test_studio_edge_limb_trouble_touches_the_left_arm_of_the_first_frames_only():
    from embodmocap.errors import InputError
    from embodmocap.synth.config import SynthConfig
    from embodmocap.synth.perception import edge_limb_trouble

    rng = np.random.default_rng(0)
    kps = {v: np.concatenate([rng.uniform(100, 400, (30, 17, 2)), rng.uniform(0.7, 0.95, (30, 17, 1))], -1)
           for v in ("v1", "v2")}
    before = {v: k.copy() for v, k in kps.items()}
    first = {"v1": 4, "v2": 6}
    out = edge_limb_trouble(kps, first, 5, "mislabelled", np.random.default_rng(1))
    for v in kps:
        np.testing.assert_array_equal(kps[v], before[v])  # inputs unchanged
    changed = {v: np.flatnonzero((out[v] != kps[v]).any(-1).any(-1)).tolist() for v in kps}
    assert changed == {"v1": [4, 5, 6, 7, 8], "v2": [6, 7, 8, 9, 10]}
    np.testing.assert_array_equal(out["v1"][4:9][:, [7, 9, 8, 10]], kps["v1"][4:9][:, [8, 10, 7, 9]])
    conf = out["v2"][6:11][:, [7, 9], 2]
    assert np.all((conf >= 0.05) & (conf <= 0.3))
    np.testing.assert_array_equal(np.delete(out["v2"][6:11], [7, 9], axis=1), np.delete(kps["v2"][6:11], [7, 9], axis=1))
    occ = edge_limb_trouble(kps, first, 5, "occluded", np.random.default_rng(1))
    assert np.all(occ["v1"][4:9][:, [7, 9]] == 0.0) and np.all(occ["v1"][9:] == kps["v1"][9:])
    with pytest.raises(ValueError, match="edge limb mode"):
        edge_limb_trouble(kps, first, 5, "sideways", np.random.default_rng(1))
    with pytest.raises(InputError, match="edge_limb_frames"):
        SynthConfig(edge_limb_frames=-1)


def test_benchmark_tables_show_the_edges_per_session_with_median_and_worst():
    from embodmocap.evaluate.benchmark import tables_markdown

    base = {"w_mpjpe_mm": 30.0, "wa_mpjpe_mm": 15.0, "w_mpjpe_mm_c500": 40.0, "wa_mpjpe_mm_c500": 15.0,
            "w_mpjpe_mm_c1000": 40.0, "wa_mpjpe_mm_c1000": 15.0, "rte_pct": 0.3}
    rows = []
    for seed, first5 in ((0, 30.0), (1, 60.0)):
        dual = {**base, "w_mpjpe_mm_all_starts_median": 25.0 + seed, "w_mpjpe_mm_all_starts_worst": 90.0 + seed,
                "first5_frame_mm": first5, "last5_frame_mm": 20.0, "median_frame_mm": 20.0, "suspect_frames": 2,
                "wrong_frames": 3, "wrong_unflagged_pct": 0.5}
        rows.append({"seed": seed, "preset": "indoor", "perception": "hard",
                     "methods": {m: base for m in ("monocular", "single_v1", "single_v2")} | {"dual": dual}})
    md = tables_markdown(rows)
    assert "### Sequence edges, dual" in md
    assert "| indoor 1 hard | realistic | 26.00 | 91.00 | 60.00 |" in md
    assert "| median of 2 | realistic |" in md and md.split("| worst of 2 | realistic | ")[1].startswith("26.00 | 91.00 | 60.00")
    assert md.rstrip().endswith("| 3.00 |")  # the worst first5 / median ratio
    assert "Sequence edges" not in tables_markdown([{**rows[0], "methods": {m: base for m in rows[0]["methods"]}}])
