"""Settings of `embodmocap check` (kept apart so the CLI imports them cheaply)."""

from __future__ import annotations

from dataclasses import dataclass, field

from embodmocap.sequence.geosync import GeoSyncConfig
from embodmocap.sequence.sync import SyncConfig


@dataclass(frozen=True)
class CheckConfig:
    """What `embodmocap check` samples and the limits of its verdicts."""

    max_frames: int = 600
    """Keypoint frames read per view at most; a longer sequence is subsampled evenly (every k-th
    frame), and the geometric sync runs on that subsampled timeline."""
    register_frames: int = 10
    """Frames per view registered to the scene's sparse model (Stage I) to place the view."""
    sync: SyncConfig = field(default_factory=SyncConfig)
    """Laser-dot detection."""
    geosync: GeoSyncConfig = field(default_factory=GeoSyncConfig)
    """Geometric sync (search window, confidence needed)."""
    min_joints: int = 6
    """A view sees the performer in a frame when at least this many keypoints are confident."""
    both_seen_reshoot: float = 0.6
    """Performer seen in both views for less than this fraction of the time: reshoot."""
    both_seen_warn: float = 0.8
    """... less than this: usable with warnings."""
    angle_range_deg: tuple[float, float] = (60.0, 120.0)
    """Angle between the two views at the performer that the method expects (the paper's 60-120)."""
    angle_in_range_reshoot: float = 0.5
    """In range for less than this fraction of the time (where measurable): reshoot."""
    angle_in_range_warn: float = 0.8
    """... less than this: usable with warnings."""
    registered_reshoot: float = 0.2
    """A view registering less than this fraction of its sampled frames to the scene: reshoot."""
    registered_warn: float = 0.4
    """... less than this: usable with warnings (Stage III itself needs 10 % of its 200 frames;
    on 10 sampled frames a normal view registers 5-10)."""
    jump_speed_mps: float = 4.0
    """A phone pose moving faster than this between two frames is a tracking jump, m/s."""
    jump_turn_deg_s: float = 400.0
    """... or turning faster than this, degrees per second."""
    jumps_reshoot: int = 5
    """More tracking jumps than this in a view: reshoot (fewer: a warning)."""
