"""Our BeyondMimic CSV through mjlab's own ``csv_to_npz`` gives our tracking npz (same bodies, 1 mm).

mjlab cannot share the project's environment (its pins clash with ours: mujoco 3.11, protobuf >= 6,
NVIDIA warp), so it lives in its own: ``./run setup-mjlab`` makes ``.venv-mjlab`` (``./run
test-slow`` does it too), and the conversion runs there as a separate process
(tests/tools/mjlab_csv_to_npz.py, mjlab's code on warp's CPU device). ``EMBODMOCAP_MJLAB_PYTHON``
names another interpreter with mjlab; without one the test is skipped with that reason.
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]


def _mjlab_python() -> str:
    exe = os.environ.get("EMBODMOCAP_MJLAB_PYTHON") or str(ROOT / ".venv-mjlab" / "bin" / "python")
    if not Path(exe).is_file():
        pytest.skip(f"no Python with mjlab ({exe} missing): run `./run setup-mjlab` or set EMBODMOCAP_MJLAB_PYTHON")
    probe = subprocess.run([exe, "-c", "import mjlab.scripts.csv_to_npz"], capture_output=True, text=True)
    if probe.returncode != 0:
        pytest.skip(f"mjlab does not import with {exe}: {probe.stderr.strip().splitlines()[-1:]}")
    return exe


def test_mjlab_csv_to_npz_reproduces_our_tracking_npz(tmp_path):
    exe = _mjlab_python()
    from embodmocap.robot.stage import retarget_sequence
    from stage4_session import make_stage4_session
    from test_robot import MJLAB_G1_JOINTS

    make_stage4_session(tmp_path / "s")
    out = retarget_sequence(tmp_path / "s")
    with np.load(out / "qpos.npz") as z:
        fps = float(z["fps"])
    ours = dict(np.load(out / "motion.npz"))
    theirs_path = tmp_path / "theirs.npz"
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    run = subprocess.run([exe, str(ROOT / "tests" / "tools" / "mjlab_csv_to_npz.py"), str(out / "motion.csv"),
                          str(fps), str(theirs_path), *MJLAB_G1_JOINTS],
                         capture_output=True, text=True, env=env, timeout=1800)
    assert run.returncode == 0, run.stderr[-3000:]
    theirs = dict(np.load(theirs_path))
    # Same frames (both resample to 50 fps), same bodies in the same (MuJoCo depth-first) order.
    assert theirs["body_pos_w"].shape == ours["body_pos_w"].shape
    np.testing.assert_allclose(theirs["body_pos_w"], ours["body_pos_w"], atol=1e-3)
    dots = np.abs(np.sum(theirs["body_quat_w"] * ours["body_quat_w"], axis=-1))
    np.testing.assert_allclose(dots, 1.0, atol=1e-5)
    np.testing.assert_allclose(theirs["joint_pos"], ours["joint_pos"], atol=1e-5)
    np.testing.assert_allclose(theirs["joint_vel"], ours["joint_vel"], atol=1e-3)
    np.testing.assert_allclose(theirs["body_lin_vel_w"], ours["body_lin_vel_w"], atol=2e-2)
