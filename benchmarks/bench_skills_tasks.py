"""Issue 17 (tasks): speed of the six skills' task observation, reward and success, batched.

Per skill, the time of one call of ``observe``, ``reward`` and ``success``
(:mod:`embodmocap.skills.tasks`) for a batch of ``--envs`` (4,096) environments in random states
around a bed-sized box: numpy float64, torch float32 on the CPU and, when there is one, torch
float32 on CUDA (synchronised). Median of ``--repeats`` calls after a warm-up. Optionally
(``--session``, a session with skills.json) the steps per second of one ``EmbodMocap/Skill-sit-v0``
environment with random actions, for scale.

    OMP_NUM_THREADS=1 PYTHONPATH=src .venv/bin/python benchmarks/bench_skills_tasks.py \
        --envs 4096 --json /work/bench/17t/bench_skills_tasks.json [--session /work/bench/17t/s0]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation


def random_batch(n: int, seed: int = 0):
    """(CharacterState, SkillGoal) of n environments, numpy float64, world frame."""
    from embodmocap.skills.tasks import CharacterState, SkillGoal

    rng = np.random.default_rng(seed)
    center, size, yaw = np.array([1.0, 2.0, 0.25]), np.array([1.9, 0.9, 0.5]), 0.4
    R = Rotation.from_euler("z", yaw).as_matrix()
    signs = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1], [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]])
    corners = center + (signs * size / 2) @ R.T
    tile = lambda a: np.broadcast_to(np.asarray(a, float), (n,) + np.shape(a)).copy()  # noqa: E731
    root = center + rng.normal(scale=1.5, size=(n, 3)) * [1, 1, 0.2] + [0, 0, 0.7]
    s = CharacterState(root_pos=root, root_rot=Rotation.random(n, random_state=seed).as_matrix(),
                       root_vel=rng.normal(size=(n, 3)), head_pos=root + [0, 0, 0.6],
                       hand_pos=root[:, None] + rng.normal(scale=0.3, size=(n, 2, 3)),
                       foot_pos=root[:, None] - [0, 0, 0.9] + rng.normal(scale=0.1, size=(n, 2, 3)))
    path = np.stack([np.linspace(0, 10, 101), np.sin(np.linspace(0, 5, 101))], -1)
    g = SkillGoal(target=tile(center + [0, 0, 0.37]), box_center=tile(center), box_rot=tile(R), box_corners=tile(corners),
                  long_axis=tile(R[:2, 0]), stand_point=tile(center + [1.2, 0, 0.65]), stand_z=tile(0.93),
                  ground_z=tile(0.0), path=path, time_s=rng.uniform(0, 10, n))
    return s, g


def convert(s, g, lib: str, device: str):
    from embodmocap.skills.tasks import CharacterState, SkillGoal

    if lib == "numpy":
        return s, g
    import torch

    t = lambda a: None if a is None else torch.as_tensor(np.asarray(a), dtype=torch.float32, device=device)  # noqa: E731
    return CharacterState(**{k: t(v) for k, v in vars(s).items()}), SkillGoal(**{k: t(v) for k, v in vars(g).items()})


def time_call(fn, repeats: int, sync) -> float:
    for _ in range(3):
        fn()
    sync()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        sync()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def env_steps_per_s(session: Path, seconds: float = 5.0) -> float:
    from embodmocap.sim.skill_env import SkillEnv

    env = SkillEnv(session=session, skill="sit")
    env.reset(seed=0)
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        _, _, term, trunc, _ = env.step(env.action_space.sample())
        n += 1
        if term or trunc:
            env.reset()
    return n / (time.perf_counter() - t0)


def main() -> None:
    from embodmocap.skills import tasks

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--envs", type=int, default=4096)
    ap.add_argument("--repeats", type=int, default=50)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--session", type=Path, default=None)
    args = ap.parse_args()
    s, g = random_batch(args.envs)
    backends = [("numpy", "cpu")]
    try:
        import torch

        backends.append(("torch", "cpu"))
        if torch.cuda.is_available():
            backends.append(("torch", "cuda"))
    except ImportError:
        torch = None
    rows = []
    for lib, device in backends:
        S, G = convert(s, g, lib, device)
        sync = (lambda: torch.cuda.synchronize()) if device == "cuda" else (lambda: None)
        for skill in tasks.SKILLS:
            row = {"backend": f"{lib}/{device}", "skill": skill, "envs": args.envs}
            for name, fn in (("observe", tasks.observe), ("reward", tasks.reward), ("success", tasks.success)):
                row[f"{name}_ms"] = 1e3 * time_call(lambda: fn(skill, S, G), args.repeats, sync)
            rows.append(row)
            print(f"{row['backend']:10s} {skill:8s} observe {row['observe_ms']:7.3f} ms  reward {row['reward_ms']:7.3f} ms"
                  f"  success {row['success_ms']:7.3f} ms  (per {args.envs} envs)")
    out = {"version": 1, "envs": args.envs, "repeats": args.repeats, "rows": rows}
    if args.session is not None:
        out["sit_env_steps_per_s"] = env_steps_per_s(args.session)
        print(f"Skill-sit-v0, one environment, random actions: {out['sit_env_steps_per_s']:.0f} steps/s")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
