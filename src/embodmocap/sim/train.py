"""PPO training and evaluation of the scene-aware tracking policy (``embodmocap sim train / eval``).

We use **stable-baselines3** PPO: it installs here next to the rest of the package (rsl-rl-lib,
MimicKit's and IsaacLab's usual choice, needs protobuf >= 6, which clashes with mediapipe's < 5 in
our environment), runs on CPU or CUDA, and its Gymnasium vector environments, checkpoints and
TensorBoard logs are standard.

A run folder holds ``run.json`` (sessions, sequence, settings), ``policy.zip`` (the final policy),
``vecnormalize.pkl`` (observation/reward normalisation statistics), ``checkpoints/`` (policy and
statistics every ``checkpoint_every`` steps), ``tb/`` (TensorBoard logs), ``progress.json`` (mean
episode return and length after each rollout) and, after ``sim eval``,
``eval.json`` and ``eval.mp4``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

import numpy as np

from embodmocap.errors import InputError, require
from embodmocap.io.atomic import write_json
from embodmocap.sim.config import TrackingConfig, TrainConfig

log = logging.getLogger(__name__)


def _tracking_from_dict(d: dict) -> TrackingConfig:
    d = dict(d)
    d["future_steps"] = tuple(d.get("future_steps", TrackingConfig.future_steps))
    return TrackingConfig(**d)


def _vec_env(clips, cfg: TrackingConfig, n: int, seed: int):
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    from embodmocap.sim.env import TrackingEnv

    def make(i):
        def f():
            env = Monitor(TrackingEnv(clips=clips, config=cfg))
            env.reset(seed=seed + i)
            return env
        return f

    fns = [make(i) for i in range(n)]
    return SubprocVecEnv(fns, start_method="fork") if n > 1 else DummyVecEnv(fns)


def _progress_callback(path: Path):
    """A callback recording, after each rollout, the mean return and length of the last episodes
    (stable-baselines3's window of 100), written to ``path`` (``progress.json``) at the end."""
    from stable_baselines3.common.callbacks import BaseCallback

    class Progress(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.rows: dict[str, list] = {"steps": [], "ep_rew_mean": [], "ep_len_mean": []}

        def _on_step(self) -> bool:
            return True

        def _on_rollout_end(self) -> None:
            eps = list(self.model.ep_info_buffer)
            if eps:
                self.rows["steps"].append(int(self.num_timesteps))
                self.rows["ep_rew_mean"].append(float(np.mean([e["r"] for e in eps])))
                self.rows["ep_len_mean"].append(float(np.mean([e["l"] for e in eps])))

        def _on_training_end(self) -> None:
            write_json(path, {"version": 1, **self.rows})

    return Progress()


def train(sessions: list[str | Path], out: str | Path, cfg: TrainConfig = TrainConfig(), *, seq: str | None = None,
          progress: bool = True, resume: str | Path | None = None) -> Path:
    """Train PPO on the clips of ``sessions``; writes the run folder ``out``; returns ``policy.zip``.

    ``resume``: a checkpoint (``policy.zip`` or ``checkpoints/policy_<n>_steps.zip``) whose policy,
    optimiser state, step count and normalisation statistics training continues from, up to
    ``cfg.steps`` steps in all (the PPO hyper-parameters are the checkpoint's)."""
    sb3 = require("stable_baselines3", "sim")
    from stable_baselines3.common.vec_env import VecNormalize

    from embodmocap.sim.env import load_clips

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    clips = load_clips([Path(s) for s in sessions], seq, cfg.tracking)
    log.info("training on %d clips (%s) for %d steps, %d envs, device %s", len(clips),
             ", ".join(c.name for c in clips), cfg.steps, cfg.num_envs, cfg.device)
    run_doc = {"version": 1, "sessions": [str(Path(s).resolve()) for s in sessions], "seq": seq,
               "clips": [c.name for c in clips], "config": dataclasses.asdict(cfg)}
    if resume is not None:
        resume = Path(resume)
        if not resume.is_file():
            raise InputError(resume, "checkpoint to resume from not found",
                             "give a policy zip written by `embodmocap sim train` (policy.zip or checkpoints/*.zip)")
        run_doc["resumed_from"] = str(resume.resolve())
    write_json(out / "run.json", run_doc)
    raw = _vec_env(clips, cfg.tracking, cfg.num_envs, cfg.seed)
    if resume is None:
        venv = VecNormalize(raw, gamma=0.99)
        model = new_ppo(venv, cfg, out)
    else:
        stats = _stats_for(resume, _run_folder(resume))
        venv = VecNormalize.load(str(stats), raw) if stats is not None else VecNormalize(raw, gamma=0.99)
        venv.training = True
        model = sb3.PPO.load(resume, env=venv, device=cfg.device, tensorboard_log=str(out / "tb"))
        log.info("resuming %s at step %d (normalisation statistics: %s)", resume, model.num_timesteps, stats)
    ckpt = checkpoint_callback(cfg, out)
    # With reset_num_timesteps=False stable-baselines3 adds total_timesteps to the step count.
    model.learn(total_timesteps=max(cfg.steps - model.num_timesteps, 0) if resume is not None else cfg.steps,
                callback=[ckpt, _progress_callback(out / "progress.json")], progress_bar=progress, tb_log_name="ppo",
                reset_num_timesteps=resume is None)
    model.save(out / "policy.zip")
    venv.save(str(out / "vecnormalize.pkl"))
    venv.close()
    log.info("wrote %s", out / "policy.zip")
    return out / "policy.zip"


def new_ppo(venv, cfg: TrainConfig, out: Path):
    """A fresh stable-baselines3 PPO on ``venv`` with the package's settings (the tracking and the
    skill runs share them): rollouts of ``cfg.n_steps`` per environment, minibatches of at most
    ``cfg.batch_size``, a [512, 256] MLP with a small initial action noise (exp(-2) of the PD
    target range: large noise makes the humanoid fall before it learns anything), TensorBoard
    logs in ``out/tb``."""
    sb3 = require("stable_baselines3", "sim")
    n_steps = max(cfg.n_steps, 2)
    batch = min(cfg.batch_size, n_steps * cfg.num_envs)
    return sb3.PPO("MlpPolicy", venv, n_steps=n_steps, batch_size=batch, learning_rate=cfg.learning_rate,
                   gamma=0.99, gae_lambda=0.95, n_epochs=5, clip_range=0.2, ent_coef=0.0, seed=cfg.seed,
                   device=cfg.device, tensorboard_log=str(out / "tb"), verbose=0,
                   policy_kwargs={"net_arch": [512, 256], "log_std_init": -2.0})


def checkpoint_callback(cfg: TrainConfig, out: Path):
    """Saves ``out/checkpoints/policy_<steps>_steps.zip`` (+ normalisation statistics) every
    ``cfg.checkpoint_every`` environment steps."""
    from stable_baselines3.common.callbacks import CheckpointCallback

    return CheckpointCallback(save_freq=max(cfg.checkpoint_every // cfg.num_envs, 1), save_path=str(out / "checkpoints"),
                              name_prefix="policy", save_vecnormalize=True)


def _run_folder(checkpoint: Path) -> Path:
    for folder in (checkpoint.parent, checkpoint.parent.parent):
        if (folder / "run.json").is_file():
            return folder
    raise InputError(checkpoint, "no run.json next to the checkpoint or one folder up",
                     "give a policy written by `embodmocap sim train`")


def _stats_for(checkpoint: Path, run: Path) -> Path | None:
    """The normalisation statistics saved with ``checkpoint`` (SB3 names them by step count)."""
    if checkpoint.name == "policy.zip":
        p = run / "vecnormalize.pkl"
        return p if p.is_file() else None
    steps = checkpoint.stem.rsplit("_", 2)[-2] if checkpoint.stem.endswith("_steps") else None
    p = checkpoint.parent / f"policy_vecnormalize_{steps}_steps.pkl"
    return p if steps and p.is_file() else None


def rollout_lengths(policy, env, normalize, episodes: int, seed: int, frames: list | None = None) -> np.ndarray:
    """Run ``episodes`` episodes (random starts) with a deterministic policy; episode lengths in seconds.
    With ``frames`` (a list), the first episode's rendered frames are appended to it."""
    lengths = []
    for e in range(episodes):
        obs, _ = env.reset(seed=seed + e)
        done, steps = False, 0
        while not done:
            o = normalize.normalize_obs(obs[None]) if normalize is not None else obs[None]
            action, _ = policy.predict(o, deterministic=True)
            obs, _, term, trunc, info = env.step(action[0])
            steps += 1
            done = term or trunc
            if frames is not None and e == 0:
                frames.append(env.render())
        lengths.append(steps / env.cfg.control_hz)
    return np.array(lengths)


def evaluate(checkpoint: str | Path, *, episodes: int = 32, video: bool = True, device: str = "cpu",
             seed: int = 10_000, video_backend: str = "auto") -> Path:
    """The paper's table (success / failure rate, episode lengths) over ``episodes`` random-start
    episodes and an MP4 of the first; writes ``eval.json`` (and ``eval.mp4``) in the run folder.

    ``video_backend``: ``mujoco`` (offscreen OpenGL), ``raycast`` (the package's ray caster, no
    OpenGL), or ``auto``: MuJoCo's, falling back to the ray caster when OpenGL is not available
    (``eval.json`` records the backend used and why it fell back)."""
    sb3 = require("stable_baselines3", "sim")
    from stable_baselines3.common.vec_env import VecNormalize

    from embodmocap.sim.env import TrackingEnv, load_clips, tracking_table

    checkpoint = Path(checkpoint)
    if not checkpoint.is_file():
        raise InputError(checkpoint, "checkpoint not found", "give a policy zip written by `embodmocap sim train`")
    run = _run_folder(checkpoint)
    info = json.loads((run / "run.json").read_text())
    tcfg = _tracking_from_dict(info["config"]["tracking"])
    clips = load_clips([Path(s) for s in info["sessions"]], info.get("seq"), tcfg)
    env = TrackingEnv(clips=clips, config=tcfg, render_mode="rgb_array" if video else None)
    policy = sb3.PPO.load(checkpoint, device=device)
    stats = _stats_for(checkpoint, run)
    normalize = None
    if stats is not None:
        from stable_baselines3.common.vec_env import DummyVecEnv

        normalize = VecNormalize.load(str(stats), DummyVecEnv([lambda: TrackingEnv(clips=clips, config=tcfg)]))
        normalize.training = False
    frames: list | None = [] if video else None
    video_error = None
    if video and video_backend == "raycast":
        env.render_backend = "raycast"
    elif video:
        try:
            env.reset(seed=seed)
            env.render()
        except Exception as err:  # noqa: BLE001 - no OpenGL here: the ray caster, or the table alone
            video_error = f"MuJoCo offscreen rendering failed ({type(err).__name__}: {err}); set MUJOCO_GL=egl or osmesa"
            log.warning("%s", video_error)
            if video_backend == "auto":
                env.render_backend = "raycast"
                log.warning("drawing the video with the package's ray caster instead")
            else:
                frames = None
    lengths = rollout_lengths(policy, env, normalize, episodes, seed, frames)
    table = tracking_table(lengths, tcfg.success_s)
    doc = {"version": 1, "checkpoint": str(checkpoint), "episode_s": tcfg.episode_s, **table,
           "lengths_s": lengths.tolist()}
    if frames:
        doc["video"] = str(_write_video(run / "eval.mp4", frames, tcfg.control_hz))
        doc["video_backend"] = env.render_backend
    if video_error:
        doc["video_error"] = video_error
    write_json(run / "eval.json", doc)
    env.close()
    log.info("eval: success %.1f %%, failure %.1f %% over %d episodes", table["success_rate"], table["failure_rate"], episodes)
    return run / "eval.json"


def _write_video(path: Path, frames: list, fps: float) -> Path:
    from embodmocap.io.video import VideoWriter

    h, w = frames[0].shape[:2]
    with VideoWriter(path, fps, w - w % 2, h - h % 2) as writer:
        for f in frames:
            writer.write(np.ascontiguousarray(f[: h - h % 2, : w - w % 2]))
    return path
