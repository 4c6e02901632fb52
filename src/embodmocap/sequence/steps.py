"""Stage II's steps, declared once (:mod:`embodmocap.io.steps`): their fingerprints, the coverage
test of :class:`~embodmocap.sequence.config.SequenceConfig` and the architecture doc's table come from here."""

from __future__ import annotations

from embodmocap.io.steps import StageSteps, Step
from embodmocap.sequence.config import SequenceConfig
from embodmocap.sequence.sync_record import SYNC_RECORD_VERSION

_DIR = "sequences/<seq>/"

STEPS = StageSteps("sequence", SequenceConfig, (
    # min_overlap_s also bounds the slicing, which comes after this step
    Step("sync", reads=("view captures",), context=("sync_frame",), version=SYNC_RECORD_VERSION,
         settings=("sync", "sync_without_laser", "min_overlap_s"),
         writes=(_DIR + "sync.json", _DIR + "sync_<view>.png"), doc="the laser-dot event of each view"),
    Step("slice", after=("sync",), settings=("fps",),
         writes=(_DIR + "<view>/frame_map.json", _DIR + "<view>/cameras.npz"),
         doc="one timeline from the event on; each view's intrinsics and VIO poses"),
    Step("keypoints", after=("slice",), reads=("keypoint folders",),
         settings=("keypoints", "detector", "keypoints_model", "detector_model", "tracking", "min_person_fraction"),
         writes=(_DIR + "<view>/keypoints2d.npz",), doc="every person's keypoints, the performer chosen across views"),
    Step("masks", after=("keypoints",), reads=("mask folder",), settings=("masks", "masks_model"),
         writes=(_DIR + "<view>/masks.npy",), doc="person masks (per view: masks_<view>)"),
    Step("depth", after=("slice",), reads=("depth folder",), settings=("depth", "depth_model", "min_depth_confidence", "no_confidence_edge_spread"),
         writes=(_DIR + "<view>/depth.npy",), doc="depth per sliced frame (per view: depth_<view>)"),
    Step("body_prior", after=("slice",), reads=("body prior file",), settings=("body_prior",),
         writes=(_DIR + "<view>/body_prior.npz",), doc="camera-space body prior (per view: body_prior_<view>)"),
), not_fingerprinted={
    "offline": "where model weights come from (cache or hub), not what they compute",
    "device": "where the model backends run (cpu or cuda): the same models and inputs",
    "batch_size": "how many frames go through a backend at once: the same frames, the same results",
    "long_gap_s": "only a log warning",
})
