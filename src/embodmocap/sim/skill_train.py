"""PPO training of an interaction skill with an AMP style reward (``embodmocap sim train --skill NAME``).

The policy acts in ``EmbodMocap/Skill-<name>-v0`` (:mod:`embodmocap.sim.skill_env`); its training
reward is ``w_task * r_task + w_style * r_style`` (the paper's r_task and r_style, weights 0.5 /
0.5 by default), where ``r_style = max(0, 1 - 0.25 (D(s_t, s_t+1) - 1)^2)`` comes from a small
least-squares discriminator (:class:`embodmocap.sim.amp.Discriminator`) trained alongside: after
every PPO rollout, on that rollout's transitions (fake) against the skill clips' own (real).

stable-baselines3 PPO, as the tracking task (:mod:`embodmocap.sim.train`). A run folder holds
``run.json`` (``kind: "skill"``, skill, sessions, clips, settings), ``policy.zip``,
``vecnormalize.pkl``, ``discriminator.pt`` (its weights and input normalisation), ``checkpoints/``,
``tb/`` and ``progress.json`` (after each rollout: steps, mean episode return and length, mean
task and style reward, the discriminator's loss and mean outputs on real and fake, and the success
rate and mean contact error of the episodes that ended in it).
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np

from embodmocap.errors import require
from embodmocap.io.atomic import write_json
from embodmocap.sim.config import SkillConfig, TrainConfig

log = logging.getLogger(__name__)


def _style_wrapper(venv, disc, cfg: SkillConfig):
    """A VecEnv wrapper: reward = w_task * task + w_style * style, keeping the rollout's transitions."""
    from stable_baselines3.common.vec_env import VecEnvWrapper

    class StyleReward(VecEnvWrapper):
        def __init__(self) -> None:
            super().__init__(venv)
            self.buffer: list[np.ndarray] = []
            self.task_sum = self.style_sum = 0.0
            self.count = 0
            self.ends: list[tuple[bool, float]] = []

        def reset(self):
            return self.venv.reset()

        def step_wait(self):
            obs, task, dones, infos = self.venv.step_wait()
            amp = np.stack([i["amp_obs"] for i in infos]).astype(np.float32)
            style = disc.style_reward(amp)
            self.buffer.append(amp)
            self.task_sum += float(task.sum())
            self.style_sum += float(style.sum())
            self.count += len(task)
            for i in infos:
                if "success" in i:
                    self.ends.append((bool(i["success"]), float(i["error_m"])))
            return obs, (cfg.w_task * task + cfg.w_style * style).astype(np.float32), dones, infos

        def take(self) -> dict:
            """The rollout's transitions and statistics (cleared)."""
            fake = np.concatenate(self.buffer) if self.buffer else np.zeros((0, 1), np.float32)
            out = {"fake": fake, "task_reward": self.task_sum / max(self.count, 1),
                   "style_reward": self.style_sum / max(self.count, 1), "ends": list(self.ends)}
            self.buffer, self.ends = [], []
            self.task_sum = self.style_sum = 0.0
            self.count = 0
            return out

    return StyleReward()


def _callback(wrapper, disc, cfg: SkillConfig, path: Path):
    """After each rollout: train the discriminator on it and record the progress row."""
    from stable_baselines3.common.callbacks import BaseCallback

    class AmpProgress(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            keys = ("steps", "ep_rew_mean", "ep_len_mean", "task_reward", "style_reward", "disc_loss", "d_real",
                    "d_fake", "episodes_ended", "success_rate", "error_m_mean")
            self.rows: dict[str, list] = {k: [] for k in keys}

        def _on_step(self) -> bool:
            return True

        def _on_rollout_end(self) -> None:
            got = wrapper.take()
            d = disc.update(got["fake"], epochs=cfg.disc_epochs) if len(got["fake"]) else {}
            eps = list(self.model.ep_info_buffer)
            ends = got["ends"]
            row = {"steps": int(self.num_timesteps),
                   "ep_rew_mean": float(np.mean([e["r"] for e in eps])) if eps else float("nan"),
                   "ep_len_mean": float(np.mean([e["l"] for e in eps])) if eps else float("nan"),
                   "task_reward": got["task_reward"], "style_reward": got["style_reward"],
                   "disc_loss": d.get("disc_loss", float("nan")), "d_real": d.get("d_real", float("nan")),
                   "d_fake": d.get("d_fake", float("nan")), "episodes_ended": len(ends),
                   "success_rate": float(np.mean([s for s, _ in ends])) if ends else float("nan"),
                   "error_m_mean": float(np.mean([e for _, e in ends])) if ends else float("nan")}
            for k, v in row.items():
                self.rows[k].append(v)
            for k in ("task_reward", "style_reward", "disc_loss", "success_rate"):
                self.logger.record(f"skill/{k}", row[k])

        def _on_training_end(self) -> None:
            write_json(path, {"version": 1, **self.rows})

    return AmpProgress()


def train_skill(sessions: list[str | Path], out: str | Path, cfg: TrainConfig, *, seq: str | None = None,
                progress: bool = True) -> Path:
    """Train PPO + AMP on the ``cfg.skill`` clips of ``sessions``; writes the run folder ``out``;
    returns ``policy.zip``. InputError when a sequence has no skills.json (run ``embodmocap skills``)."""
    require("stable_baselines3", "sim")
    import torch
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecNormalize

    from embodmocap.sim.amp import Discriminator
    from embodmocap.sim.skill_env import SkillEnv, load_skill_clips
    from embodmocap.sim.train import checkpoint_callback, new_ppo

    if cfg.skill is None:
        raise ValueError("train_skill needs cfg.skill (follow, sit, climb, lie, prone or support)")
    scfg = cfg.skill_task
    out = Path(out)
    clips = load_skill_clips([Path(s) for s in sessions], cfg.skill, seq, scfg.control_hz)
    out.mkdir(parents=True, exist_ok=True)
    log.info("training skill %s on %d clips (%s) for %d steps, %d envs, device %s", cfg.skill, len(clips),
             ", ".join(c.id for c in clips), cfg.steps, cfg.num_envs, cfg.device)
    write_json(out / "run.json", {"version": 1, "kind": "skill", "skill": cfg.skill,
                                  "sessions": [str(Path(s).resolve()) for s in sessions], "seq": seq,
                                  "clips": [f"{c.session.name}/{c.seq}/{c.id}" for c in clips],
                                  "config": dataclasses.asdict(cfg)})
    real = SkillEnv(clips=clips, skill=cfg.skill, config=scfg).reference_transitions
    disc = Discriminator(real, tuple(scfg.disc_hidden), scfg.disc_lr, scfg.disc_grad_penalty, cfg.device, cfg.seed)

    def make(i):
        def f():
            env = Monitor(SkillEnv(clips=clips, skill=cfg.skill, config=scfg))
            env.reset(seed=cfg.seed + i)
            return env
        return f

    fns = [make(i) for i in range(cfg.num_envs)]
    base = SubprocVecEnv(fns, start_method="fork") if cfg.num_envs > 1 else DummyVecEnv(fns)
    styled = _style_wrapper(base, disc, scfg)
    venv = VecNormalize(styled, gamma=0.99)
    model = new_ppo(venv, cfg, out)
    ckpt = checkpoint_callback(cfg, out)
    model.learn(total_timesteps=cfg.steps, callback=[ckpt, _callback(styled, disc, scfg, out / "progress.json")],
                progress_bar=progress, tb_log_name="ppo")
    model.save(out / "policy.zip")
    venv.save(str(out / "vecnormalize.pkl"))
    tmp = out / "discriminator.pt.tmp"
    torch.save(disc.state_dict(), tmp)
    tmp.replace(out / "discriminator.pt")
    venv.close()
    log.info("wrote %s", out / "policy.zip")
    return out / "policy.zip"


def evaluate_skill(checkpoint: str | Path, *, episodes: int = 32, device: str = "cpu", seed: int = 10_000,
                   deterministic: bool = False) -> Path:
    """The paper's skill table for a policy of ``sim train --skill``: success rate (%), contact
    error (cm, mean over the episodes' ends) and APD of the generated motions; writes
    ``eval.json`` in the run folder.

    Episodes start as in training (a random clip); actions are sampled from the policy
    (``deterministic=False``): the diversity APD measures comes from the policy's sampling and the
    clips, as for the paper's generated samples. APD is over the episodes' first ``T`` steps
    (``T`` = the shortest episode): body positions relative to the first frame's root (24 x 3)
    and hinge angles (69) per step.
    """
    sb3 = require("stable_baselines3", "sim")
    import json

    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    from embodmocap.errors import InputError
    from embodmocap.sim.skill_env import SkillEnv, load_skill_clips
    from embodmocap.skills.apd import apd

    checkpoint = Path(checkpoint)
    run = next((f for f in (checkpoint.parent, checkpoint.parent.parent) if (f / "run.json").is_file()), None)
    if not checkpoint.is_file() or run is None:
        raise InputError(checkpoint, "not a policy of a skill run (no run.json next to it or one folder up)",
                         "give RUN/policy.zip written by `embodmocap sim train --skill NAME`")
    info = json.loads((run / "run.json").read_text())
    scfg = SkillConfig(**{**info["config"]["skill_task"], "disc_hidden": tuple(info["config"]["skill_task"]["disc_hidden"])})
    clips = load_skill_clips([Path(s) for s in info["sessions"]], info["skill"], info.get("seq"), scfg.control_hz)
    env = SkillEnv(clips=clips, skill=info["skill"], config=scfg)
    policy = sb3.PPO.load(checkpoint, device=device)
    stats = run / "vecnormalize.pkl"
    norm = None
    if checkpoint.name == "policy.zip" and stats.is_file():
        norm = VecNormalize.load(str(stats), DummyVecEnv([lambda: SkillEnv(clips=clips, skill=info["skill"], config=scfg)]))
        norm.training = False
    ends, motions = [], []
    for e in range(episodes):
        obs, _ = env.reset(seed=seed + e)
        root0 = env.data.xpos[1].copy()
        frames, done, last = [], False, {}
        while not done:
            o = norm.normalize_obs(obs[None]) if norm is not None else obs[None]
            action, _ = policy.predict(o, deterministic=deterministic)
            obs, _, term, trunc, last = env.step(action[0])
            done = term or trunc
            frames.append(np.concatenate([(env.data.xpos[1:] - root0).ravel(), env.data.qpos[7:]]))
        ends.append((bool(last["success"]), float(last["error_m"])))
        motions.append(np.asarray(frames))
    T = min(len(m) for m in motions)
    feats = np.stack([m[:T] for m in motions])
    doc = {"version": 1, "kind": "skill", "skill": info["skill"], "checkpoint": str(checkpoint), "episodes": episodes,
           "deterministic": deterministic, "success_rate": 100.0 * float(np.mean([s for s, _ in ends])),
           "error_cm_mean": 100.0 * float(np.mean([x for _, x in ends])),
           "apd": apd(feats[..., :72].reshape(episodes, T, 24, 3), feats[..., 72:].reshape(episodes, T, 23, 3)),
           "apd_steps": int(T), "success": [s for s, _ in ends], "error_m": [x for _, x in ends]}
    write_json(run / "eval.json", doc)
    log.info("eval %s: success %.1f %%, error %.1f cm, APD %.2f over %d episodes", info["skill"], doc["success_rate"],
             doc["error_cm_mean"], doc["apd"], episodes)
    return run / "eval.json"
