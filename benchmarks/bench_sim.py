"""Issue 16: the simulation package's figures.

1. ``sim check`` on the studio's ground-truth motion (in the true scene mesh) vs our fit (in the
   Stage I mesh of the same session, and, as an oracle row, in the true mesh placed by the studio's
   true ``T_scene_vio``), per seed: penetration, floating, foot skating, residual root force. Sessions: folders with Stages I-IV done and a ``ground_truth/`` (the studio's), read only.
2. ``sim check`` time for a 60 s sequence (the first session's fit tiled to 60 s at its frame rate).
3. Tracking environment steps/s: one environment, and vectorised (Gymnasium sync and async
   vector environments, one process per environment for async) with random actions.

    OMP_NUM_THREADS=1 PYTHONPATH=src .venv/bin/python benchmarks/bench_sim.py \
        --sessions /work/bench/16/fits/hard_{0,1,2,3,4} --json /work/bench/16/bench_sim.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

KEYS = ("penetration_max_cm", "penetration_mean_cm", "floating_max_cm", "floating_mean_cm", "foot_skating_mean_cm",
        "residual_force_n_per_kg_mean", "residual_torque_nm_per_kg_mean")


def truth_sequence(session: Path):
    """The studio's true motion (all motion frames) in its true scene mesh, as a SimSequence."""
    from embodmocap.io.mesh_file import read_mesh_ply
    from embodmocap.sim.session import SimSequence, load_sequence
    from embodmocap.types import SmplParams

    fit = load_sequence(session)
    gt_dir = session / "ground_truth"
    info = json.loads((gt_dir / "ground_truth.json").read_text())
    gt = np.load(gt_dir / f"seq_{info['sequence']}.npz")
    params = SmplParams(gt["betas"], gt["global_orient"], gt["body_pose"], gt["transl"], fps=float(info["config"]["fps"]))
    v, f, _ = read_mesh_ply(gt_dir / f"scene_{info['scene']}_mesh.ply")
    return SimSequence(session, fit.name, params, np.arange(len(params)), fit.body_model, np.asarray(v, float),
                       np.asarray(f, np.int64)), fit


def fit_in_true_mesh(truth, fit):
    """Oracle: our fit in the true scene mesh placed in the fit's world by the studio's true
    ``T_scene_vio`` (so only the motion's error counts, not the scan's holes)."""
    from embodmocap.geometry.transforms import invert_T
    from embodmocap.sim.session import SimSequence

    T = invert_T(np.load(fit.session / "ground_truth" / "scene_scene0_device.npz")["T_scene_vio"])
    v = truth.scene_vertices @ T[:3, :3].T + T[:3, 3]
    return SimSequence(fit.session, fit.name, fit.params, fit.frames, fit.body_model, v, truth.scene_faces)


def make_sessions(sessions: list[Path]) -> None:
    """Synthesise (if missing) and fit each session folder named ``hard_<seed>`` like issue 11's
    hard sessions: indoor, 6 s at 30 fps, 15 s scene scan, hard perception, Stages I-IV with their
    default settings (each stage resumes: a finished one is skipped)."""
    from embodmocap.calibrate import stage as stage3
    from embodmocap.motion import stage as stage4
    from embodmocap.scene import stage as stage1
    from embodmocap.scene.config import SceneConfig
    from embodmocap.sequence import stage as stage2
    from embodmocap.sequence.config import SequenceConfig
    from embodmocap.synth.config import SynthConfig
    from embodmocap.synth.studio import synthesize

    for s in sessions:
        seed = int(s.name.rsplit("_", 1)[-1])
        if not (s / "ground_truth" / "ground_truth.json").is_file():
            synthesize(SynthConfig(seed=seed, preset="indoor", seconds=6.0, scene_seconds=15.0, perception="hard"), s)
        stage1.run(SceneConfig(), s)
        stage2.run(SequenceConfig(), s)
        stage3.run(stage3.CalibrateConfig(), s)
        stage4.run(stage4.MotionConfig(), s)
        print(f"made {s}", flush=True)


def check_rows(sessions: list[Path]) -> list[dict]:
    from embodmocap.sim.check import plausibility

    rows = []
    for s in sessions:
        truth, fit = truth_sequence(s)
        for kind, sq in (("truth", truth), ("fit", fit), ("fit_true_mesh_oracle", fit_in_true_mesh(truth, fit))):
            summ = plausibility(sq)["summary"]
            rows.append({"session": s.name, "kind": kind, "frames": summ["frames"], "seconds": summ["seconds"],
                         "unsupported_frames": summ["unsupported_frames"],
                         **{k: summ[k] for k in KEYS}, "contact_fraction": summ["contact_fraction"]})
            print(json.dumps({k: (round(v, 3) if isinstance(v, float) else v) for k, v in rows[-1].items()
                              if k != "contact_fraction"}), flush=True)
    return rows


def check_time_60s(session: Path) -> dict:
    from embodmocap.sim.check import plausibility
    from embodmocap.sim.config import SimCheckConfig
    from embodmocap.sim.session import load_sequence

    sq = load_sequence(session)
    p = sq.params
    reps = int(np.ceil(60.0 * p.fps / len(p)))
    idx = np.tile(np.arange(len(p)), reps)[: int(round(60.0 * p.fps))]
    long = sq.with_params(dataclasses.replace(p, global_orient=p.global_orient[idx], body_pose=p.body_pose[idx],
                                              transl=p.transl[idx]))
    out = {"frames": int(len(idx)), "fps": float(p.fps), "vertices": int(sq.body_model.num_vertices)}
    for stride in (1, 4):
        t0 = time.perf_counter()
        plausibility(long, SimCheckConfig(vertex_stride=stride))
        out[f"seconds_stride_{stride}"] = time.perf_counter() - t0
    return out


def env_speed(session: Path, steps: int, num_envs: int) -> dict:
    import gymnasium as gym

    import embodmocap.sim
    from embodmocap.sim.env import TrackingEnv, load_clips

    clips = load_clips(session)
    env = TrackingEnv(clips=clips)
    env.reset(seed=0)
    t0 = time.perf_counter()
    for _ in range(steps):
        _, _, term, trunc, _ = env.step(env.action_space.sample())
        if term or trunc:
            env.reset()
    out = {"single_steps_per_s": steps / (time.perf_counter() - t0)}
    for mode in ("sync", "async"):
        envs = gym.make_vec(embodmocap.sim.ENV_ID, num_envs=num_envs, vectorization_mode=mode, clips=clips)
        envs.reset(seed=0)
        n = max(steps // num_envs, 1)
        t0 = time.perf_counter()
        for _ in range(n):
            envs.step(envs.action_space.sample())  # vector envs reset finished episodes themselves
        out[f"{mode}_{num_envs}_steps_per_s"] = n * num_envs / (time.perf_counter() - t0)
        envs.close()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=Path, nargs="+", required=True)
    ap.add_argument("--steps", type=int, default=3000, help="environment steps per speed measurement")
    ap.add_argument("--num-envs", type=int, default=2)
    ap.add_argument("--skip", nargs="*", default=[], choices=["check", "time", "env"])
    ap.add_argument("--profile", action="store_true", help="print where the 60 s check spends its time")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--make", action="store_true",
                    help="first synthesise and fit the sessions (folders named hard_<seed>) that are not done")
    a = ap.parse_args()
    if a.make:
        make_sessions(a.sessions)
    res: dict = {"date": time.strftime("%Y-%m-%d"), "sessions": [str(s) for s in a.sessions]}
    if "env" not in a.skip:
        res["env"] = env_speed(a.sessions[0], a.steps, a.num_envs)
        print(json.dumps(res["env"]), flush=True)
    if "time" not in a.skip:
        res["check_60s"] = check_time_60s(a.sessions[0])
        print(json.dumps(res["check_60s"]), flush=True)
    if "check" not in a.skip:
        rows = check_rows(a.sessions)
        res["check"] = rows
        for kind in ("truth", "fit", "fit_true_mesh_oracle"):
            sel = [r for r in rows if r["kind"] == kind]
            res[f"{kind}_mean"] = {k: float(np.mean([r[k] for r in sel])) for k in KEYS}
            print(kind, json.dumps({k: round(v, 3) for k, v in res[f"{kind}_mean"].items()}), flush=True)
    if a.json:
        a.json.write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
