"""Stage I's steps, declared once (:mod:`embodmocap.io.steps`): their fingerprints, the coverage
test of :class:`~embodmocap.scene.config.SceneConfig` and the architecture doc's table come from here."""

from __future__ import annotations

from embodmocap.io.steps import StageSteps, Step
from embodmocap.scene.config import SceneConfig
from embodmocap.scene.solve import KEYFRAMES_VERSION

#: Version of the floor check (:func:`embodmocap.geometry.planes.find_floor`), part of its fingerprint.
FLOOR_VERSION = 1
#: Version of the simplified mesh's recipe, part of its step's fingerprint: 2 = faces wound by the
#: raw faces' vote, one face per triple of cells (1: Open3D's clustering kept either or both
#: windings), so a session simplified before redoes that step (seconds) and nothing else.
SIMPLIFY_VERSION = 2

_DIR = "scenes/<scene>/"

STEPS = StageSteps("scene", SceneConfig, (
    Step("keyframes", reads=("scene capture",), context=("indoor",), version=KEYFRAMES_VERSION,
         # the tracking-jump test also keeps jumps out of the fused frames: the mesh comes after this step
         settings=("keyframe_step_m_indoor", "keyframe_step_m_outdoor", "keyframe_step_deg", "blur_window",
                   "blur_long_side_px", "jump_speed_mps", "jump_rate_dps", "jump_ratio", "jump_min_step_m",
                   "jump_neighbours", "min_keyframes"),
         writes=(_DIR + "keyframes.json",), doc="key frames by camera motion, blurry ones and tracking jumps out"),
    Step("sfm", after=("keyframes",), settings=("sfm",), writes=(_DIR + "sfm/",),
         doc="sparse model of the key frames, poses fixed (or drift-corrected)"),
    # after sfm only with sfm.refine_poses (its drift correction is carried over to the fused frames)
    Step("mesh", after=("keyframes", "sfm"),
         settings=("min_confidence", "confidence_weights", "depth_trunc_m_indoor", "depth_trunc_m_outdoor",
                   "depth_weight_range_m", "depth_refine", "depth_refine_model", "voxel_m_indoor", "voxel_m_outdoor",
                   "sdf_trunc_voxels", "integrate_every", "fuse_step_m", "fuse_step_deg", "fuse_min_valid_fraction",
                   "min_component_fraction", "min_component_triangles", "floater_max_extent_m",
                   "structure_min_extent_m"),
         writes=(_DIR + "mesh_raw.ply",), doc="TSDF fusion of the LiDAR depth, cleaned"),
    Step("floor", after=("mesh",), settings=("floor_tilt_warn_deg",), version=FLOOR_VERSION,
         doc="gravity check: the floor's tilt (a manifest figure)"),
    Step("simplify", after=("mesh",), settings=("simplify_voxel_m",), version=SIMPLIFY_VERSION,
         writes=(_DIR + "mesh_simplified.ply",), doc="light mesh for viewers and physics"),
), not_fingerprinted={
    "min_valid_depth_fraction": "checked on every run before any step (scene.depth.check_depth); writes nothing",
    "fusion_threads": "how many threads integrate the TSDF; the mesh is the same for any number",
})
