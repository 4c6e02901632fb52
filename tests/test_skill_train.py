"""`embodmocap sim train --skill NAME`: PPO with the task + AMP style reward (CPU smoke run)."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")
pytest.importorskip("mujoco")

from skill_session import skill_session  # noqa: E402,F401


def test_discriminator_tells_the_clips_transitions_from_others(skill_session):
    from embodmocap.sim.amp import Discriminator
    from embodmocap.sim.skill_env import SkillEnv

    env = SkillEnv(session=skill_session, skill="sit")
    real = env.reference_transitions
    rng = np.random.default_rng(0)
    # Fake: the same transitions played backwards in time with their velocities (a different motion).
    fake = np.concatenate([real[:, real.shape[1] // 2:], real[:, : real.shape[1] // 2]], axis=1)
    fake = fake + rng.normal(scale=0.05, size=fake.shape).astype(np.float32)
    disc = Discriminator(real, lr=1e-3, seed=0)
    before = disc.style_reward(real).mean() - disc.style_reward(fake).mean()
    for _ in range(60):
        disc.update(fake, epochs=1, batch=128)
    r_real, r_fake = disc.style_reward(real), disc.style_reward(fake)
    assert r_real.min() >= 0 and r_real.max() <= 1 and r_fake.min() >= 0
    assert r_real.mean() - r_fake.mean() > max(before, 0) + 0.3, (r_real.mean(), r_fake.mean())


def test_missing_skills_json_fails_the_command_with_the_fix(skill_session, tmp_path, capsys):
    import shutil

    from embodmocap.cli import main
    from embodmocap.sim.skill_env import skills_json_path

    copy = tmp_path / "session"
    shutil.copytree(skill_session, copy)
    skills_json_path(copy, "seq0").unlink()
    assert main(["sim", "train", str(copy), "--skill", "sit", "--out", str(tmp_path / "run"), "--steps", "8"]) != 0
    err = capsys.readouterr()
    assert f"embodmocap skills {copy}" in err.out + err.err
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_smoke_training_runs_and_writes_a_checkpoint(skill_session, tmp_path):
    from stable_baselines3 import PPO

    from embodmocap.cli import main
    from embodmocap.sim.skill_env import PROPRIO_SIZE, SkillEnv

    run = tmp_path / "run"
    assert main(["sim", "train", str(skill_session), "--skill", "sit", "--out", str(run), "--steps", "4096",
                 "--num-envs", "1", "--n-steps", "512", "--batch-size", "256", "--checkpoint-every", "2048"]) == 0
    info = json.loads((run / "run.json").read_text())
    assert info["kind"] == "skill" and info["skill"] == "sit" and info["clips"] == ["session/seq0/sit_00"]
    assert (run / "policy.zip").is_file() and (run / "discriminator.pt").is_file() and (run / "vecnormalize.pkl").is_file()
    assert list((run / "checkpoints").glob("policy_*_steps.zip"))
    prog = json.loads((run / "progress.json").read_text())
    assert len(prog["steps"]) == 8 and prog["steps"][-1] == 4096
    assert all(0.0 <= x <= 1.0 for x in prog["task_reward"] + prog["style_reward"])
    assert sum(prog["episodes_ended"]) > 0 and all(np.isfinite(prog["disc_loss"]))
    # The discriminator, trained alongside, scores the clip's transitions above the policy's.
    assert np.mean(prog["d_real"][-3:]) > np.mean(prog["d_fake"][-3:])
    # `sim eval` on a skill policy: the paper's skill table (success rate, contact error, APD).
    assert main(["sim", "eval", str(run / "policy.zip"), "--episodes", "3"]) == 0
    ev = json.loads((run / "eval.json").read_text())
    assert ev["kind"] == "skill" and ev["episodes"] == 3 and len(ev["success"]) == len(ev["error_m"]) == 3
    assert 0.0 <= ev["success_rate"] <= 100.0 and ev["error_cm_mean"] == pytest.approx(100 * np.mean(ev["error_m"]))
    assert ev["apd"] > 0 and ev["apd_steps"] >= 1  # sampled actions: the three motions differ
    policy = PPO.load(run / "policy.zip", device="cpu")
    env = SkillEnv(session=skill_session, skill="sit")
    obs, _ = env.reset(seed=0)
    action, _ = policy.predict(obs[None], deterministic=True)
    assert obs.shape == (PROPRIO_SIZE + 38,) and action.shape == (1, 69)
