"""The monocular pipeline's steps, declared once (:mod:`embodmocap.io.steps`): their fingerprints,
the coverage test of :class:`~embodmocap.mono.config.MonoConfig` and the architecture doc's table
come from here."""

from __future__ import annotations

from embodmocap.io.steps import StageSteps, Step
from embodmocap.mono.config import MonoConfig

_DIR = "sequences/<seq>/mono/<view>/"

STEPS = StageSteps("mono", MonoConfig, (
    # Every setting is the stitch's: the camera-space body (human model, its depth refinement, the
    # height) gives the metric scale, and the body step comes after it.
    Step("stitch", context=("view",),
         reads=("<view>/cameras.npz", "<view>/masks.npy", "<view>/keypoints2d.npz", "scene model files",
                "human model file", "body model"),
         settings=("scene_model", "human_model", "human_depth", "depth_refine", "chunk", "overlap", "gravity",
                   "ply_points", "ply_frame_stride", "stitch", "scale", "colmap"),
         writes=(_DIR + "cameras_world.npz", _DIR + "points.ply"),
         doc="chunks stitched, metric scale from the body, gravity"),
    Step("body", after=("stitch",), writes=(_DIR + "smpl_world.npz",), doc="the body in the metric world"),
))
