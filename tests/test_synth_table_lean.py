"""The studio's ground truth is physically clean: leaning on the table puts the hands ON its top
(not inside it), and no scripted interaction pushes the body into the furniture.

Geometry only: the skinned truth against the furniture's solid parts as the studio builds them
(:func:`embodmocap.synth.scene._piece_parts`, the same boxes its scene mesh is made of)."""

from __future__ import annotations

import numpy as np
import pytest

from embodmocap.body.model import load_body_model
from embodmocap.synth.motion import MotionScriptConfig, _in_footprint, script_motion
from embodmocap.synth.motion_body import LEAN_HAND_GAP_M, hand_vertex_ids
from embodmocap.synth.scene import _piece_parts, build_scene

FPS = 30.0


@pytest.fixture(scope="module")
def body():
    return load_body_model(None)


def _betas(body, seed: int) -> np.ndarray:
    """The studio's shape draw (synth/studio.py) for this seed."""
    b = np.zeros(body.num_betas)
    b[:4] = np.random.default_rng([seed, 2]).normal(0.0, [0.8, 0.6, 0.5, 0.5])
    return b


def furniture_penetration(spec, points: np.ndarray) -> np.ndarray:
    """(...,) how deep each point (..., 3) is inside any solid part of any piece of furniture,
    metres (0 outside): the distance to the nearest face of the box it is in."""
    p = np.asarray(points, dtype=np.float64)
    depth = np.zeros(p.shape[:-1])
    for f in spec.furniture.values():
        d = p[..., :2] - np.asarray(f.centre_xy)
        c, s = np.cos(f.yaw), np.sin(f.yaw)
        local = np.stack([d[..., 0] * c + d[..., 1] * s, -d[..., 0] * s + d[..., 1] * c, p[..., 2]], axis=-1)
        for centre, size, _ in _piece_parts(f.name, np.asarray(f.size), f.top_z, "indoor"):
            inside = (np.asarray(size) / 2 - np.abs(local - np.asarray(centre))).min(axis=-1)
            depth = np.maximum(depth, inside)
    return depth


def test_penetration_helper_on_a_known_point():
    spec = build_scene("indoor", np.random.default_rng(0)).spec
    t = spec.furniture["table"]
    centre = np.array([*t.centre_xy, t.top_z])
    assert furniture_penetration(spec, centre - [0, 0, 0.005]) == pytest.approx(0.005, abs=1e-9)
    assert furniture_penetration(spec, centre + [0, 0, 0.005]) == 0.0


@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4, 5])
def test_table_lean_hands_rest_on_the_top(body, seed):
    spec = build_scene("indoor", np.random.default_rng([seed, 1])).spec
    betas = _betas(body, seed)
    script = script_motion(spec, body, betas, 12.0, FPS, np.random.default_rng([seed, 3]),
                           MotionScriptConfig(interactions=("table",)))
    lean = script.frames_of("lean_in", "lean_table", "lean_out")
    hold = script.frames_of("lean_table")
    assert len(hold) > 10
    out = body.from_params(script.params)
    v = out.vertices.numpy().astype(np.float64)
    # Nothing inside the table (or any furniture) while leaning in, on and out.
    assert furniture_penetration(spec, v[lean]).max() < 0.01
    # Held: each hand's lowest point on the top (touching: within 1 cm above it), over the top.
    table = spec.furniture["table"]
    ids = hand_vertex_ids(body)
    owner = np.asarray(body.lbs_weights)[ids].argmax(axis=1)
    left, right = ids[np.isin(owner, (20, 22))], ids[np.isin(owner, (21, 23))]  # SMPL wrist, hand
    for side in (left, right):
        hv = v[hold][:, side]
        low = hv[..., 2].min(axis=1)
        assert np.all(low - table.top_z > -0.005) and np.all(low - table.top_z < 0.01)
        k = hv[..., 2].argmin(axis=1)
        lowest = hv[np.arange(len(hold)), k]
        assert np.all(_in_footprint(table, lowest[:, :2]))
    # Calibrated to rest the hands LEAN_HAND_GAP_M above the top: the median gap is that, to 3 mm.
    gap = v[hold][:, ids, 2].min(axis=1) - table.top_z
    assert abs(np.median(gap) - LEAN_HAND_GAP_M) < 0.003


@pytest.mark.parametrize("seed", [0, 1])
def test_no_interaction_pushes_the_body_into_furniture(body, seed):
    """All four interactions (chair, box, table, sofa/bed) in a 40 s script: truth penetration
    into the furniture < 1 cm on every frame, and never below the floor."""
    spec = build_scene("indoor", np.random.default_rng([seed, 1])).spec
    script = script_motion(spec, body, _betas(body, seed), 40.0, FPS, np.random.default_rng([seed, 3]),
                           MotionScriptConfig())
    names = {n for n, _, _ in script.segments}
    assert {"sit", "stand_on_box", "lean_table"} <= names
    out = body.from_params(script.params)
    v = out.vertices.numpy().astype(np.float64)
    depth = np.concatenate([furniture_penetration(spec, v[s:s + 200]).max(axis=1) for s in range(0, len(v), 200)])
    worst = int(depth.argmax())
    seg = next(n for n, s, e in script.segments if s <= worst < e)
    assert depth.max() < 0.01, f"{depth.max() * 100:.1f} cm into furniture at frame {worst} ({seg})"
    assert v[..., 2].min() > -0.005


@pytest.mark.parametrize("seed,seconds", [(12, 7.8), (5, 12.0), (7, 12.0)])
def test_walking_away_from_a_sofa_or_bed_keeps_the_heels_out_of_it(body, seed, seconds):
    """A sofa or bed is solid down to the floor and the performer stands up with the calves at its
    front: the first step away must not swing a heel into it (seed 12's bed: 3.3 cm before the
    step forward that now comes first)."""
    spec = build_scene("indoor", np.random.default_rng([seed, 1])).spec
    script = script_motion(spec, body, _betas(body, seed), seconds, FPS, np.random.default_rng([seed, 3]),
                           MotionScriptConfig())
    v = body.from_params(script.params).vertices.numpy().astype(np.float64)
    after = script.frames_of("stand_up", "step_away", "walk")
    depth = furniture_penetration(spec, v[after]).max()
    assert depth < 0.005, f"{depth * 100:.1f} cm into furniture after standing up"
