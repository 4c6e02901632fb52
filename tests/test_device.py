"""``--device``: auto / cpu / cuda for Stage IV's fit; ``cuda`` without CUDA is one clear error.

Without a GPU the device code path runs on the CPU device (the same code with device="cpu"):
``test_smplify_device_cpu_is_the_default_fit`` checks that the fit on an explicit CPU device and
through ``auto`` is the same answer. The GPU itself is checked by ``benchmarks/gpu_check.sh``.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from embodmocap.cli import main
from embodmocap.device import motion_on_device, resolve_device
from embodmocap.errors import InputError
from embodmocap.motion.config import MotionConfig

no_cuda = pytest.mark.skipif(torch.cuda.is_available(), reason="checks the machine without CUDA")


def test_resolve_device():
    assert resolve_device("cpu") == "cpu"
    assert resolve_device("auto") == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(InputError, match="unknown device 'gpu'"):
        resolve_device("gpu")


@no_cuda
def test_cuda_without_cuda_is_one_clear_error():
    with pytest.raises(InputError, match="--device cuda asks for a GPU") as err:
        resolve_device("cuda")
    assert "--device cpu" in str(err.value)
    with pytest.raises(InputError, match="--device cuda"):
        motion_on_device(MotionConfig(), "cuda")


@no_cuda
@pytest.mark.parametrize("command", ["motion", "run"])
def test_cli_device_cuda_without_cuda(command, tmp_path, capsys):
    """Before any stage runs or the session is even looked at: exit status 2, one line."""
    status = main([command, str(tmp_path / "no_session"), "--device", "cuda"])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2
    assert len(err) == 1 and err[0].startswith("error: --device cuda asks for a GPU"), err


def test_motion_on_device_sets_the_fit_device():
    cfg = MotionConfig()
    assert motion_on_device(cfg, None) is cfg
    assert motion_on_device(cfg, "cpu").smplify.device == "cpu"
    assert motion_on_device(cfg, "cpu").smplify.phase2_iterations == cfg.smplify.phase2_iterations
