"""Settings of the perception helpers that Stage II's config holds: :class:`TrackingConfig` (also
importable from :mod:`embodmocap.perception.tracking`) and :class:`ModelSources` (what the model
backends read). No model or image library is imported here."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class TrackingConfig:
    """How detections are linked into tracks."""

    conf_thr: float = 0.3
    """Keypoints with at least this confidence count (for boxes and OKS)."""
    min_keypoints: int = 3
    """A person with fewer confident keypoints is ignored (too little to track)."""
    box_scale: float = 1.2
    """Enlargement of the box of the confident keypoints (see ``boxes_from_keypoints``)."""
    iou_weight: float = 0.4
    """Weight of box IoU in the similarity; the rest goes to keypoint similarity (OKS)."""
    oks_sigma: float = 0.1
    """Keypoint distance scale, as a fraction of sqrt(box area) (about 10% of the body size)."""
    gap_growth: float = 0.15
    """Per missed frame, the OKS distance scale grows by this fraction (prediction uncertainty)."""
    velocity_smoothing: float = 0.5
    """Weight of the newest box-centre motion in the track's velocity average (0..1]."""
    min_similarity: float = 0.15
    """Track and detection are linked only when their similarity reaches this."""
    max_gap: int = 30
    """A track survives this many frames without a detection (occlusions) before it ends."""
    age_bonus: float = 0.1
    """Similarity bonus of an established track (full at ``age_frames`` observations): when two
    tracks fit a detection about equally, the older one keeps it (a person briefly detected in two
    pieces must not hand their identity to the piece's new track)."""
    age_frames: int = 30
    """Observations after which a track gets the full ``age_bonus``."""


@dataclass(frozen=True)
class ModelSources:
    """What the registry's model backends read of their settings: the model folders or hub ids,
    the device, offline. Stage II's :class:`~embodmocap.sequence.config.SequenceConfig` has the same
    fields (documented there) and is what Stage II passes; this is the default of
    :func:`embodmocap.perception.registry.make` when none is given (same defaults, tested)."""

    detector_model: str = ""
    """RT-DETR model: a local folder or a hub id; empty = the backend's default."""
    keypoints_model: str = ""
    """ViTPose model: a local folder or a hub id; empty = the backend's default."""
    masks_model: str = ""
    """SAM 2 model: a local folder or a hub id; empty = the backend's default."""
    depth_model: str = ""
    """Prompt Depth Anything model: a local folder or a hub id; empty = the backend's default."""
    offline: bool = False
    """Never download model weights."""
    device: str = "cpu"
    """cpu or cuda."""
