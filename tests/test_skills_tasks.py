"""The six skill tasks (embodmocap.skills.tasks) and APD: sizes, rewards' shape, success, numpy = torch."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from embodmocap.skills import tasks as T
from embodmocap.skills.apd import apd
from embodmocap.skills.tasks import CharacterState, SkillGoal, follow

# The supplement's observation sizes.
SIZES = {"follow": 20, "sit": 38, "climb": 27, "lie": 38, "prone": 35, "support": 27}


def _box(center, yaw, size):
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    signs = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1], [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]])
    corners = np.asarray(center) + (signs * np.asarray(size) / 2) @ R.T
    return R, corners


def _rot(x, z):
    x, z = np.asarray(x, float), np.asarray(z, float)
    return np.stack([x, np.cross(z, x), z], axis=-1)


def target_state(skill: str, rng=None):
    """A character exactly at the skill's target (the state its reward is 1 at), and its goal."""
    center, yaw, size = np.array([1.0, 2.0, 0.25]), 0.4, np.array([1.9, 0.9, 0.5])  # a bed-like box
    R_box, corners = _box(center, yaw, size)
    top = center[2] + size[2] / 2
    long_axis = R_box[:2, 0]
    up = np.eye(3)
    feet = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    g = dict(box_center=center, box_rot=R_box, box_corners=corners, long_axis=long_axis, ground_z=0.0, stand_z=0.93)
    if skill == "follow":
        path = np.stack([np.linspace(0, 3, 101), np.sin(np.linspace(0, 3, 101))], -1)
        t = 2.35
        wp = np.array([np.interp(t / 0.1, np.arange(101), path[:, 0]), np.interp(t / 0.1, np.arange(101), path[:, 1])])
        s = dict(root_pos=[wp[0], wp[1], 0.93], root_rot=up)
        g.update(path=path, time_s=t)
    elif skill in ("sit", "climb"):
        tgt = np.array([center[0], center[1], top + (0.10 if skill == "sit" else 0.94)])
        s = dict(root_pos=tgt, root_rot=up, foot_pos=np.array([[0, 0.1, top], [0, -0.1, top]]))
        g.update(target=tgt)
    elif skill in ("lie", "prone"):
        tgt = np.array([center[0], center[1], top + 0.12])
        fwd = [0, 0, 1.0] if skill == "lie" else [0, 0, -1.0]  # on the back / face down
        R = _rot(fwd, [long_axis[0], long_axis[1], 0])
        head = tgt + 0.6 * R[:, 2]
        s = dict(root_pos=tgt, root_rot=R, head_pos=head)
        g.update(target=tgt, stand_point=np.array([center[0] + 1.0, center[1] + 0.2, 0.93]))
    else:  # support: hands' centre on the top's centre, feet together on the ground, upright
        tgt = np.array([center[0], center[1], top])
        s = dict(root_pos=np.array([center[0] - 0.3, center[1], top]), root_rot=up,
                 hand_pos=np.array([tgt + [0, 0.15, 0], tgt - [0, 0.15, 0]]), foot_pos=feet + [center[0] - 0.5, center[1], 0])
        g.update(target=tgt)
    s.setdefault("head_pos", np.asarray(s["root_pos"]) + [0, 0, 0.6])
    s.setdefault("hand_pos", np.zeros((2, 3)))
    s.setdefault("foot_pos", np.zeros((2, 3)))
    s["root_vel"] = np.zeros(3)
    return s, g


def batch(d: dict, n: int = 1, lib=np) -> dict:
    out = {}
    for k, v in d.items():
        a = np.asarray(v, dtype=np.float64)
        if k != "path":
            a = np.broadcast_to(a, (n,) + a.shape).copy()
        out[k] = lib.as_tensor(a) if lib is not np else a
    return out


_ITEM_NDIM = {"root_pos": 1, "root_rot": 2, "root_vel": 1, "head_pos": 1, "hand_pos": 2, "foot_pos": 2}


def make(s: dict, g: dict, n: int = 1, lib=np):
    """Batched state and goal; state entries already batched (one more axis) are kept."""
    st = {}
    for k, v in s.items():
        a = np.asarray(v, dtype=np.float64)
        a = np.broadcast_to(a, (n,) + a.shape).copy() if a.ndim == _ITEM_NDIM[k] else a
        st[k] = lib.as_tensor(a) if lib is not np else a
    return CharacterState(**st), SkillGoal(**batch(g, n, lib))


def moved(s: dict, skill: str, offsets: np.ndarray) -> dict:
    """The state with the whole character moved by (n, 3) offsets (the support's hands follow)."""
    out = dict(s)
    for k in ("root_pos", "head_pos", "hand_pos", "foot_pos"):
        a = np.asarray(s[k], float)
        out[k] = a[None] + (offsets[:, None, :] if a.ndim == 2 else offsets)
    return out


@pytest.mark.parametrize("skill", T.SKILLS)
def test_observation_sizes_are_the_supplements(skill):
    s, g = target_state(skill)
    S, G = make(s, g, 5)
    assert T.OBS_SIZE[skill] == SIZES[skill]
    assert T.observe(skill, S, G).shape == (5, SIZES[skill])


@pytest.mark.parametrize("skill", T.SKILLS)
def test_reward_is_its_maximum_at_the_target_and_decreases_away(skill):
    s, g = target_state(skill)
    S, G = make(s, g)
    assert T.reward(skill, S, G)[0] == pytest.approx(1.0, abs=1e-9)  # every weight sums to 1
    assert T.success(skill, S, G)[0]
    rng = np.random.default_rng(0)
    # Moving away in any direction (horizontal for follow, any for the others) lowers the reward
    # steadily, out to 1.4 m (inside lie's / prone's 1.5 m approach radius).
    d = np.r_[0.0, np.linspace(0.013, 1.393, 28)]  # no distance right on a threshold
    for _ in range(8):
        u = rng.normal(size=3)
        u[2] = 0 if skill in ("follow", "support") else abs(u[2])  # support: slide over the top
        u /= np.linalg.norm(u)
        Sm, Gm = make(moved(s, skill, d[:, None] * u), g, len(d))
        r = np.asarray(T.reward(skill, Sm, Gm))
        assert np.all(np.diff(r) < 0), (skill, r)
        err = np.asarray(T.error(skill, Sm, Gm))
        assert np.allclose(err, d, atol=1e-9)
        ok = np.asarray(T.success(skill, Sm, Gm))
        assert np.array_equal(ok, d < T.SUCCESS_M[skill])
    # No random state scores more than the target (the maximum).
    n = 2000
    rs = dict(s)
    rs["root_pos"] = np.asarray(s["root_pos"]) + rng.normal(scale=0.7, size=(n, 3))
    rs["root_rot"] = Rotation.random(n, random_state=1).as_matrix()
    rs["root_vel"] = rng.normal(scale=1.5, size=(n, 3))
    rs["head_pos"] = rs["root_pos"] + rng.normal(scale=0.4, size=(n, 3))
    rs["hand_pos"] = np.asarray(s["hand_pos"]) + rng.normal(scale=0.3, size=(n, 2, 3))
    rs["foot_pos"] = np.asarray(s["foot_pos"]) + rng.normal(scale=0.3, size=(n, 2, 3))
    Sr = CharacterState(**{k: np.asarray(v, float) for k, v in rs.items()})
    _, Gr = make(s, g, n)
    r = np.asarray(T.reward(skill, Sr, Gr))
    assert r.max() < 1.0 and r.min() >= 0.0


def test_far_terms_reward_walking_towards_the_object():
    # Sit and climb far from the object: 1.5 m/s straight at it beats standing and walking away.
    for skill in ("sit", "climb", "support"):
        s, g = target_state(skill)
        s = moved(s, skill, np.array([[3.0, -1.0, 0.0]] * 3))
        to = np.asarray(g.get("box_center", g.get("target")))[:2] - s["root_pos"][0, :2]
        to = np.append(to / np.linalg.norm(to), 0.0)
        s["root_vel"] = np.stack([np.zeros(3), 1.5 * to, -1.5 * to])
        S, G = make(s, g, 3)
        r = np.asarray(T.reward(skill, S, G))
        assert r[1] > r[0] > r[2] or (r[1] > r[0] and r[0] >= r[2]), (skill, r)


def test_support_needs_the_feet_together():
    s, g = target_state("support")
    s2 = dict(s, foot_pos=np.asarray(s["foot_pos"]) + [[0, 0.25, 0], [0, -0.25, 0]])  # 50 cm apart
    S, G = make(s2, g)
    assert not T.success("support", S, G)[0] and T.error("support", S, G)[0] == pytest.approx(0.0)
    assert T.reward("support", S, G)[0] < 1.0


@pytest.mark.parametrize("skill", T.SKILLS)
def test_observation_is_in_the_characters_heading_frame(skill):
    # Turning and shifting the whole world about Z leaves the task observation unchanged.
    s, g = target_state(skill)
    s = dict(s, root_rot=Rotation.from_euler("z", 0.7).as_matrix() @ np.asarray(s["root_rot"]))
    a = T.observe(skill, *make(s, g))
    yaw, shift = 1.1, np.array([0.4, -2.0, 0.0])
    Rz = Rotation.from_euler("z", yaw).as_matrix()

    def tf(d, kinds):
        out = dict(d)
        for k, kind in kinds.items():
            if k in out and out[k] is not None:
                v = np.asarray(out[k], float)
                if kind == "p":
                    out[k] = v @ Rz.T + shift
                elif kind == "p2":
                    out[k] = v @ Rz[:2, :2].T + shift[:2]
                elif kind == "v2":
                    out[k] = v @ Rz[:2, :2].T
                elif kind == "v":
                    out[k] = v @ Rz.T
                else:
                    out[k] = Rz @ v
        return out

    s2 = tf(s, {"root_pos": "p", "head_pos": "p", "hand_pos": "p", "foot_pos": "p", "root_vel": "v", "root_rot": "R"})
    g2 = tf(g, {"target": "p", "box_center": "p", "box_corners": "p", "stand_point": "p", "path": "p2",
                "long_axis": "v2", "box_rot": "R"})
    b = T.observe(skill, *make(s2, g2))
    assert np.allclose(a, b, atol=1e-9)
    assert T.reward(skill, *make(s2, g2))[0] == pytest.approx(T.reward(skill, *make(s, g))[0], abs=1e-9)


@pytest.mark.parametrize("skill", T.SKILLS)
def test_numpy_and_torch_agree(skill):
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(3)
    s, g = target_state(skill)
    n = 64
    s = moved(s, skill, rng.normal(scale=0.8, size=(n, 3)))
    s["root_rot"] = Rotation.random(n, random_state=2).as_matrix()
    s["root_vel"] = rng.normal(size=(n, 3))
    S, G = make(s, g, n)
    St, Gt = make(s, g, n, torch)
    for fn in (T.observe, T.reward, T.error):
        a, b = fn(skill, S, G), fn(skill, St, Gt)
        assert isinstance(b, torch.Tensor) and np.allclose(a, b.numpy(), atol=1e-10)
    assert np.array_equal(T.success(skill, S, G), T.success(skill, St, Gt).numpy())
    # float32 tensors work too (the usual GPU dtype).
    St32 = CharacterState(**{k: v.float() for k, v in vars(St).items()})
    Gt32 = SkillGoal(**{k: v.float() if v is not None else None for k, v in vars(Gt).items()})
    assert np.allclose(T.reward(skill, St32, Gt32).numpy(), T.reward(skill, S, G), atol=1e-4)


def test_follow_waypoints_interpolate_the_path():
    path = np.stack([np.arange(30) * 0.12, np.cos(np.arange(30) * 0.3)], -1)  # a point every 0.1 s
    t = np.array([0.0, 0.55, 2.0, 5.0])  # 5 s is past the path's end (2.9 s): held at its last point
    w = follow.sample_path(path, t)
    assert w.shape == (4, 10, 2)
    tt = np.clip(t[:, None] + 0.1 * np.arange(10), 0, 2.9) / 0.1
    assert np.allclose(w[..., 0], np.interp(tt, np.arange(30), path[:, 0]))
    assert np.allclose(w[..., 1], np.interp(tt, np.arange(30), path[:, 1]))
    # Per-environment paths (N, P, 2) give each environment its own.
    w2 = follow.sample_path(np.stack([path, path + 1.0]), t[:2])
    assert np.allclose(w2[0], w[0]) and np.allclose(w2[1], w[1] + 1.0)


def test_apd_known_answers_and_backends():
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(0)
    base = rng.normal(size=(1, 5, 24, 3))
    same = np.repeat(base, 4, axis=0)
    assert apd(same) == 0.0
    # Two motions, every coordinate 0.1 apart: distance 0.1 * sqrt(5 * 24 * 3).
    two = np.concatenate([base, base + 0.1])
    assert apd(two) == pytest.approx(0.1 * np.sqrt(360))
    # Three motions on a line at 0, 1, 3 (scaled unit offsets): pairs 1, 2, 3 -> mean 2.
    u = np.ones((1, 5, 24, 3)) / np.sqrt(360)
    three = np.concatenate([base, base + u, base + 3 * u])
    assert apd(three) == pytest.approx(2.0)
    # Rotations add their own distances (here 0.5 * sqrt(5 * 24 * 3) for the second motion).
    rot = np.zeros((2, 5, 24, 3))
    rot[1] = 0.5
    assert apd(np.repeat(base, 2, axis=0), rot) == pytest.approx(0.5 * np.sqrt(360))
    x = rng.normal(size=(6, 8, 24, 3))
    r = rng.normal(size=(6, 8, 24, 6))
    assert apd(torch.as_tensor(x), torch.as_tensor(r)) == pytest.approx(apd(x, r))
    assert apd(x[:1]) == 0.0
