"""Metrics (pure functions) and reports.

:mod:`.mesh_metrics`: scene-mesh accuracy and completeness against a ground-truth mesh.
"""

import os as _os

# Open3D's OpenMP threads spin-wait by default; on a busy 2-core machine that made a small TSDF
# integration ~30x slower (measured: 10 s vs 0.3 s for 30 frames). The policy is read when the
# OpenMP runtime loads, so it must be set before open3d is first imported; setdefault keeps a
# user's own choice.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

