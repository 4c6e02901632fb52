"""Stage I (scene): key frames, depth, TSDF fusion, mesh clean-up and the sparse model.

Modules: :mod:`.config` (settings), :mod:`.keyframes` (key frame choice, blur, tracking jumps),
:mod:`.depth` (confidence-filtered, truncated LiDAR depth), :mod:`.tsdf` (Open3D fusion and a
NumPy reference TSDF), :mod:`.mesh` (clean-up, simplification, PLY writing), :mod:`.sfm` (sparse
model) and :mod:`.stage` (the stage runner). Only the config is imported here, so importing the
package stays cheap.
"""

from embodmocap.scene.config import SceneConfig

__all__ = ["SceneConfig"]
