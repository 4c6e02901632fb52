"""The scripted performer: feet on the floor, seated on the seat, no teleports, reproducible."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from embodmocap.body.model import load_body_model
from embodmocap.body.vertex_sets import foot_vertex_ids
from embodmocap.synth.motion import MotionScriptConfig, _in_footprint, foot_contact_frames, script_motion
from embodmocap.synth.motion_body import hand_vertex_ids
from embodmocap.synth.scene import build_scene

FPS = 30.0
BETAS = np.array([0.5, -0.3, 0.2, 0.0, 0.1, 0, 0, 0, 0, 0])


@pytest.fixture(scope="module")
def body():
    return load_body_model(None)


@pytest.fixture(scope="module", params=[0, 1])
def run(request, body):
    """A 60 s script in a generated room, skinned."""
    spec = build_scene("indoor", np.random.default_rng(request.param)).spec
    script = script_motion(spec, body, BETAS, 60.0, FPS, np.random.default_rng(request.param), MotionScriptConfig())
    out = body.from_params(script.params)
    v = out.vertices.numpy().astype(np.float64)
    j = out.joints.numpy().astype(np.float64)
    return spec, script, v, j


def test_segments_cover_the_clip_and_start_idle(run):
    spec, script, v, j = run
    segs = script.segments
    assert len(script.params) == 1800
    assert segs[0][0] == "idle" and 1.0 <= (segs[0][2] - segs[0][1]) / FPS <= 2.0
    assert segs[0][1] == 0 and segs[-1][2] == 1800
    assert all(a[2] == b[1] for a, b in zip(segs, segs[1:]))
    names = {s[0] for s in segs}
    # 60 s does every interaction.
    assert {"walk", "sit", "stand_up", "step_up", "stand_on_box", "step_down", "lean_table"} <= names
    assert sum(n == "sit" for n, _, _ in segs) == 2  # chair and sofa/bed


def test_feet_on_the_floor_and_on_the_box(run, body):
    spec, script, v, j = run
    assert v[..., 2].min() >= -0.01  # never below the floor
    gap, contact = foot_contact_frames(spec, v, foot_vertex_ids(body, BETAS))
    # Furniture holds the body up only in its interactions; elsewhere the floor is the support.
    feet = foot_vertex_ids(body, BETAS)
    floor_gap = np.stack([v[:, ids, 2].min(axis=1) for ids in feet], axis=1)
    on_floor = script.frames_of("idle", "walk", "lean_table")
    assert np.all(floor_gap[on_floor].min(axis=1) <= 0.02), "a walking/standing frame has both feet in the air"
    assert np.all(floor_gap[on_floor] >= -0.01)
    on_box = script.frames_of("stand_on_box")
    assert np.all(gap[on_box].min(axis=1) <= 0.02) and np.all(gap[on_box] >= -0.01)
    box = spec.furniture["box"]
    both = np.concatenate(feet)
    assert np.all(np.abs(v[on_box][:, both, 2].min(axis=1) - box.top_z) < 0.02)


def test_sitting_rests_on_the_seat(run):
    spec, script, v, j = run
    for name, s, e in script.segments:
        if name != "sit":
            continue
        pelvis = j[s:e, 0]
        seat = next(f for f in spec.furniture.values()
                    if f.name in ("chair", "sofa", "bed") and _in_footprint(f, pelvis[:1, :2])[0])
        above = pelvis[:, 2] - seat.top_z
        # Pelvis joint above the seat by about the thickness of buttocks/thighs.
        assert np.all((above > 0.05) & (above < 0.25)), above
        over = _in_footprint(seat, v[s:e, :, :2]) & (v[s:e, :, 2] > seat.top_z - 0.2)
        lowest = np.where(over, v[s:e, :, 2], np.inf).min(axis=1)
        assert np.all(np.abs(lowest - seat.top_z) < 0.01)  # resting on the seat, not hovering


def test_hands_on_the_table(run):
    spec, script, v, j = run
    table = spec.furniture["table"]
    hold = script.frames_of("lean_table")
    wrists = j[hold][:, 20:22]
    assert len(wrists)
    assert np.all(_in_footprint(table, wrists[..., :2]))
    # The hands (not the wrists: the fingers hang below them) rest on the top.
    low = v[hold][:, hand_vertex_ids(load_body_model(None)), 2].min(axis=1) - table.top_z
    assert np.all((low > -0.005) & (low < 0.01))


def test_no_teleport_and_bounded_joint_speed(run):
    spec, script, v, j = run
    speed = np.linalg.norm(np.diff(j[:, 0], axis=0), axis=1) * FPS
    assert speed.max() < 3.0
    walk = script.frames_of("walk")
    assert 0.9 < np.percentile(speed[walk[walk < len(speed)]], 90) < 1.4  # ~1.15 m/s cruising
    p = script.params
    rots = Rotation.from_rotvec(np.concatenate([p.global_orient[:, None], p.body_pose.reshape(-1, 23, 3)], 1).reshape(-1, 3))
    R = rots.as_matrix().reshape(len(p), 24, 3, 3)
    rel = np.einsum("tjki,tjkl->tjil", R[:-1], R[1:])
    ang = np.arccos(np.clip((np.trace(rel, axis1=-2, axis2=-1) - 1) / 2, -1, 1)) * FPS
    assert ang.max() < 10.0  # rad/s (a fast knee swing): no joint snaps


def test_stays_in_the_room(run):
    spec, script, v, j = run
    lo, hi = np.asarray(spec.floor_min_xy), np.asarray(spec.floor_max_xy)
    assert np.all(v[..., :2] > lo - 0.02) and np.all(v[..., :2] < hi + 0.02)
    # Wandering happens inside the walk area (legs to and from furniture leave it briefly).
    walk_lo, walk_hi = np.asarray(spec.walk_area_min_xy), np.asarray(spec.walk_area_max_xy)
    inside = np.all((j[:, 0, :2] > walk_lo - 0.05) & (j[:, 0, :2] < walk_hi + 0.05), axis=1)
    assert inside[script.frames_of("walk")].mean() > 0.6


def test_same_seed_same_motion(body):
    spec = build_scene("indoor", np.random.default_rng(5)).spec
    a = script_motion(spec, body, BETAS, 6.0, FPS, np.random.default_rng(9))
    b = script_motion(spec, body, BETAS, 6.0, FPS, np.random.default_rng(9))
    c = script_motion(spec, body, BETAS, 6.0, FPS, np.random.default_rng(10))
    for name in ("global_orient", "body_pose", "transl"):
        np.testing.assert_array_equal(getattr(a.params, name), getattr(b.params, name))
    assert a.segments == b.segments
    assert not np.allclose(a.params.transl, c.params.transl)


@pytest.mark.parametrize("seconds", [10.0, 2.7])
def test_short_clips(body, seconds):
    spec = build_scene("outdoor", np.random.default_rng(2)).spec
    s = script_motion(spec, body, BETAS, seconds, FPS, np.random.default_rng(2))
    assert len(s.params) == round(seconds * FPS)
    names = [n for n, _, _ in s.segments]
    assert names[0] == "idle" and "walk" in names
    if seconds >= 10:  # a walk and at least one complete interaction
        ends = {"stand_up", "step_down", "lean_out"}
        assert any(n in ends and e < len(s.params) for n, _, e in s.segments), s.segments
    out = body.from_params(s.params)
    assert out.vertices[..., 2].min() >= -0.01
