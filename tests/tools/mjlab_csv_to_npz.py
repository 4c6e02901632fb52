"""Run mjlab's own ``csv_to_npz`` conversion on a BeyondMimic CSV, on the CPU, without uploading.

Run with a Python where ``mjlab`` imports (its own environment: ``./run setup-mjlab`` makes
``.venv-mjlab``); used by tests/test_robot_mjlab.py. Usage::

    python mjlab_csv_to_npz.py MOTION.csv FPS OUT.npz JOINT_NAME...

The script's ``run_sim`` writes ``/tmp/motion.npz`` and then logs it to Weights & Biases (a network
service); the upload is replaced by a module that does nothing, everything else is mjlab's code.
"""

from __future__ import annotations

import shutil
import sys
import types


class _NoUpload(types.ModuleType):
    """What ``run_sim`` calls on ``wandb`` after it has saved the npz: nothing happens."""

    def __init__(self) -> None:
        super().__init__("wandb")

    def init(self, **kw):
        return types.SimpleNamespace(log_artifact=lambda **k: None, link_artifact=lambda **k: None)

    def log(self, *a, **k):
        return None

    def finish(self):
        return None


def main(argv: list[str]) -> None:
    csv, fps, out, joints = argv[0], float(argv[1]), argv[2], argv[3:]
    sys.modules["wandb"] = _NoUpload()
    from mjlab.scene import Scene
    from mjlab.scripts import csv_to_npz
    from mjlab.sim.sim import Simulation, SimulationCfg
    from mjlab.tasks.tracking.config.g1.env_cfgs import unitree_g1_flat_tracking_env_cfg

    sim_cfg = SimulationCfg()
    sim_cfg.mujoco.timestep = 1.0 / 50.0  # the script's own setting for its 50 fps output
    scene = Scene(unitree_g1_flat_tracking_env_cfg().scene, device="cpu")
    sim = Simulation(num_envs=1, cfg=sim_cfg, model=scene.compile(), device="cpu")
    scene.initialize(sim.mj_model, sim.model, sim.data)
    csv_to_npz.run_sim(sim=sim, scene=scene, joint_names=joints, input_file=csv, input_fps=fps,
                       output_fps=50.0, output_name="embodmocap-test", render=False, line_range=None)
    shutil.move("/tmp/motion.npz", out)


if __name__ == "__main__":
    main(sys.argv[1:])
