"""One-phone sessions (issue 28, part 2): a sequence filmed by one iPhone runs every stage.

Fast tests of the pieces (the manifest, the performer in one view, the lift of one view's keypoints
with its depth against known joint centres); one slow end-to-end test: a synthetic one-phone
studio session through Stages I-IV, checked against its ground truth and for the one-view flags
in every output.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from embodmocap.geometry.keypoint_depth import JOINT_DEPTH_BEHIND_SURFACE_M
from embodmocap.io.manifest import ManifestError, load_manifest
from embodmocap.motion.lift import LiftConfig, lift_keypoints, person_depth

ONE_VIEW = """\
version = 1
[scenes.room]
capture = "captures/room"
[sequences.seq0]
scene = "room"
[sequences.seq0.views.{view}]
capture = "captures/seq0/{view}"
"""


def _manifest(tmp_path: Path, view: str) -> Path:
    for folder in ("captures/room", f"captures/seq0/{view}"):
        (tmp_path / folder).mkdir(parents=True, exist_ok=True)
    (tmp_path / "session.toml").write_text(ONE_VIEW.format(view=view))
    return tmp_path / "session.toml"


def test_a_sequence_may_have_one_view_named_v1(tmp_path):
    entry = load_manifest(_manifest(tmp_path, "v1")).sequence("seq0")
    assert entry.view_names == ("v1",) and entry.one_view
    with pytest.raises(ManifestError) as info:
        load_manifest(_manifest(tmp_path / "other", "v2"))
    assert any("v1 alone (one phone)" in p for p in info.value.problems)


def test_the_performer_is_found_in_one_view():
    from embodmocap.sequence.solve import solve_performer

    def person(x: float, conf: float = 0.9) -> np.ndarray:
        kp = np.zeros((17, 3))
        kp[:, 0], kp[:, 1], kp[:, 2] = x + np.arange(17), 100 + 5 * np.arange(17), conf
        return kp

    # The performer (large, centred, every frame) and a bystander in the first frames.
    people = [np.stack([person(150 + t)] + ([person(10, 0.5)] if t < 4 else [])) for t in range(10)]
    found = solve_performer({"v1": people}, {"v1": (320, 240)}, {"v1": 10.0})
    assert list(found) == ["v1"] and found["v1"].seen.all()
    np.testing.assert_allclose(found["v1"].keypoints[2], person(152))


def _scene(T: int = 3, z=None):
    """Joint centres of T frames in front of a camera, the depth map a LiDAR would see of them
    (each joint's surface a patch at its depth minus its half thickness) and the person mask;
    z: (T, 17) the joints' z-depths (default: random around 2.5 m)."""
    rng = np.random.default_rng(0)
    W, H, w, h = 128, 96, 64, 48  # RGB and depth sizes (depth at half resolution)
    K = np.array([[100.0, 0, 63.5], [0, 100.0, 47.5], [0, 0, 1]])
    # Depth pixel (row, col) centre <-> RGB pixel 2 col + 0.5: each joint on a depth pixel centre.
    cols, rows = np.meshgrid(np.arange(6, 60, 12), np.arange(6, 44, 10))
    cols, rows = cols.ravel()[:17], rows.ravel()[:17]
    xy = np.stack([2 * cols + 0.5, 2 * rows + 0.5], -1)
    z = 2.5 + rng.uniform(-0.3, 0.3, (T, 17)) if z is None else np.asarray(z, dtype=np.float64)
    ray = np.stack([(xy[:, 0] - K[0, 2]) / K[0, 0], (xy[:, 1] - K[1, 2]) / K[1, 1], np.ones(17)], -1)
    p_cam = ray[None] * z[..., None]
    behind = np.asarray(JOINT_DEPTH_BEHIND_SURFACE_M)
    surface = z - behind / np.linalg.norm(ray, axis=-1)  # the ray enters the body this much earlier
    depth = np.full((T, h, w), 4.0)  # the wall behind
    mask = np.zeros((T, H, W), dtype=bool)
    for t in range(T):
        for j in range(17):
            depth[t, rows[j] - 2:rows[j] + 3, cols[j] - 2:cols[j] + 3] = surface[t, j]
            mask[t, 2 * rows[j] - 5:2 * rows[j] + 6, 2 * cols[j] - 5:2 * cols[j] + 6] = True
    # A camera turned and moved in the world.
    c, s = np.cos(0.7), np.sin(0.7)
    T_wc = np.tile(np.array([[c, -s, 0, 1.0], [s, c, 0, -2.0], [0, 0, 1, 1.2], [0, 0, 0, 1]]), (T, 1, 1))
    world = np.einsum("tij,tkj->tki", T_wc[:, :3, :3], p_cam) + T_wc[:, None, :3, 3]
    kp = np.concatenate([np.broadcast_to(xy, (T, 17, 2)), np.full((T, 17, 1), 0.9)], -1)
    return kp, K, T_wc, depth, mask, world, (W, H)


def test_lifted_keypoints_are_the_joint_centres():
    kp, K, T_wc, depth, mask, world, size = _scene()
    depth_at = person_depth(lambda t: depth[t], lambda t: mask[t], erode_px=1)
    got = lift_keypoints(kp, K, T_wc, depth_at, size)
    np.testing.assert_allclose(got.points, world, atol=1e-9)
    assert got.depth_found.all() and not got.filled.any() and not got.dropped_far.any()
    np.testing.assert_allclose(got.conf, 0.9)


def test_a_keypoint_off_the_person_or_far_from_the_body_is_not_lifted():
    kp, K, T_wc, depth, mask, world, size = _scene()
    r, c = int((kp[1, 9, 1] - 0.5) / 2), int((kp[1, 9, 0] - 0.5) / 2)
    depth[1, r - 2:r + 3, c - 2:c + 3] = 3.9  # frame 1, left wrist: an occluder's depth 1.4 m behind the torso
    x, y = kp[1, 0, :2].astype(int)
    r0, c0 = int((y - 0.5) / 2), int((x - 0.5) / 2)
    mask[1, y - 8:y + 9, x - 8:x + 9] = False  # frame 1, nose: outside the person mask (the wall there)
    depth[1, r0 - 4:r0 + 5, c0 - 4:c0 + 5] = 4.0
    depth_at = person_depth(lambda t: depth[t], lambda t: mask[t], erode_px=1)
    got = lift_keypoints(kp, K, T_wc, depth_at, size, LiftConfig(max_from_body_m=0.8), max_gap_frames=0)
    assert got.dropped_far[1, 9] and not got.depth_found[1, 0]
    assert np.isnan(got.points[1, [0, 9]]).all() and (got.conf[1, [0, 9]] == 0).all()
    others = np.ones((3, 17), bool)
    others[1, [0, 9]] = False
    np.testing.assert_allclose(got.points[others], world[others], atol=1e-9)
    # Without the mask the nose reads the wall (4 m): still dropped, as far from the body.
    got = lift_keypoints(kp, K, T_wc, lambda t: depth[t], size, max_gap_frames=0)
    assert got.dropped_far[1, 0]
    # A one-frame gap is interpolated (and flagged) as the triangulation's gaps are.
    got = lift_keypoints(kp, K, T_wc, depth_at, size, max_gap_frames=1)
    assert got.filled[1, 9] and np.isfinite(got.points[1, 9]).all()


def test_an_unsure_keypoint_that_reads_an_occluder_is_put_behind_it():
    # A still body 2.5 m away (so its bones keep their lengths); in frame 4 something 0.5 m in front
    # of the left wrist hides it: its pixel shows the occluder's depth and the detector is unsure.
    # This grid's forearm is 1.2 m long and seen from the side, so 0.5 m of depth changes its length
    # by 9%: the tolerance is set below that (a real forearm, 0.25 m, changes far more).
    T, t, j = 8, 4, 9
    kp, K, T_wc, depth, mask, world, size = _scene(T, np.full((T, 17), 2.5))
    r, c = int((kp[t, j, 1] - 0.5) / 2), int((kp[t, j, 0] - 0.5) / 2)
    depth[t, r - 2:r + 3, c - 2:c + 3] -= 0.5
    kp[t, j, 2] = 0.4
    depth_at = person_depth(lambda i: depth[i], lambda i: mask[i], erode_px=1)
    cfg = LiftConfig(bone_tol=0.05)
    old = lift_keypoints(kp, K, T_wc, depth_at, size, replace(cfg, behind_occluder=False), max_gap_frames=0)
    new = lift_keypoints(kp, K, T_wc, depth_at, size, cfg, max_gap_frames=0)
    # Taken as an equality the depth puts the wrist on the occluder, 0.5 m (along z) in front of it;
    # as a lower bound with the forearm's length (measured on the trusted frames) it is behind it.
    err_old = np.linalg.norm(old.points[t, j] - world[t, j])
    err_new = np.linalg.norm(new.points[t, j] - world[t, j])
    assert err_old > 0.4 and err_new < 1e-6, (err_old, err_new)
    # The points the depth saw are unchanged, and a confident keypoint's depth is trusted as it is.
    others = np.ones((T, 17), bool)
    others[t, j] = False
    np.testing.assert_allclose(new.points[others], world[others], atol=1e-9)
    kp[t, j, 2] = 0.9
    sure = lift_keypoints(kp, K, T_wc, depth_at, size, cfg, max_gap_frames=0)
    np.testing.assert_allclose(sure.points[t, j], old.points[t, j], atol=1e-12)


def _side_on_body(T: int):
    """A body 3 m from one camera, turned 50 degrees from it (one arm nearer the camera than the
    other), arms held out and swinging, and what the phone records of it: per frame the LiDAR depth
    (the body's vertices splatted with a z-buffer at half the RGB size) and the person mask;
    (COCO-17 points (T, 17, 3), K, T_world_cam (T, 4, 4), depth (T, h, w) m, masks (T, H, W), (W, H))."""
    import torch
    from scipy.spatial.transform import Rotation

    from embodmocap.body.model import load_body_model
    from embodmocap.geometry.transforms import R_ZUP_YUP, look_at_T

    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    W, H, w, h = 640, 480, 320, 240
    phase = np.linspace(0, 2 * np.pi, T)
    pose = np.zeros((T, 69))
    pose[:, 15 * 3 + 2], pose[:, 16 * 3 + 2] = -0.7, 0.7  # shoulders: arms out
    pose[:, 15 * 3 + 1] = pose[:, 16 * 3 + 1] = -0.4 * np.sin(phase)  # swinging
    go = np.tile(Rotation.from_matrix(R_ZUP_YUP).as_rotvec(), (T, 1))
    transl = np.column_stack([np.linspace(0, 0.3, T), np.zeros(T), np.full(T, 0.9)])
    with torch.no_grad():
        out = load_body_model(None).forward(np.zeros(10), go, pose, transl, dtype=torch.float64)
    verts, coco = out.vertices.numpy(), out.coco17.numpy()
    facing = np.cross(coco[0, 5] - coco[0, 6], [0.0, 0.0, 1.0])
    facing /= np.linalg.norm(facing)
    a = np.radians(50.0)
    turn = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    centre = coco[0, [5, 6, 11, 12]].mean(0)
    T_wc = np.repeat(look_at_T(centre + 3.0 * turn @ facing + [0, 0, 0.2], centre)[None], T, 0)
    depth, masks = np.zeros((T, h, w)), np.zeros((T, H, W), dtype=bool)
    for t in range(T):
        cam = (verts[t] - T_wc[t, :3, 3]) @ T_wc[t, :3, :3]
        u, v = K[0, 0] * cam[:, 0] / cam[:, 2] + K[0, 2], K[1, 1] * cam[:, 1] / cam[:, 2] + K[1, 2]
        d = np.full((h, w), np.inf)
        x, y = np.floor(u * w / W).astype(int), np.floor(v * h / H).astype(int)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                np.minimum.at(d, (np.clip(y + dy, 0, h - 1), np.clip(x + dx, 0, w - 1)), cam[:, 2])
        depth[t] = np.where(np.isfinite(d), d, 0.0)
        for dy in range(-2, 3):
            for dx in range(-2, 3):
                masks[t, np.clip(np.floor(v).astype(int) + dy, 0, H - 1), np.clip(np.floor(u).astype(int) + dx, 0, W - 1)] = True
    return coco, K, T_wc, depth, masks, (W, H)


def test_one_views_arm_labels_take_the_side_its_depth_puts_them_on():
    """Issue 28 (hard studio seed 3, one phone): the detector had the arms exchanged in the first
    frames and right after; one view's trajectories cannot say which side of that jump was right,
    and the label chain kept the longer run's labels, exchanging the right ones (the fitted arms
    30-40 cm off, W-MPJPE c100 145 mm against 60 for two phones). The view's depth can: each
    elbow and wrist lifted with it lies nearer its own shoulder than the other's."""
    from embodmocap.motion.config import MotionConfig
    from embodmocap.motion.label_track import TRACKED_GROUPS
    from embodmocap.motion.solve import lift_view

    T = 24
    coco, K, T_wc, depth, masks, size = _side_on_body(T)
    cam = np.einsum("tab,tjb->tja", np.swapaxes(T_wc[:, :3, :3], 1, 2), coco - T_wc[:, None, :3, 3])
    uv = np.einsum("ab,tjb->tja", K, cam)
    kp = np.concatenate([uv[..., :2] / uv[..., 2:], np.full((T, 17, 1), 0.9)], -1)
    bad = kp.copy()
    for a, b in TRACKED_GROUPS["arms"]:  # exchanged in frames 0-13, right in 14-23
        bad[:14, a], bad[:14, b] = kp[:14, b], kp[:14, a]
    depth_at = person_depth(lambda t: depth[t], lambda t: masks[t], erode_px=1)
    cams = {"v1": {"K": K, "T_world_cam": T_wc}}

    def wrong(cfg):
        tri = lift_view(cfg, cams, {"v1": bad}, T, depth_at, size)
        got = tri.file.keypoints2d[:, 0]
        return np.flatnonzero((np.linalg.norm(got[:, 7:11, :2] - kp[:, 7:11, :2], axis=-1) > 5).any(-1)), tri

    cfg = MotionConfig()
    fixed, tri = wrong(cfg)
    assert len(fixed) == 0, fixed
    lifted = np.linalg.norm(tri.file.points[:, 7:11] - coco[:, 7:11], axis=-1)
    assert np.nanmedian(lifted) < 0.02  # the arms lifted where they are
    # By the trajectories alone the chain keeps the longer run: every frame's arms the wrong way round.
    plain, _ = wrong(replace(cfg, label_track=replace(cfg.label_track, depth_side_m=0.0)))
    assert len(plain) == T


# ------------------------------------------------------------------------------ end to end


@pytest.mark.slow
def test_a_one_phone_session_runs_every_stage(tmp_path):
    from embodmocap.check.config import CheckConfig
    from embodmocap.check.core import check_session
    from embodmocap.evaluate.session import evaluate_session
    from embodmocap.io.layout import SessionLayout
    from embodmocap.io.smpl_file import read_smpl_one_view
    from embodmocap.io.stage_files import read_keypoints3d
    from embodmocap.pipeline import PipelineConfig, run_session
    from embodmocap.synth.config import SynthConfig
    from embodmocap.synth.studio import synthesize

    cfg = SynthConfig(seed=1, views=1, seconds=3.0, scene_seconds=15.0, body_prior="none")
    synthesize(cfg, tmp_path / "s")
    lay = SessionLayout(tmp_path / "s")
    assert not lay.view_capture(cfg.sequence_name, "v2").exists()
    res = run_session(PipelineConfig(), lay.root)
    assert res.ok, res.failed()
    sl = lay.sequence(cfg.sequence_name)
    assert sl.views() == ("v1",)
    # Every output says it came from one view.
    sync = json.loads(sl.sync.read_text())
    assert sync["one_view"] and sync["chosen"]["source"] == "one_view" and sync["chosen"]["final"]
    assert json.loads(sl.calibration.read_text())["one_view"]
    assert bool(read_keypoints3d(sl.keypoints3d)["one_view"])
    assert read_smpl_one_view(sl.smpl_world) and read_smpl_one_view(sl.smpl_fit)
    for m in (sl.manifest, sl.calibrate_manifest, sl.motion_manifest):
        assert json.loads(m.read_text())["figures"]["one_view"] is True, m
    # Against the truth: the motion is placed in the scene within a one-phone error.
    ev = evaluate_session(lay.root)["sequences"][cfg.sequence_name]
    assert ev["one_view"] and ev["invalid_frames"] <= 5
    # This 3 s take's W-MPJPE is mostly one whole-body offset (WA-MPJPE about 31 mm, PA-MPJPE about
    # 27 mm); it measured 145 mm before the lower-bound depth rule of the lift and 162 mm with it
    # (WA and PA a little better), so the pose is held to the tighter bound. Reaching the hidden
    # right limbs' unsure end points at the start (ik.reach_end without the one-view confidence
    # gate, MotionConfig.reach_min_conf_one_view) made it 194 mm; with the gate 161 mm.
    assert ev["w_mpjpe_mm"] < 180.0 and ev["v1_view_translation_err_cm"] < 10.0, ev
    assert ev["pa_mpjpe_mm"] < 40.0 and ev["wa_mpjpe_mm"] < 45.0, ev
    # The benchmark's single-view row is this path: the same fit from the same files.
    from embodmocap.body.model import load_body_model
    from embodmocap.evaluate.benchmark import _Context
    from embodmocap.io.smpl_file import read_smpl_npz

    ctx = _Context(lay, cfg.sequence_name, cfg.scene_name, load_body_model(lay.body_model))
    params = ctx.fit(single_view="v1", cameras={"v1": ctx.cameras("v1")}, prior=False)
    fitted, _ = read_smpl_npz(sl.smpl_fit)
    np.testing.assert_allclose(params.poses, fitted.poses, atol=1e-6)
    np.testing.assert_allclose(params.transl, fitted.transl, atol=1e-6)
    # `check` says what one view cannot give, without calling the take unusable for it.
    (chk,) = check_session(CheckConfig(), lay.root)
    assert chk.figures["one_view"] and any("no triangulation" in n for n in chk.notes)
    assert chk.verdict != "reshoot", chk.reasons
