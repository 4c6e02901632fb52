"""Our BeyondMimic CSV through mjlab's own ``csv_to_npz`` gives our tracking npz (same bodies, 1 mm).

mjlab cannot be installed in the project's environment (its pins clash with ours and it needs
NVIDIA warp), so this test runs only where ``mjlab.scripts.csv_to_npz`` imports (e.g. a separate
venv with ``pip install mjlab`` plus this package) and is skipped, with that reason, elsewhere.
Its only stand-in is for the Weights & Biases upload at the end of the script (a network service):
the script's own ``run_sim`` does the conversion and writes ``/tmp/motion.npz``, which we read.
"""

from __future__ import annotations

import sys
import types
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.slow


def _csv_to_npz():
    try:
        from mjlab.scripts import csv_to_npz
    except Exception as err:  # noqa: BLE001 - mjlab raises more than ImportError without warp
        pytest.skip(f"mjlab does not import here ({type(err).__name__}: {err}); run this test in an "
                    "environment where `pip install mjlab` succeeded")
    return csv_to_npz


class _NoUpload(types.ModuleType):
    """What run_sim calls on ``wandb`` after it has saved the npz: nothing happens."""

    def __init__(self) -> None:
        super().__init__("wandb")

    def init(self, **kw):
        return types.SimpleNamespace(log_artifact=lambda **k: None, link_artifact=lambda **k: None)

    def log(self, *a, **k):
        return None

    def finish(self):
        return None


def test_mjlab_csv_to_npz_reproduces_our_tracking_npz(tmp_path, monkeypatch):
    tool = _csv_to_npz()
    from embodmocap.robot.stage import retarget_sequence
    from stage4_session import make_stage4_session

    make_stage4_session(tmp_path / "s")
    out = retarget_sequence(tmp_path / "s")
    with np.load(out / "qpos.npz") as z:
        fps = float(z["fps"])
    ours = dict(np.load(out / "motion.npz"))

    from mjlab.scene import Scene
    from mjlab.sim.sim import Simulation, SimulationCfg
    from mjlab.tasks.tracking.config.g1.env_cfgs import unitree_g1_flat_tracking_env_cfg

    monkeypatch.setitem(sys.modules, "wandb", _NoUpload())
    sim_cfg = SimulationCfg()
    sim_cfg.mujoco.timestep = 1.0 / 50.0
    scene = Scene(unitree_g1_flat_tracking_env_cfg().scene, device="cpu")
    sim = Simulation(num_envs=1, cfg=sim_cfg, model=scene.compile(), device="cpu")
    scene.initialize(sim.mj_model, sim.model, sim.data)
    from test_robot import MJLAB_G1_JOINTS

    Path("/tmp/motion.npz").unlink(missing_ok=True)
    tool.run_sim(sim=sim, scene=scene, joint_names=MJLAB_G1_JOINTS, input_file=str(out / "motion.csv"),
                 input_fps=fps, output_fps=50.0, output_name="embodmocap-test", render=False, line_range=None)
    theirs = dict(np.load("/tmp/motion.npz"))
    assert theirs["body_pos_w"].shape == ours["body_pos_w"].shape
    np.testing.assert_allclose(theirs["body_pos_w"], ours["body_pos_w"], atol=1e-3)
    dots = np.abs(np.sum(theirs["body_quat_w"] * ours["body_quat_w"], axis=-1))
    np.testing.assert_allclose(dots, 1.0, atol=1e-5)
    np.testing.assert_allclose(theirs["joint_pos"], ours["joint_pos"], atol=1e-5)
