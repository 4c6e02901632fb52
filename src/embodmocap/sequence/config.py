"""Settings of Stage II (`embodmocap sequence`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from embodmocap.perception.config import TrackingConfig
from embodmocap.sequence.sync import SyncConfig


@dataclass(frozen=True)
class SequenceConfig:
    """How Stage II syncs, slices and observes the performer."""

    sync: SyncConfig = field(default_factory=SyncConfig)
    """Laser-dot detection (frames given in session.toml override it)."""
    fps: float | None = None
    """Frame rate of the sliced sequence; None = the lower of the two views' rates."""
    min_overlap_s: float = 1.0
    """Shortest common span of the two views after sync, seconds (shorter = error)."""
    sync_without_laser: Literal["geometric", "error"] = "geometric"
    """A view without a laser event (and no sync_frame): slice both views from their first frames
    and let Stage III's geometric sync find the offset, or stop with an error."""

    keypoints: Literal["precomputed", "vitpose", "mediapipe"] = "precomputed"
    """2D keypoint backend: the view's keypoint folder from session.toml, a ViTPose model, or MediaPipe."""
    detector: Literal["precomputed", "rtdetr", "mediapipe"] = "precomputed"
    """Person boxes for model keypoint backends (precomputed = boxes of the view's keypoint files)."""
    masks: Literal["precomputed", "sam2", "mediapipe", "none"] = "precomputed"
    """Person-mask backend (precomputed = the view's mask folder; none = write no masks)."""
    depth: Literal["lidar", "precomputed", "promptda"] = "lidar"
    """Depth per frame: the capture's LiDAR depth, the view's depth folder, or Prompt Depth Anything."""
    body_prior: Literal["precomputed", "none"] = "precomputed"
    """Camera-space body prior: the view's body_prior file, or none."""
    detector_model: str = ""
    """RT-DETR model (detector = rtdetr): a local folder or a Hugging Face hub id; empty = the default
    PekingU/rtdetr_r50vd_coco_o365. Hub ids are downloaded into the Hugging Face cache unless offline."""
    keypoints_model: str = ""
    """ViTPose model (keypoints = vitpose): a local folder or a hub id; empty = the default
    usyd-community/vitpose-base-simple."""
    masks_model: str = ""
    """SAM 2 model (masks = sam2): a local folder or a hub id; empty = the default facebook/sam2.1-hiera-tiny."""
    depth_model: str = ""
    """Prompt Depth Anything model (depth = promptda): a local folder or a hub id; empty = the default
    depth-anything/prompt-depth-anything-vits-hf."""
    offline: bool = False
    """Never download model weights: hub ids must already be in the Hugging Face cache (HF_HUB_CACHE,
    else ~/.cache/huggingface/hub; `hf download ID` fills it). HF_HUB_OFFLINE=1 does the same."""
    device: str = "cpu"
    """Device for model backends: cpu or cuda."""
    batch_size: int = 8
    """Frames per batch for model backends (and per chunk of the streaming loop)."""

    min_depth_confidence: int = 1
    """LiDAR depth pixels with lower confidence (0 low, 1 medium, 2 high) are set to 0 (invalid)."""
    no_confidence_edge_spread: float = 0.1
    """For a capture without a confidence map (a Spectacular AI recording): depth pixels whose 3x3
    neighbourhood spans more than this fraction of their depth are set to 0, the depth edges the
    LiDAR's confidence would have marked low (``geometry.depth_edges``); 0 keeps every pixel.
    Captures with a confidence map use ``min_depth_confidence`` instead."""
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    """Linking detections into tracks so the performer keeps one identity."""
    long_gap_s: float = 2.0
    """A stretch without the performer longer than this (seconds) is reported as a warning."""
    min_person_fraction: float = 0.2
    """Below this fraction of frames with the performer, a view is an error (wrong keypoints?)."""

    def __post_init__(self) -> None:
        from embodmocap.errors import InputError

        bad = []
        if self.fps is not None and not 0 < self.fps <= 240:
            bad.append("fps must be in (0, 240]")
        if self.batch_size < 1:
            bad.append("batch_size must be >= 1")
        if self.min_depth_confidence not in (0, 1, 2):
            bad.append("min_depth_confidence must be 0, 1 or 2")
        if not 0 <= self.no_confidence_edge_spread < 10:
            bad.append("no_confidence_edge_spread must be in [0, 10) (0 = off)")
        if not 0 <= self.min_person_fraction <= 1:
            bad.append("min_person_fraction must be in [0, 1]")
        if bad:
            raise InputError(None, "invalid sequence settings: " + "; ".join(bad), "fix the options")
