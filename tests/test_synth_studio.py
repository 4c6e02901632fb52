"""End to end: the studio writes a session that the readers, the manifest and inspect read back,
and whose ground truth agrees with what was written."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from embodmocap.geometry.transforms import apply_T, invert_T
from embodmocap.io.captures import open_capture
from embodmocap.check.inspect import inspect_path
from embodmocap.io.layout import VIEWS, SessionLayout
from embodmocap.io.manifest import load_manifest
from embodmocap.synth.config import SynthConfig
from embodmocap.synth.studio import synthesize

SMALL = dict(seconds=1.5, scene_seconds=2.0, width=160, height=120, depth_width=64, depth_height=48)


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth") / "s"
    synthesize(SynthConfig(seed=3, **SMALL), out)
    return out


def _digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def test_manifest_and_inspect_read_it_back(session):
    m = load_manifest(session / "session.toml")
    assert list(m.sequences["seq0"].views) == list(VIEWS)
    text, problems = inspect_path(session)
    assert problems == [], text


def test_poses_in_capture_match_ground_truth(session):
    lay = SessionLayout(session)
    gt = np.load(lay.ground_truth.sequence("seq0"))
    for v in VIEWS:
        cap = open_capture(lay.view_capture("seq0", v))
        T_vio_cam = gt[f"{v}_T_vio_cam"]
        assert cap.num_frames == len(T_vio_cam)
        np.testing.assert_allclose(cap.trajectory.T_world_cam, T_vio_cam, atol=1e-4)
        # VIO world differs from the scene frame by a yaw + offset, plus slow drift (small).
        T_scene_cam = gt[f"{v}_T_scene_cam"]
        est = gt[f"{v}_T_scene_vio"] @ T_vio_cam
        assert np.abs(est[:, :3, 3] - T_scene_cam[:, :3, 3]).max() < 0.05
        # Gravity: the scene frame's Z and the VIO world's Z agree (yaw-only offset).
        np.testing.assert_allclose(gt[f"{v}_T_scene_vio"][:3, 2], [0, 0, 1], atol=1e-9)


def test_laser_dot_disappears_at_the_sync_frame(session):
    lay = SessionLayout(session)
    gt = np.load(lay.ground_truth.sequence("seq0"))
    for v in VIEWS:
        cap = open_capture(lay.view_capture("seq0", v))
        s = int(gt[f"{v}_sync_frame"])
        assert 0 < s < cap.num_frames

        def red(i):
            rgb = cap.frames.rgb(i).astype(int)
            return int(((rgb[..., 0] > 200) & (rgb[..., 1] < 90) & (rgb[..., 2] < 90)).sum())

        assert red(s - 1) > 0, f"{v}: dot not visible just before the event"
        assert red(s) == 0, f"{v}: dot still visible at the event frame"


def test_keypoints_masks_and_prior_are_consistent(session):
    from embodmocap.io.body_prior import read_body_prior
    from embodmocap.io.openpose import read_keypoint_folder
    from embodmocap.types import PngMasks

    lay = SessionLayout(session)
    gt = np.load(lay.ground_truth.sequence("seq0"))
    for v in VIEWS:
        perc = lay.perception("seq0", v)
        n = len(gt[f"{v}_T_vio_cam"])
        kp, missing = read_keypoint_folder(perc.keypoints_dir, np.arange(n))
        assert kp.data.shape == (n, 17, 3)
        good = kp.conf > 0.5
        err = np.linalg.norm(kp.xy - gt[f"{v}_keypoints2d_gt"], axis=-1)[good]
        assert np.median(err) < 6.0
        masks = PngMasks(tuple(perc.mask_png(i) for i in range(n)))
        # Confident keypoints of the torso (shoulders, hips) mostly fall inside the person mask.
        inside = []
        for i in range(0, n, 5):
            m = masks.mask(i)
            for j in (5, 6, 11, 12):
                if kp.conf[i, j] > 0.5:
                    x, y = np.round(kp.xy[i, j]).astype(int)
                    if 0 <= x < m.shape[1] and 0 <= y < m.shape[0]:
                        inside.append(m[max(0, y - 2):y + 3, max(0, x - 2):x + 3].any())
        assert len(inside) > 0 and np.mean(inside) > 0.8
        prior = read_body_prior(perc.body_prior)
        assert len(prior.frame_ids) == n


def test_scene_capture_sees_the_ground_truth_mesh(session):
    import trimesh

    lay = SessionLayout(session)
    cap = open_capture(lay.scene_capture("scene0"))
    dev = np.load(lay.ground_truth.scene_device("scene0"))
    mesh = trimesh.load(lay.ground_truth.scene_mesh("scene0"), force="mesh")
    f = cap.frame(cap.num_frames // 2)
    K = cap.depth_intrinsics
    v, u = np.nonzero(f.depth_m > 0)
    sel = np.random.default_rng(0).choice(len(u), size=min(400, len(u)), replace=False)
    z = f.depth_m[v[sel], u[sel]]
    pc = np.stack([(u[sel] - K.cx) / K.fx * z, (v[sel] - K.cy) / K.fy * z, z], axis=1)
    # Depth is in the capture's VIO world; the true T_scene_vio takes it to the scene frame.
    T_scene_cam = dev["T_scene_vio"] @ f.T_world_cam
    pts = apply_T(T_scene_cam, pc)
    _, dist, _ = trimesh.proximity.closest_point(mesh, pts)
    # LiDAR noise is ~0.5 cm + 1 %, plus a little drift: the median stays within a few cm.
    assert np.median(dist) < 0.04


def test_same_seed_same_files(session, tmp_path):
    again = tmp_path / "again"
    synthesize(SynthConfig(seed=3, **SMALL), again)
    assert _digest(again) == _digest(session)


def test_another_take_shares_the_scene_capture(session, tmp_path):
    """A take > 0 of a seed films a new performance in the same room: the scene capture (and the
    scene's ground truth) is the same file for file, the views are not."""
    other = tmp_path / "take1"
    synthesize(SynthConfig(seed=3, take=1, **SMALL), other)
    a, b = _digest(session), _digest(other)
    scene = [k for k in a if k.startswith("captures/scene0/") or k.startswith("ground_truth/scene_")]
    assert scene and all(b[k] == a[k] for k in scene)
    views = [k for k in a if k.startswith("captures/seq0/")]
    assert any(b.get(k) != a[k] for k in views)
    gt_a, gt_b = (np.load(SessionLayout(r).ground_truth.sequence("seq0")) for r in (session, other))
    assert not np.allclose(gt_a["v1_T_scene_cam"][0], gt_b["v1_T_scene_cam"][0])


def test_spectacular_format_session_reads_back(tmp_path):
    out = tmp_path / "sai"
    synthesize(SynthConfig(seed=5, format="spectacular", **SMALL), out)
    lay = SessionLayout(out)
    gt = np.load(lay.ground_truth.sequence("seq0"))
    for v in VIEWS:
        cap = open_capture(lay.view_capture("seq0", v))
        assert cap.format == "spectacular"
        np.testing.assert_allclose(cap.trajectory.T_world_cam, gt[f"{v}_T_vio_cam"], atol=1e-4)
        d = cap.frames.depth_m(0)
        assert d.shape == (SMALL["depth_height"], SMALL["depth_width"]) and (d > 0).mean() > 0.5
    text, problems = inspect_path(out)
    assert problems == [], text
