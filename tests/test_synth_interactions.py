"""The studio scripts all six skill interactions (follow, sit, climb, lie, prone, support) with
their clips known: lying rests the whole body on the bed without sinking into it, on the back or
the front; the follow path is walked without stopping inside the walk area; nothing snaps."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from embodmocap.body.model import load_body_model
from embodmocap.synth.motion import _in_footprint
from skills_truth import FPS, bed_seeds, scripted


@pytest.fixture(scope="module")
def run():
    body = load_body_model(None)
    built, script = scripted(body, bed_seeds(1, start=3)[0])
    out = body.from_params(script.params)
    return built.spec, script, out.vertices.numpy().astype(np.float64), out.joints.numpy().astype(np.float64)


def clip(script, skill):
    return next(c for c in script.clips if c.skill == skill)


def test_all_six_scripted_with_consistent_clips(run):
    spec, script, v, j = run
    skills = [c.skill for c in script.clips]
    assert set(skills) == {"follow", "sit", "climb", "lie", "prone", "support"}
    T = len(script.params)
    for c in script.clips:
        assert 0 <= c.start < c.end <= T
        if c.skill != "follow":
            assert c.start < c.contact_start < c.contact_end < c.end and c.furniture in spec.furniture
    # Clips do not overlap; their holds are the segments of the same name.
    order = sorted(script.clips, key=lambda c: c.start)
    assert all(a.end <= b.start for a, b in zip(order, order[1:]))
    hold = {"sit": "sit", "lie": "lie", "prone": "prone", "support": "lean_table"}
    for skill, seg in hold.items():
        c = clip(script, skill)
        assert (seg, c.contact_start, c.contact_end) in script.segments
    assert {"lie_down", "prone_down", "get_up", "follow"} <= {n for n, _, _ in script.segments}


@pytest.mark.parametrize("skill", ["lie", "prone"])
def test_lying_rests_on_the_bed_without_penetrating(run, skill):
    spec, script, v, j = run
    bed = spec.furniture["bed"]
    c = clip(script, skill)
    vv = v[c.start:c.end]
    over = _in_footprint(bed, vv[..., :2])
    lowest = np.where(over, vv[..., 2], np.inf).min(axis=1)
    assert np.all(lowest[np.isfinite(lowest)] >= bed.top_z - 0.01)  # never more than 1 cm into the top
    h = slice(c.contact_start - c.start, c.contact_end - c.start)
    assert np.all(np.abs(lowest[h] - bed.top_z) < 0.01)  # resting on it, not hovering
    # The whole body is on the bed while lying: every vertex over its footprint, the torso flat.
    assert over[h].mean() > 0.9  # the feet may overhang the foot end
    axis = j[c.contact_start:c.contact_end, 12] - j[c.contact_start:c.contact_end, 0]
    assert np.all(np.abs(axis[:, 2]) / np.linalg.norm(axis, axis=1) < 0.25)
    # Lying along the bed with the head toward the headboard (local -y), clear of it.
    fwd = np.array([np.cos(bed.yaw), np.sin(bed.yaw)])
    side = np.array([-fwd[1], fwd[0]])
    head_y = (j[c.contact_start:c.contact_end, 15, :2] - bed.centre_xy) @ side
    pelvis_y = (j[c.contact_start:c.contact_end, 0, :2] - bed.centre_xy) @ side
    assert np.all(head_y < pelvis_y - 0.3)
    local_y = (vv[..., :2] - bed.centre_xy) @ side
    assert local_y.min() > -bed.size[1] / 2 + 0.08 + 0.02
    # Back down (supine: the body's front faces up) or front down.
    R = Rotation.from_rotvec(np.array(script.params.global_orient[c.contact_start:c.contact_end])).as_matrix()
    front_z = R[:, :, 2] @ np.array([0.0, 0.0, 1.0])  # SMPL's canonical front is +Z
    assert np.all(front_z > 0.9) if skill == "lie" else np.all(front_z < -0.9)


def test_follow_walks_a_curved_path_without_stopping(run):
    spec, script, v, j = run
    s, e = next((s, e) for n, s, e in script.segments if n == "follow")
    xy = j[s:e, 0, :2]
    lo, hi = np.asarray(spec.walk_area_min_xy), np.asarray(spec.walk_area_max_xy)
    assert np.all((xy > lo - 0.05) & (xy < hi + 0.05))
    speed = np.linalg.norm(np.gradient(xy, axis=0), axis=1) * FPS
    n = e - s
    assert speed[int(0.2 * n):int(0.8 * n)].min() > 0.5
    vel = np.gradient(xy, axis=0)
    heading = np.arctan2(vel[:, 1], vel[:, 0])
    turned = np.abs(np.unwrap(heading)[-1] - np.unwrap(heading)[0])
    assert turned > np.deg2rad(30)  # a path, not a straight line


def test_support_keeps_the_feet_together_and_hands_on_the_table(run):
    spec, script, v, j = run
    c = clip(script, "support")
    table = spec.furniture["table"]
    h = slice(c.contact_start, c.contact_end)
    assert np.all(_in_footprint(table, j[h, 20:22, :2]))
    assert np.all(np.linalg.norm(j[h, 7, :2] - j[h, 8, :2], axis=1) < 0.4)


def test_nothing_snaps(run):
    spec, script, v, j = run
    assert v[..., 2].min() >= -0.01
    speed = np.linalg.norm(np.diff(j[:, 0], axis=0), axis=1) * FPS
    assert speed.max() < 3.0
    p = script.params
    R = Rotation.from_rotvec(np.concatenate([np.array(p.global_orient)[:, None], p.body_pose.reshape(-1, 23, 3)], 1)
                             .reshape(-1, 3)).as_matrix().reshape(len(p), 24, 3, 3)
    rel = np.einsum("tjki,tjkl->tjil", R[:-1], R[1:])
    ang = np.arccos(np.clip((np.trace(rel, axis1=-2, axis2=-1) - 1) / 2, -1, 1)) * FPS
    assert ang.max() < 10.0
