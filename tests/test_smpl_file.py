"""World SMPL motion files: round trip and every bad-input case."""

from __future__ import annotations

import numpy as np
import pytest

from embodmocap.errors import InputError
from embodmocap.io.smpl_file import read_smpl_npz, write_smpl_npz
from embodmocap.types import SmplParams


def _params(T=5, seed=0) -> SmplParams:
    rng = np.random.default_rng(seed)
    return SmplParams(rng.normal(size=10), rng.normal(size=(T, 3)), 0.1 * rng.normal(size=(T, 69)),
                      rng.normal(size=(T, 3)), fps=29.97, gender="female")


def test_round_trip(tmp_path):
    p = _params()
    path = write_smpl_npz(tmp_path / "m.npz", p, frames=np.arange(10, 15))
    q, frames = read_smpl_npz(path)
    for k in ("betas", "global_orient", "body_pose", "transl"):
        np.testing.assert_array_equal(getattr(q, k), getattr(p, k))
    assert q.fps == 29.97 and q.gender == "female"
    np.testing.assert_array_equal(frames, np.arange(10, 15))
    # AMASS key names, so AMASS readers take the file as it is.
    with np.load(path) as z:
        assert {"poses", "trans", "betas", "gender", "mocap_framerate"} <= set(z.files)
        assert z["poses"].shape == (5, 72)


def test_bad_files(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_smpl_npz(tmp_path / "nope.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="not a readable npz"):
        read_smpl_npz(tmp_path / "junk.npz")
    np.savez(tmp_path / "keys.npz", poses=np.zeros((3, 72)))
    with pytest.raises(InputError, match="keys .* missing"):
        read_smpl_npz(tmp_path / "keys.npz")
    np.savez(tmp_path / "shape.npz", poses=np.zeros((3, 66)), trans=np.zeros((3, 3)), betas=np.zeros(10),
             gender="neutral", mocap_framerate=30.0, frames=np.arange(3))
    with pytest.raises(InputError, match="SMPL layout"):
        read_smpl_npz(tmp_path / "shape.npz")
    np.savez(tmp_path / "nan.npz", poses=np.full((3, 72), np.nan), trans=np.zeros((3, 3)), betas=np.zeros(10),
             gender="neutral", mocap_framerate=30.0, frames=np.arange(3))
    with pytest.raises(InputError, match="non-finite"):
        read_smpl_npz(tmp_path / "nan.npz")
    with pytest.raises(ValueError, match="frames"):
        write_smpl_npz(tmp_path / "x.npz", _params(), frames=np.arange(4))
