"""The studio's hard camera preset: VIO errors that grow with the path (synth.vio)."""

from __future__ import annotations

import numpy as np
import pytest

from embodmocap.geometry.transforms import look_at_T
from embodmocap.synth.config import SynthConfig
from embodmocap.synth.vio import HARD_VIO, VioErrorConfig, add_path_errors


def walk(n=300, length_m=6.0):
    """A camera walking a straight line of ``length_m`` at 1.4 m height, looking ahead."""
    x = np.linspace(0.0, length_m, n)
    return np.stack([look_at_T(np.array([xi, 0.0, 1.4]), np.array([xi + 1.0, 0.3, 1.2])) for xi in x])


def test_scale_error_stretches_the_path_from_the_first_frame():
    T = walk()
    out = add_path_errors(T, np.random.default_rng(0), VioErrorConfig(scale_error_percent=(2.0, 2.0)))
    np.testing.assert_allclose(out[0], T[0])
    d_true = np.linalg.norm(T[:, :3, 3] - T[0, :3, 3], axis=1)
    d_out = np.linalg.norm(out[:, :3, 3] - out[0, :3, 3], axis=1)
    assert np.allclose(d_out[1:] / d_true[1:], 1.02) or np.allclose(d_out[1:] / d_true[1:], 0.98)
    np.testing.assert_allclose(out[:, :3, :3], T[:, :3, :3])  # no yaw drift asked for


@pytest.mark.parametrize("pct", [0.5, 2.0])
def test_drift_grows_with_the_path_walked(pct):
    T = walk()
    ends = []
    for seed in range(40):
        out = add_path_errors(T, np.random.default_rng(seed), VioErrorConfig(drift_percent_of_path=(pct, pct)))
        err = np.linalg.norm(out[:, :3, 3] - T[:, :3, 3], axis=1)
        assert err[0] == 0
        ends.append(err[-1])
    # after 6 m: of the order of pct % of 6 m (the direction wanders, so somewhat less on average)
    assert 0.2 * pct / 100 * 6.0 < np.median(ends) < 1.2 * pct / 100 * 6.0, np.median(ends)


def test_yaw_drift_turns_the_cameras():
    T = walk()
    out = add_path_errors(T, np.random.default_rng(1), VioErrorConfig(yaw_drift_deg_per_m=(0.3, 0.3)))
    R = np.einsum("nji,njk->nik", T[:, :3, :3], out[:, :3, :3])
    yaw = np.degrees(np.abs(np.arctan2(R[:, 1, 0], R[:, 0, 0])))
    assert yaw[0] < 1e-9 and 0.05 < yaw.max() < 0.3 * 6.0


def test_presets():
    assert not SynthConfig().vio_errors().active
    assert SynthConfig(cameras="hard").vio_errors() == HARD_VIO
    own = VioErrorConfig(scale_error_percent=(0.5, 0.5))
    assert SynthConfig(cameras="hard", vio=own).vio_errors() == own
    T = walk(50)
    np.testing.assert_array_equal(add_path_errors(T, np.random.default_rng(0), VioErrorConfig()), T)
