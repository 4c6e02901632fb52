"""embodmocap.io.open3d_core: Open3D without its ML package (and scikit-learn), still fusing."""

from __future__ import annotations

import subprocess
import sys

import pytest

pytest.importorskip("open3d")

# A fresh interpreter: in the test process Open3D may already be imported whole.
_SCRIPT = """
import sys
import numpy as np
from embodmocap.io.open3d_core import open3d as o3d
assert "sklearn" not in sys.modules, "scikit-learn was imported"
import open3d
assert open3d is o3d
# A plane at z = 1 m seen by one camera fuses into a mesh at z = 1 m (Open3D's pipelines work).
from embodmocap.scene.tsdf import fuse_open3d
from embodmocap.types import Intrinsics
K = Intrinsics(fx=100.0, fy=100.0, cx=32.0, cy=24.0, width=64, height=48)
depth = np.ones((48, 64), np.float32)
rgb = np.full((48, 64, 3), 200, np.uint8)
v, f, c = fuse_open3d([(rgb, depth, K, np.eye(4))], 0.02, 0.1, 3.0)
assert len(f) > 100 and abs(np.median(v[:, 2]) - 1.0) < 0.01, (len(f), np.median(v[:, 2]))
print("ok")
"""


def test_open3d_without_ml_imports_no_sklearn_and_fuses():
    out = subprocess.run([sys.executable, "-c", _SCRIPT], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().endswith("ok")
