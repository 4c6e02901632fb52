"""The interaction skill environments EmbodMocap/Skill-<name>-v0 on a scripted studio session."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

gym = pytest.importorskip("gymnasium")
pytest.importorskip("mujoco")

import embodmocap.sim  # noqa: E402  (registers the environments)
from embodmocap.errors import InputError  # noqa: E402
from embodmocap.sim.amp import AMP_FRAME_SIZE, AMP_TRANSITION_SIZE, amp_frame_features  # noqa: E402
from embodmocap.sim.skill_env import PROPRIO_SIZE, SkillEnv, load_skill_clips, skills_json_path  # noqa: E402
from embodmocap.skills import tasks  # noqa: E402
from skill_session import skill_session  # noqa: E402,F401

SIZES = {"follow": 20, "sit": 38, "climb": 27, "lie": 38, "prone": 35, "support": 27}  # the supplement's


@pytest.fixture(scope="module")
def envs(skill_session):
    return {k: gym.make(f"EmbodMocap/Skill-{k}-v0", session=str(skill_session)) for k in tasks.SKILLS}


@pytest.mark.parametrize("skill", tasks.SKILLS)
def test_registered_made_by_id_and_passes_the_checker(envs, skill):
    from gymnasium.utils.env_checker import check_env

    env = envs[skill]
    assert f"EmbodMocap/Skill-{skill}-v0" in gym.registry
    assert isinstance(env.unwrapped, SkillEnv) and env.unwrapped.skill == skill
    check_env(env.unwrapped, skip_render_check=True)
    obs, info = env.reset(seed=0)
    assert obs.shape == (PROPRIO_SIZE + SIZES[skill],) == env.observation_space.shape
    assert env.action_space.shape == (69,)
    # The task part of the observation is the task function's, on the environment's state.
    u = env.unwrapped
    assert np.allclose(obs[PROPRIO_SIZE:], tasks.observe(skill, u.character_state(), u.goal())[0], atol=1e-5)


@pytest.mark.parametrize("skill", ["sit", "climb", "support", "follow"])
def test_the_reference_clips_own_end_frame_succeeds(envs, skill):
    u = envs[skill].unwrapped
    for c in range(len(u.clips)):
        ok, err = u.reference_result(c)
        assert ok, (skill, u.clips[c].id, err)
        assert err < tasks.SUCCESS_M[skill]
        # ... and its first frame (still approaching) does not, and scores less.
        if skill != "follow":
            ok0, err0 = u.reference_result(c, 0)
            assert not ok0 and err0 > err


@pytest.mark.parametrize("skill", ["sit", "climb", "support"])
def test_task_reward_rises_along_the_reference(envs, skill):
    # Replaying the reference clip (positions set frame by frame), the task reward at the hold is
    # higher than at the start of the approach.
    u = envs[skill].unwrapped
    ref = u.clips[0].ref
    r = []
    for k in (0, len(ref) - 1):
        u.set_state(ref.qpos[k], ref.qvel[k])
        u._start, u._step = k, 0
        r.append(float(tasks.reward(skill, u.character_state(), u.goal())[0]))
    assert r[1] > r[0] + 0.2, r


def test_amp_features_of_the_simulated_state_match_the_clips(envs):
    u = envs["sit"].unwrapped
    real = u.reference_transitions
    assert real.shape == (sum(len(c.ref) - 1 for c in u.clips), AMP_TRANSITION_SIZE) and np.isfinite(real).all()
    ref = u.clips[0].ref
    k = len(ref) // 2
    u.reset(seed=0, options={"clip": 0, "start": k})
    f_env = u._amp_frame()
    f_ref = amp_frame_features(ref.qpos[k:k + 1], ref.qvel[k:k + 1], ref.xpos[k:k + 1], u.clips[0].floor_z)[0]
    assert f_env.shape == (AMP_FRAME_SIZE,) and np.allclose(f_env, f_ref, atol=1e-4)
    assert np.allclose(real[k, :AMP_FRAME_SIZE], f_ref, atol=1e-6) and np.allclose(real[k - 1, AMP_FRAME_SIZE:], f_ref, atol=1e-6)
    # Root height, then hinge angles at their documented offsets.
    assert f_ref[0] == pytest.approx(ref.qpos[k, 2] - u.clips[0].floor_z, abs=1e-5)
    assert np.allclose(f_ref[13:82], ref.qpos[k, 7:], atol=1e-5)
    _, _, _, _, info = u.step(u.action_space.sample() * 0)
    assert info["amp_obs"].shape == (AMP_TRANSITION_SIZE,) and np.allclose(info["amp_obs"][:AMP_FRAME_SIZE], f_env)


def test_episode_end_reports_success_and_error(envs):
    u = envs["follow"].unwrapped
    u.reset(seed=1)
    info, done = {}, False
    for _ in range(400):
        _, r, term, trunc, info = u.step(u.action_space.sample() * 0)
        assert 0.0 <= r <= 1.0
        if term or trunc:
            done = True
            break
    assert done and "success" in info and info["error_m"] >= 0


def test_missing_skills_json_names_the_command(skill_session, tmp_path):
    copy = tmp_path / "session"
    shutil.copytree(skill_session, copy)
    skills_json_path(copy, "seq0").unlink()
    with pytest.raises(InputError, match=r"embodmocap skills"):
        gym.make("EmbodMocap/Skill-sit-v0", session=str(copy))
    with pytest.raises(InputError, match="skills.json"):
        load_skill_clips(copy, "sit")


@pytest.fixture(scope="module")
def lie_prone_session(tmp_path_factory):
    """A room with a bed where the studio scripts lying on the back and on the front."""
    from embodmocap.synth import motion
    from skill_session import make_skill_session

    if "lie" not in getattr(motion, "INTERACTIONS", ()):
        pytest.skip("the studio on this branch scripts no lie / prone (the clip half of issue 17 adds them)")
    root = tmp_path_factory.mktemp("lie") / "session"
    make_skill_session(root, seed=1, seconds=30.0, interactions=("lie", "prone"))
    return root


@pytest.mark.parametrize("skill", ["lie", "prone"])
def test_lie_and_prone_reference_end_frames_succeed(lie_prone_session, skill):
    from gymnasium.utils.env_checker import check_env

    u = gym.make(f"EmbodMocap/Skill-{skill}-v0", session=str(lie_prone_session)).unwrapped
    assert not any(c.id.endswith("standin") for c in u.clips)
    check_env(u, skip_render_check=True)
    for c in range(len(u.clips)):
        ok, err = u.reference_result(c)
        assert ok and err < 0.3, (skill, u.clips[c].id, err)
        ok0, err0 = u.reference_result(c, 0)
        assert not ok0 and err0 > err


def test_the_feet_are_the_soles(envs):
    # The feet's height is the sole's (the foot boxes' lowest corner): on the floor standing at the
    # sit clip's start, on the box top (climb target - 0.94 m) standing on it at the climb's end.
    u = envs["sit"].unwrapped
    ref = u.clips[0].ref
    u.set_state(ref.qpos[0], ref.qvel[0])
    assert np.allclose(u.character_state().foot_pos[0, :, 2], u.clips[0].floor_z, atol=0.01)
    u = envs["climb"].unwrapped
    ref = u.clips[0].ref
    u.set_state(ref.qpos[-1], ref.qvel[-1])
    top = u.clips[0].goal.target[0, 2] - 0.94
    assert np.allclose(u.character_state().foot_pos[0, :, 2], top, atol=0.01)
