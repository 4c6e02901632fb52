"""Outputs that the rotation refactor (issue 32 item 5) must not change, old source against new.

Runs the same script under two source trees (each in its own process, the tests folder beside it
for the tiny studio session) and prints the largest difference of every output: the tracking
environment's observations, rewards and assist forces over 15 steps, AMP features, the reference
clip's angular velocities, the robot exports (tracking npz arrays, BeyondMimic CSV, GMR pkl), the
training export's resampled motion, pose interpolation, rotation_between and the Stage I
correction. Needs the sim and robot extras.

    python benchmarks/compare_rotation_outputs.py --old-src /work/base-src/src
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

CHILD = r'''
import sys, pickle
from pathlib import Path
import numpy as np
out = {}
rng = np.random.default_rng(0)
session = Path(sys.argv[2])
if not session.exists():
    from stage4_session import make_stage4_session
    make_stage4_session(session)
from embodmocap.sim.env import TrackingEnv, load_clips
from embodmocap.sim.config import TrackingConfig
clips = load_clips(session)
env = TrackingEnv(clips=clips, config=TrackingConfig(root_assist=True))
obs, _ = env.reset(seed=0, options={"start": 0})
o, r, x = [obs], [], []
for k in range(15):
    a = rng.uniform(-0.3, 0.3, env.action_space.shape)
    ob, rew, term, trunc, info = env.step(a)
    o.append(ob); r.append(rew); x.append(env.data.xfrc_applied[1].copy())
    if term or trunc: break
out["env_obs"], out["env_rew"], out["env_xfrc"] = np.array(o), np.array(r), np.array(x)
from embodmocap.sim.amp import amp_frame_features
cl = clips[0]
out["amp"] = amp_frame_features(cl.qpos, cl.qvel, cl.xpos, 0.0)
out["clip_angvel"] = cl.angvel; out["clip_qpos"] = cl.qpos
from embodmocap.robot.g1 import G1
from embodmocap.robot.model import RobotModel
from embodmocap.robot import files as rf
robot = RobotModel.load(G1)
T = 40
lo, hi = robot.joint_range.T
t = np.linspace(0, 1, T)[:, None]
J = lo + (hi - lo) * (0.5 + 0.3 * np.sin(2 * np.pi * t * rng.uniform(0.5, 2, len(lo))))
ang = np.cumsum(rng.normal(0, 0.05, (T, 3)), 0)
from scipy.spatial.transform import Rotation
qx = Rotation.from_rotvec(ang).as_quat()
quat = qx[:, [3, 0, 1, 2]]
pos = np.cumsum(rng.normal(0, 0.01, (T, 3)), 0) + [0, 0, 0.8]
qpos = robot.qpos(pos, quat, J)
for k, v in rf.tracking_arrays(robot, qpos, 30.0, 50.0).items():
    out["track_" + k] = v
out["csv"] = rf.csv_rows(robot, qpos)
gmr = Path(sys.argv[1]).with_suffix(".pkl")
rf.write_gmr_pkl(gmr, robot, qpos, 30.0)
d = pickle.load(open(gmr, "rb"))
out["gmr_local"], out["gmr_root_rot"] = d["local_body_pos"], d["root_rot"]
from embodmocap.export.training import resample_motion
poses = rng.normal(0, 0.5, (20, 72)); tr = rng.normal(0, 1, (20, 3))
res = resample_motion(poses, tr, np.arange(20) / 10.0, np.linspace(-0.05, 2.0, 33))
out["train_poses"], out["train_transl"] = res[0], res[1]
from embodmocap.geometry.interpolate import interp_poses
Ts = np.tile(np.eye(4), (10, 1, 1)); Ts[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 1, (10, 3))).as_matrix(); Ts[:, :3, 3] = rng.normal(size=(10, 3))
out["interp"] = interp_poses(Ts, np.arange(10.0), np.linspace(-1, 10, 40))[0]
from embodmocap.sim.model import params_from_qpos, reference_qpos
from embodmocap.geometry.similarity import rotation_between
out["rb"] = np.array([rotation_between(a, b) for a, b in zip(rng.normal(size=(20, 3)), rng.normal(size=(20, 3)))] + [rotation_between(np.array([0, 0, 1.0]), np.array([0, 0, -1.0]))])
from embodmocap.scene.adjust import apply_correction
out["adjust"] = apply_correction(rng.normal(0, 0.1, (5, 6)), Ts[:5], np.array([0.1, 0.2, 0.3]))
np.savez(sys.argv[1], **out)
print("ok", len(out))
'''


def _outputs(src: Path, out: Path, session: Path) -> dict:
    tests = src.parent / "tests"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(src), str(tests)])}
    subprocess.run([sys.executable, "-c", CHILD, str(out), str(session)], check=True, env=env, cwd=tests)
    return dict(np.load(out))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old-src", type=Path, required=True, help="the baseline's src folder (its tests/ beside it)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        session = Path(tmp) / "session"
        old = _outputs(args.old_src.resolve(), Path(tmp) / "old.npz", session)
        new = _outputs(ROOT / "src", Path(tmp) / "new.npz", session)
    print("| output | shape | max abs difference | identical |\n|---|---|---|---|")
    for k in old:
        a, b = old[k].astype(np.float64), new[k].astype(np.float64)
        print(f"| {k} | {a.shape} | {np.max(np.abs(a - b)) if a.size else 0.0:.3g} | {np.array_equal(a, b)} |")


if __name__ == "__main__":
    main()
