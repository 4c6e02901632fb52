"""Stage I (scene): key frames, depth, TSDF fusion, mesh clean-up and the sparse model.

Modules: :mod:`.config` (settings), :mod:`.keyframes` (key frame choice, blur, tracking jumps),
:mod:`.depth` (confidence-filtered, truncated LiDAR depth), :mod:`.tsdf` (Open3D fusion and a
NumPy reference TSDF), :mod:`.mesh` (clean-up, simplification, PLY writing), :mod:`.sfm` (sparse
model) and :mod:`.stage` (the stage runner). Only the config is imported here, so importing the
package stays cheap.
"""

import os as _os

# Open3D's OpenMP threads spin-wait by default; on a busy 2-core machine that made a small TSDF
# integration ~30x slower (measured: 10 s vs 0.3 s for 30 frames). The policy is read when the
# OpenMP runtime loads, so it must be set before open3d is first imported; setdefault keeps a
# user's own choice.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


from embodmocap.scene.config import SceneConfig

__all__ = ["SceneConfig"]
