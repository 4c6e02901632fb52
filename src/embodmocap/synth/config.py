"""Settings of the synthetic studio (kept apart from the studio so the CLI imports it cheaply)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from embodmocap.synth.vio import HARD_VIO, VioErrorConfig
from embodmocap.types import Intrinsics


WallLook = Literal["scene", "reddish", "magenta", "beige", "grey", "textured"]
"""Wall appearance presets for the laser dot's walls (``"scene"``: the scene's own wall colour)."""


@dataclass(frozen=True)
class LaserConfig:
    """How the laser dot of the sync event looks in the two views.

    ``"easy"`` is the studio's original dot: a saturated red disc of at least 2.5 px radius with a
    red glow, on the scene's calm wall. ``"realistic"`` renders what a phone records of a real
    pointer at 2-6 m: a small spot whose over-exposed core is ``core_px`` across with a red halo of
    ``halo_px``, every look drawn per seed from the ranges below (wall colour and texture,
    exposure, lens blur, motion blur from the phone moving, a brief occlusion). ``"none"`` films
    the same wall with no laser at all (false-event tests); the ground truth still names the frame
    where the event would have been.
    """

    mode: Literal["easy", "realistic", "none"] = "easy"
    """Which dot: the original easy one, the realistic range, or no laser."""
    core_px: tuple[float, float] = (2.0, 6.0)
    """Range of the over-exposed core's diameter at the event, pixels (realistic mode). One
    physical spot size is drawn per session; each view sees it at its own distance (clipped to
    this range, as a phone's exposure sets how much of the spot saturates)."""
    halo_px: tuple[float, float] = (5.0, 10.0)
    """Range of the red halo's diameter (lens and sensor bloom), pixels; at least core + 2 px."""
    walls: tuple[WallLook, ...] = ("scene", "reddish", "magenta", "beige", "grey", "textured")
    """Wall looks drawn from (one per session, applied to every wall of the room or fence)."""
    gain: tuple[float, float] = (3.0, 10.0)
    """Range of the spot's brightness relative to a white wall (>1: the core over-exposes)."""
    whiteness: tuple[float, float] = (0.25, 0.7)
    """Range of the green/blue response to the spot relative to red (sensor crosstalk): with the
    gain, how white the saturated core gets."""
    psf_sigma_px: tuple[float, float] = (0.4, 0.8)
    """Range of the lens blur (Gaussian sigma), pixels."""
    shutter: tuple[float, float] = (0.1, 0.8)
    """Range of the exposure time as a fraction of the frame interval: the image moves this
    fraction of its per-frame motion while the shutter is open (motion blur of the whole frame)."""
    shake_deg: tuple[float, float] = (1.0, 5.0)
    """Range of the amplitude of the operator's hand wobble (the aim wanders around the dot and
    the performer), degrees: the dot moves in the image and is motion-blurred."""
    shake_hz: tuple[float, float] = (0.5, 2.0)
    """Range of the wobble's main frequency, hertz."""
    occlusion_prob: float = 0.5
    """Chance that, in a view, something (the performer's arm) passes in front of the dot for a
    few frames while it is on."""
    occlusion_frames: tuple[int, int] = (1, 4)
    """Range of the length of that occlusion, frames."""
    red_clothes_prob: float = 0.35
    """Chance that the performer wears red (a red distractor for the detector), realistic and
    none modes."""
    false_event: bool = False
    """A second, false disappearance in one view (``false_event_view``): shortly before the real
    switch-off the dot leaves that view's frame (the pointer swept off the part of the wall it
    films) and comes back, so the view shows two disappearances that look alike and only the
    other view's event and the geometry tell which is the sync. The view records long enough
    before the event to see both (views then start up to 1.3 s before it)."""
    false_event_view: Literal["v1", "v2"] = "v1"
    """The view that sees the false disappearance."""
    false_event_lead_s: tuple[float, float] = (0.6, 0.9)
    """Range of how long before the real switch-off the dot leaves the view, seconds."""
    false_event_gone_s: tuple[float, float] = (0.33, 0.4)
    """Range of how long the dot stays out of the view, seconds (longer than the detector's
    ``absent_frames``, so it reads as a disappearance; shorter than the lead, so it comes back)."""


@dataclass(frozen=True)
class SynthConfig:
    """Settings of one synthetic session."""

    seed: int = 0
    """Random seed; the same seed gives identical files."""
    take: int = 0
    """Take of the performance in the seed's scene: 0 = the historic session; another take draws
    its own performer, motion, operators' paths, laser look, clocks and detections while the room
    and the scene capture stay those of ``seed`` (byte for byte), so several takes share one scan
    and its Stage I."""
    preset: Literal["indoor", "outdoor"] = "indoor"
    """Scene kind: a furnished room or a fenced yard."""
    room: Literal["standard", "large", "high_ceiling", "low_texture", "repetitive"] = "standard"
    """Indoor studio preset: ``"standard"`` (4.5-7 x 4-6 m, 2.6-3 m ceiling), ``"large"`` (8 x 6 m),
    ``"high_ceiling"`` (4-4.6 m), ``"low_texture"`` (plain painted walls) or ``"repetitive"``
    (walls with a repeating wallpaper); see :func:`embodmocap.synth.scene.build_scene`."""
    lighting_change: bool = False
    """Film the sequence under other light than the scene capture: each view gets an exposure gain
    (0.55-0.75 or 1.35-1.7) and a white balance shift (up to 15 % per channel), as when lamps are
    switched or daylight changes between the scan and the performance."""
    seconds: float = 10.0
    """Length of the performance after the sync event, seconds (views record about this long)."""
    scene_seconds: float = 20.0
    """Length of the empty-scene capture, seconds."""
    scan_turns_per_lap: float = 1.0
    """Turns of the empty-scene scan's view per lap walked, relative to the walk
    (:attr:`embodmocap.synth.trajectory.SceneWalkConfig.turns_per_lap`): 1 looks out at the walls,
    along the loop and in across the walk area at its floor; 0 = the earlier scan that only looks
    outwards and never sees the floor where the performer walks."""
    fps: float = 30.0
    """Frame rate of every capture and of the motion."""
    width: int = 640
    """RGB width in pixels (up to 1920); height follows ``height``."""
    height: int = 480
    """RGB height in pixels (up to 1440)."""
    depth_width: int = 256
    """LiDAR depth width in pixels (the iPhone's is 256)."""
    depth_height: int = 192
    """LiDAR depth height in pixels (the iPhone's is 192)."""
    hfov_deg: float = 67.0
    """Horizontal field of view of the RGB camera, degrees (an iPhone main camera is about 67)."""
    format: Literal["strayscanner", "spectacular"] = "strayscanner"
    """Capture format the phones' files are written in."""
    scene_name: str = "scene0"
    """Name of the scene in the manifest."""
    sequence_name: str = "seq0"
    """Name of the sequence in the manifest."""
    lead_min_s: float = 0.4
    """Shortest time a view records before the sync event, seconds."""
    tail_max_s: float = 0.5
    """Longest time a view stops before the end of the motion, seconds (views end at different times)."""
    phone_offset_frames: float = 0.0
    """Sub-frame clock offset of the second phone: view 2's frames are exposed this fraction of a
    frame later than view 1's (negative: earlier), in (-0.5, 0.5). Real phones' frame clocks are
    never aligned; 0 = the studio's historic exact alignment. The laser sync frame is unchanged."""
    phone_phase: Literal["auto", "fixed", "random"] = "auto"
    """Where view 2's sub-frame phase comes from: ``fixed`` = ``phone_offset_frames``; ``random`` = a
    draw uniform in (-0.5, 0.5) per session and take (its own generator: no other draw moves), as
    two real phones' frame clocks are; ``auto`` = ``random`` for ``perception = "hard"`` with
    ``phone_offset_frames`` left at 0, else ``fixed``. The phase used is in the ground truth
    (``view_time_offset_frames``); a hard session in phase needs ``fixed``."""
    view_separation_deg: float | None = None
    """Fixed azimuth separation of the two operators about the performer, degrees; None = the
    normal 75-105 degrees. A "built to fail" session uses 20 (views nearly parallel)."""
    views: int = 2
    """Phones filming the performance: 2 (the product's two-phone session) or 1 (a one-phone
    session: only ``v1`` is written, identical to ``v1`` of the two-phone session of the same seed,
    so the two can be compared frame for frame)."""
    view2_away_fraction: float = 0.0
    """Fraction of the performance (after the sync event, at its end) during which operator 2
    turns the phone away from the performer ("built to fail": performer out of one view)."""
    view2_other_scene: bool = False
    """View 2 is filmed in another room than the scene capture ("built to fail": the view cannot
    be registered to the scene)."""
    edge_limb_frames: int = 0
    """For this many frames from the sync event (the sequence's first frames), the left arm is hard
    for the detector in both views: view 2 sees it occluded (confidence 0.05-0.3, noisy) and view 1
    mislabels or misses it (``edge_limb``): the start of a sequence with no past to tell the limb
    by (issue 29). 0 = off."""
    edge_limb: Literal["mislabelled", "occluded"] = "mislabelled"
    """What view 1 does with the left arm over ``edge_limb_frames``: ``mislabelled`` (the two arms'
    labels exchanged) or ``occluded`` (not detected)."""
    interactions: tuple[str, ...] | None = None
    """The performer's interactions, as many as fit (names of
    :data:`embodmocap.synth.motion_base.INTERACTIONS`, e.g. ``("lie",)`` to lie on the bed of a room
    that has one); None = the motion script's default (chair, box, table, sofa)."""
    laser: LaserConfig = LaserConfig()
    """The laser dot of the sync event: easy (default), realistic range, or none."""
    cameras: Literal["standard", "hard"] = "standard"
    """The views' VIO: ``standard`` = the studio's historic slow drift in time only (a rigid offset
    fits every frame of a view to a few millimetres); ``hard`` = also the errors of a real handheld
    ARKit track that no rigid offset absorbs (:data:`embodmocap.synth.vio.HARD_VIO`: a 1-2 % scale
    error, drift of 1-2 % of the path walked, 0.1-0.3 deg of yaw per metre), unless ``vio`` sets
    its own. Stage III's hard preset (``indoor+vio``, ``outdoor+vio`` in the benchmarks)."""
    vio: VioErrorConfig = VioErrorConfig()
    """Path-dependent VIO errors of the two views (scale, drift per metre walked, yaw per metre);
    all zero by default. Non-zero values are used as given, whatever ``cameras`` says."""
    perception: Literal["clean", "hard"] = "clean"
    """The 2D detector the perception files imitate: ``clean`` = a good detector on a clear view
    (jitter, low confidence when occluded, rare outliers, short swaps); ``hard`` = every adversity
    of real detectors on (:data:`embodmocap.synth.perception.HARD_KEYPOINT_NOISE`: noise growing
    with occlusion and distance, missed joints, more outliers, left/right limb swaps lasting up to
    a second, whole-body misses, furniture-hidden joints guessed at wrong places) and, unless
    ``keypoint_layout`` says otherwise, OpenPose BODY_25 output."""
    body_prior: Literal["none", "realistic", "poor"] = "realistic"
    """The camera-space body prior written per view: ``none`` (no file: a user without regressor
    weights), ``realistic`` (a VIMO-like regressor: 7 deg per joint, depth 10 % off) or ``poor``
    (15 deg per joint, depth 20 % off)."""
    keypoint_layout: Literal["auto", "COCO17", "BODY_25"] = "auto"
    """Layout of the keypoint JSON: ``COCO17``, ``BODY_25`` (OpenPose's default model, with its own
    hip definition) or ``auto`` (BODY_25 for ``perception = hard``, else COCO17)."""

    def __post_init__(self) -> None:
        from embodmocap.errors import InputError

        checks = [
            (self.take >= 0, "take must be >= 0"),
            (self.seconds > 0 and self.scene_seconds > 0, "seconds and scene_seconds must be > 0"),
            (0 < self.fps <= 120, "fps must be in (0, 120]"),
            (16 <= self.width <= 1920 and 16 <= self.height <= 1440, "RGB size must be within 16x16..1920x1440"),
            (self.width % 2 == 0 and self.height % 2 == 0, "RGB width and height must be even (H.264)"),
            (8 <= self.depth_width <= self.width and 8 <= self.depth_height <= self.height, "depth size must be >= 8 and <= the RGB size"),
            (20 < self.hfov_deg < 150, "hfov_deg must be in (20, 150)"),
            (self.room == "standard" or self.preset == "indoor", "room presets other than 'standard' are indoor only"),
            (-0.5 < self.phone_offset_frames < 0.5, "phone_offset_frames must be in (-0.5, 0.5)"),
            (self.view_separation_deg is None or 0 <= self.view_separation_deg <= 180, "view_separation_deg must be in [0, 180]"),
            (0 <= self.view2_away_fraction < 1, "view2_away_fraction must be in [0, 1)"),
            (self.edge_limb_frames >= 0, "edge_limb_frames must be >= 0"),
            (self.views in (1, 2), "views must be 1 or 2"),
            (self.edge_limb_frames == 0 or self.views == 2, "edge_limb_frames needs two views"),
            (all(0 < r[0] <= r[1] for r in (self.laser.core_px, self.laser.halo_px, self.laser.gain,
                                             self.laser.psf_sigma_px, self.laser.shutter, self.laser.whiteness,
                                             self.laser.shake_deg, self.laser.shake_hz))
             and len(self.laser.walls) > 0 and 0 <= self.laser.occlusion_frames[0] <= self.laser.occlusion_frames[1]
             and 0 <= self.laser.occlusion_prob <= 1 and 0 <= self.laser.red_clothes_prob <= 1,
             "laser ranges must be (low, high) with 0 < low <= high, walls not empty, probabilities in [0, 1]"),
            (not self.laser.false_event or (0 < self.laser.false_event_gone_s[0] <= self.laser.false_event_gone_s[1]
                                            < self.laser.false_event_lead_s[0] <= self.laser.false_event_lead_s[1] <= 1.0),
             "laser.false_event_gone_s and false_event_lead_s must be ranges with gone < lead <= 1 s"),
        ]
        bad = [msg for ok, msg in checks if not ok]
        if bad:
            raise InputError(None, "invalid synth settings: " + "; ".join(bad), "change the options")

    def vio_errors(self) -> VioErrorConfig:
        """The views' path-dependent VIO errors: ``vio`` when set, else the ``cameras`` preset's."""
        if self.vio.active or self.cameras == "standard":
            return self.vio
        return HARD_VIO

    def phone_phase_frames(self) -> float:
        """View 2's sub-frame phase, frames (:attr:`phone_phase`)."""
        random = self.phone_phase == "random" or (
            self.phone_phase == "auto" and self.perception == "hard" and self.phone_offset_frames == 0.0)
        if not random:
            return float(self.phone_offset_frames)
        rng = np.random.default_rng([self.seed, 97] if self.take == 0 else [self.seed, 97, self.take])
        return float(np.clip(np.round(rng.uniform(-0.5, 0.5), 3), -0.499, 0.499))

    def layout(self) -> str:
        """The keypoint layout the perception files are written in."""
        if self.keypoint_layout != "auto":
            return self.keypoint_layout
        return "BODY_25" if self.perception == "hard" else "COCO17"

    def intrinsics(self) -> Intrinsics:
        fx = (self.width / 2) / np.tan(np.deg2rad(self.hfov_deg) / 2)
        return Intrinsics(fx, fx, (self.width - 1) / 2, (self.height - 1) / 2, self.width, self.height)

    def depth_intrinsics(self) -> Intrinsics:
        return self.intrinsics().scaled(self.depth_width, self.depth_height)
