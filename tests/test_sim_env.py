"""The tracking environment `EmbodMocap/SceneTracking-v0` on the tiny studio session."""

from __future__ import annotations

import numpy as np
import pytest

gym = pytest.importorskip("gymnasium")
pytest.importorskip("mujoco")

import embodmocap.sim  # noqa: E402  (registers the environment)
from embodmocap.geometry.heightmap import egocentric_heightmap  # noqa: E402
from embodmocap.sim.config import TrackingConfig  # noqa: E402
from embodmocap.sim.env import TrackingEnv, _heading, load_clips, tracking_success, tracking_table  # noqa: E402
from sim_session import sim_session  # noqa: E402,F401


@pytest.fixture(scope="module")
def clips(sim_session):
    return load_clips(sim_session)


def test_registered_made_by_id_and_passes_the_checker(sim_session):
    from gymnasium.utils.env_checker import check_env

    assert embodmocap.sim.ENV_ID in gym.registry
    env = gym.make(embodmocap.sim.ENV_ID, session=str(sim_session), seq="seq0")
    assert isinstance(env.unwrapped, embodmocap.sim.TrackingEnv)
    check_env(env.unwrapped, skip_render_check=True)
    obs, _ = env.reset(seed=0)
    assert obs.shape == env.observation_space.shape and env.action_space.shape == (69,)


def _replay(env, start=0):
    env.reset(seed=0, options={"start": start})
    rewards, info = [], {}
    for _ in range(400):
        _, r, term, trunc, info = env.step(env.reference_action())
        rewards.append(r)
        if term or trunc:
            return np.array(rewards), term, info
    return np.array(rewards), False, info


def test_replaying_the_reference_keeps_the_reward_near_its_maximum(clips):
    # With the residual root assist the actuators reproduce the reference: reward ~ 1 (its maximum).
    r, term, info = _replay(TrackingEnv(clips=clips, config=TrackingConfig(root_assist=True)))
    assert not term and len(r) == 300 and info["time_s"] == pytest.approx(10.0)  # a 10 s episode
    assert r.mean() > 0.9
    # Without it (the paper's task), the ideal actions alone still track this standing clip.
    r, term, _ = _replay(TrackingEnv(clips=clips))
    assert not term and r[:30].mean() > 0.9 and r.mean() > 0.7
    # Random actions fall behind.
    env = TrackingEnv(clips=clips)
    env.reset(seed=1, options={"start": 0})
    rr = [env.step(env.action_space.sample())[1] for _ in range(30)]
    assert np.mean(rr) < r[:30].mean() - 0.1


def test_random_starts_and_the_egocentric_height_map(clips):
    env = TrackingEnv(clips=clips)
    starts = {env.reset(seed=s)[1]["start"] for s in range(20)}
    assert len(starts) > 3
    obs, _ = env.reset(seed=0)
    d = env.data
    root = d.xpos[1]
    grid = egocentric_heightmap(clips[0].heightmap, root[:2], np.float64(_heading(d.xquat[1])), fill=np.nanmin(clips[0].heightmap.heights))
    assert np.allclose(obs[-121:], (grid - root[2]).ravel(), atol=1e-5)
    # Standing on the studio floor (z = 0): the grid under the performer is the floor below the root.
    assert obs[-121 + 60] == pytest.approx(-root[2], abs=1e-4)


def test_success_metric():
    lengths = np.array([10.0, 9.0, 8.0, 3.0, 8.1])
    assert tracking_success(lengths) == pytest.approx(3 / 5)  # more than 8 s
    t = tracking_table(lengths)
    assert t["success_rate"] == pytest.approx(60.0) and t["failure_rate"] == pytest.approx(40.0)
    assert t["failure_len_mean_s"] == pytest.approx(5.5) and t["episodes"] == 5


def test_vector_env_steps_many_environments(clips):
    envs = gym.make_vec(embodmocap.sim.ENV_ID, num_envs=3, vectorization_mode="sync", clips=clips)
    obs, _ = envs.reset(seed=0)
    assert obs.shape == (3,) + envs.single_observation_space.shape
    for _ in range(5):
        obs, r, term, trunc, _ = envs.step(envs.action_space.sample())
    assert r.shape == (3,) and np.isfinite(obs).all()
    envs.close()


@pytest.mark.parametrize("sub", ["check", "train", "eval"])
def test_sim_commands_have_help(sub, capsys):
    from embodmocap.cli import main

    with pytest.raises(SystemExit) as e:
        main(["sim", sub, "--help"])
    assert e.value.code == 0 and "usage: embodmocap sim:" in capsys.readouterr().out


def test_clips_from_a_folder_of_sessions_each_with_its_model(sim_session):
    clips = load_clips([sim_session.parent, sim_session])  # a folder holding the session, and the session
    assert [c.name for c in clips] == ["session/seq0", "session/seq0"]
    env = TrackingEnv(clips=clips)
    _, info0 = env.reset(seed=0, options={"clip": 0, "start": 0})
    m0 = env.model
    _, info1 = env.reset(seed=0, options={"clip": 1, "start": 2})
    assert env.model is not m0 and info1["start"] == 2
    assert np.allclose(env.data.qpos, clips[1].qpos[2])


def test_a_missing_extra_is_one_line_naming_it(monkeypatch):
    import sys

    from embodmocap.errors import MissingExtraError
    from embodmocap.sim import deps

    monkeypatch.setitem(sys.modules, "mujoco", None)  # as if not installed
    with pytest.raises(MissingExtraError, match=r"embodmocap\[sim\]"):
        deps.mujoco()


def test_raycast_render_matches_mujocos_picture(sim_session):
    """The ray-cast fallback of the video (no OpenGL) draws what MuJoCo's renderer draws: the
    performer's silhouette overlaps MuJoCo's own segmentation of the same camera (IoU > 0.8, at
    320 x 240), the ground is below it and the sky above."""
    from embodmocap.sim.env import TrackingEnv

    env = TrackingEnv(session=sim_session, config=TrackingConfig(random_start=False), render_mode="rgb_array")
    env.reset(seed=0)
    env.data.qpos[7 + 3 * 16] = -1.2  # an arm raised sideways: a silhouette with some shape
    env.mj.mj_forward(env.model, env.data)
    env.render_backend = "raycast"
    img = env.render()
    assert img.shape == (240, 320, 3) and img.dtype == np.uint8
    body = (img[..., 0].astype(int) - img[..., 2] > 40)
    sky = (img == [170, 200, 230]).all(axis=-1)
    assert sky[:10].mean() > 0.5 and not sky[-20:].any()
    # MuJoCo's own segmentation of the same free camera, as the reference (in a subprocess with
    # EGL: this process may have imported MuJoCo with another GL backend first).
    import os
    import subprocess
    import sys

    from embodmocap.sim.env import _heading

    tmp = sim_session.parent / "raycast_ref"
    tmp.mkdir(exist_ok=True)
    (tmp / "m.xml").write_text(env.clip.xml)
    np.save(tmp / "qpos.npy", env.data.qpos)
    az = 90.0 + np.degrees(_heading(env.data.xquat[1]))
    code = f"""
import numpy as np, mujoco
m = mujoco.MjModel.from_xml_path({str(tmp / 'm.xml')!r}); d = mujoco.MjData(m)
d.qpos[:] = np.load({str(tmp / 'qpos.npy')!r}); mujoco.mj_forward(m, d)
r = mujoco.Renderer(m, 240, 320); cam = mujoco.MjvCamera(); cam.lookat[:] = d.xpos[1]
cam.distance, cam.azimuth, cam.elevation = 3.5, {az!r}, -20.0
r.enable_segmentation_rendering(); r.update_scene(d, cam); seg = r.render()
body = (seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM)) & (m.geom_bodyid[np.clip(seg[..., 0], 0, None)] > 0) & (seg[..., 0] >= 0)
np.save({str(tmp / 'ref.npy')!r}, body)
"""
    res = subprocess.run([sys.executable, "-c", code], env=dict(os.environ, MUJOCO_GL="egl"), capture_output=True, text=True)
    if res.returncode != 0:
        pytest.skip(f"no MuJoCo offscreen rendering here: {res.stderr.strip().splitlines()[-1:]}")
    ref = np.load(tmp / "ref.npy")
    iou = (body & ref).sum() / (body | ref).sum()
    assert ref.sum() > 500 and iou > 0.8, iou
    env.close()
