"""Settings of the monocular pipeline (``embodmocap mono``): one frozen dataclass per part, every
field documented (tyro turns them into the command's options). No heavy import here."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

SceneModelName = Literal["precomputed", "vio"]
"""Scene/camera role backends: ``precomputed`` reads one npz per chunk in Pi3's output layout
(bring Pi3, VGGT or MASt3R output); ``vio`` uses the phone's own metric poses and LiDAR depth as
point maps (an ablation: what a perfect scene model would give)."""
HumanModelName = Literal["precomputed", "prior"]
"""Human role backends: ``precomputed`` reads a camera-space SMPL npz (VIMO / TRAM / GVHMR output);
``prior`` reads Stage II's ``<view>/body_prior.npz``."""


@dataclass(frozen=True)
class StitchConfig:
    """How chunks are aligned to each other (weighted Umeyama on the overlap)."""

    points_per_frame: int = 1500
    """Point-map pixels sampled per overlapping frame for the alignment (a regular grid, then
    those with confidence); more is slower and barely more accurate."""
    min_conf: float = 0.1
    """Point-map pixels whose confidence (in either chunk) is below this are not used."""
    centre_weight: float = 0.2
    """Share of the total weight given to the overlapping frames' camera centres (the rest to the
    points): they pin the path where the points are few."""
    robust_iterations: int = 4
    """Cauchy re-weighting rounds of the alignment (0 = plain weighted Umeyama)."""
    min_overlap_frames: int = 2
    """Fewer overlapping frames than this cannot be aligned: a new segment starts."""
    min_points: int = 50
    """Fewer usable overlap points than this cannot be aligned: a new segment starts."""
    max_rel_residual: float = 0.1
    """An alignment whose weighted median point residual exceeds this fraction of the median
    point distance from the cameras is refused: a new segment starts (never a silent jump)."""


@dataclass(frozen=True)
class ScaleConfig:
    """How the metric scale comes from the body (median of body depth / point-map depth)."""

    erode_px: int = 0
    """Point-map pixels this close to the body's rendered silhouette edge are left out. 0 by
    default: ``max_edge_rel`` already drops pixels on depth edges (where a model's point mixes
    person and background), and at a low map resolution an erosion leaves a body drawn too far
    (small) no pixel, so such frames stopped voting and biased the scale low (3.40 -> 2.97 % on a
    20 s studio view whose prior alone is 2.7 % off)."""
    min_conf: float = 0.3
    """Point-map pixels below this confidence are not sampled."""
    max_edge_rel: float = 0.05
    """A pixel whose 3x3 point-map depths spread more than this fraction of its depth is on a depth
    edge (person against background, an object in front) and is left out."""
    min_frame_samples: int = 10
    """A frame whose person mask covers fewer point-map pixels than this does not vote."""
    min_samples: int = 50
    """Fewer (pixel, frame) samples in a segment than this: no metric scale (the segment stays in
    the model's units, its frames flagged invalid)."""


@dataclass(frozen=True)
class MonoConfig:
    """The monocular pipeline: one view's video -> cameras, scene points and SMPL in a metric world."""

    scene_model: SceneModelName = "precomputed"
    """Scene/camera model: ``precomputed`` (npz per chunk, Pi3 layout, in
    ``perception/<seq>/<view>/mono_scene/``) or ``vio`` (the phone's poses and depth; ablation)."""
    human_model: HumanModelName = "prior"
    """Camera-space body: ``prior`` (Stage II's body prior) or ``precomputed``
    (``perception/<seq>/<view>/mono_human.npz``)."""
    chunk: int = 64
    """Frames per chunk given to the scene model."""
    overlap: int = 16
    """Frames shared by consecutive chunks (what the alignment uses); < chunk."""
    gravity: Literal["auto", "vio", "plane"] = "auto"
    """Where Z-up comes from: ``vio`` (the phone's gravity-aligned poses), ``plane`` (the scene
    points' dominant plane near the cameras' mean down direction), ``auto`` = ``vio`` when Stage II
    has tracked VIO poses, else ``plane``."""
    ply_points: int = 200_000
    """At most this many coloured points in ``points.ply``."""
    ply_frame_stride: int = 8
    """Every n-th frame contributes points (and decodes its RGB frame) to ``points.ply``."""
    stitch: StitchConfig = field(default_factory=StitchConfig)
    """Chunk alignment settings."""
    scale: ScaleConfig = field(default_factory=ScaleConfig)
    """Metric scale settings."""

    def __post_init__(self) -> None:
        from embodmocap.errors import InputError

        if self.chunk < 2 or not 0 <= self.overlap < self.chunk:
            raise InputError(None, f"--chunk {self.chunk} --overlap {self.overlap}: need chunk >= 2 and 0 <= overlap < chunk",
                             "pick e.g. --chunk 64 --overlap 16")
