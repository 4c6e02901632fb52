"""The synthetic performer's scripted motion: walking and using the furniture, in the scene frame.

How a motion is made (read :func:`script_motion` top to bottom):

1. **Plan.** A list of pieces, each a few seconds long with a name (``idle``, ``turn``, ``walk``,
   ``sit_down``, ``sit``, ``stand_up``, ``step_up``, ``stand_on_box``, ``step_down``,
   ``lean_in``, ``lean_table``, ``lean_out``, ``step_back``, ``step_away``). Each piece gives, per frame, the planned pelvis
   position on the floor (x, y), the heading (yaw about +Z) and a few scalar *channels* in
   [0, 1] (gait amplitude and phase, how far seated, how far leaning, how far each leg is lifted
   ...). Every piece starts where the previous one ended and eases in and out (quintic
   smoothstep, zero velocity at the ends), so positions, headings and channels are continuous
   with continuous velocity: blends happen inside the pieces (0.3-1.5 s long).
2. **Pose.** Joint angles are sums of per-channel contributions (hip flexion, knee flexion, arm
   swing ...), turned into SMPL axis-angle ``body_pose`` in one vectorised call. Angles that
   depend on the body (seat posture, table lean, step height) are calibrated once by posing the
   actual body model on a small grid of candidate angles (the table lean's arm angle is then
   solved continuously so that the hands' lowest vertices rest on the table top).
3. **Skin and place.** The body is skinned in chunks of frames. While seated or leaning the feet
   stay where they were when the piece began (the pelvis moves instead, as it does in life).
   Then each frame is lifted so that no vertex is below a support (floor z = 0; the box, chair
   and sofa/bed tops for vertices over their footprints) and at least one touches: the lift is
   ``max over supports of (support height - lowest vertex over it)``. So the stance foot is on
   the floor while walking, on the box while standing on it, and the buttocks on the seat while
   sitting.

Conventions: scene frame Z up, metres, floor at z = 0. SMPL's canonical frame is Y up facing +Z
with its left on +X; ``global_orient`` includes the fixed rotation from that frame to the scene
(:data:`embodmocap.geometry.transforms.R_ZUP_YUP` then a yaw about +Z). A heading ``yaw`` means
the body faces ``(cos yaw, sin yaw, 0)``.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from embodmocap.synth.motion_base import (  # noqa: F401 (MotionScriptConfig, INTERACTIONS: public here)
    INTERACTIONS, SLAB_DEPTH, MotionScriptConfig, _ease, _heading, _in_footprint, _supports,
)
from embodmocap.synth.motion_body import _Calib, _calibrate, _global_orient, _head_top, _joint_angles
from embodmocap.synth.motion_place import _place
from embodmocap.synth.motion_skills import ScriptedClip, follow_path, lie_on_bed, lift_envelope, scripted_clips, step_curves
from embodmocap.synth.spec import Furniture, SceneSpec
from embodmocap.types import SmplParams

log = logging.getLogger(__name__)

#: Channels a plan piece may set; missing ones are 0.
CHANNELS: tuple[str, ...] = (
    "gait_amp", "gait_phase", "lean",
    # Leaning: the arms' part (0 hanging .. 1 on the table), ahead of the torso's ``lean``.
    "lean_arm",
    # Leaning: extra elbow bend (0 .. 1 = 45 degrees) while the hands pass over the table's edge.
    "lean_lift",
    # Seated: how far (0 standing .. 1 seated) and the seated hip/knee angles of this seat.
    "sit", "sit_hip", "sit_knee",
    # Stepping onto / off the box places the feet by inverse kinematics: weight of the IK legs,
    # ankle targets (forward, height above the floor) of each foot and the hip height, all in
    # metres along the heading relative to the piece's start.
    "ik", "al_x", "al_z", "ar_x", "ar_z", "hip_x", "hip_z",
    # Lying down: the whole body (legs included) pitches about the pelvis, radians: negative
    # onto the back, positive onto the front (the hips do not compensate it, unlike the tilt).
    "body_tilt",
    # Lying on the front: the feet pointed (ankle plantar flexion) and the head turned to the
    # side (about the neck's own vertical axis), radians, so that the body rests on its front.
    "point_toes", "head_turn",
)

@dataclass(frozen=True)
class MotionScript:
    """A scripted motion.

    Attributes:
        params: SMPL parameters in the scene frame (Z up), one row per frame.
        segments: ``(name, start_frame, end_frame)`` of each planned piece, end exclusive,
            covering ``0..len(params)`` in order.
        clips: the skill clips the script holds (:class:`ScriptedClip`), in time order.
    """

    params: SmplParams
    segments: list[tuple[str, int, int]] = field(default_factory=list)
    clips: list[ScriptedClip] = field(default_factory=list)
    """The interactions as skill clips (labels and frames the clip finder must recover)."""

    def frames_of(self, *names: str) -> NDArray[np.int64]:
        """Frame indices inside the segments with any of ``names``."""
        idx = [np.arange(s, e) for n, s, e in self.segments if n in names]
        return np.concatenate(idx) if idx else np.zeros(0, np.int64)


# --------------------------------------------------------------------------------------------
# public entry
# --------------------------------------------------------------------------------------------


def script_motion(
    spec: SceneSpec,
    body,
    betas: NDArray,
    seconds: float,
    fps: float,
    rng: np.random.Generator,
    cfg: MotionScriptConfig = MotionScriptConfig(),
) -> MotionScript:
    """Script ``seconds`` of the performer's motion in the scene (see the module docstring).

    Args:
        spec: the scene (furniture, walk area).
        body: the body model (``forward``, ``pelvis_offset``).
        betas: (B,) body shape.
        seconds: length of the motion; the result has ``round(seconds * fps)`` frames.
        fps: frame rate.
        rng: random generator (start point, order of interactions, wander targets).
        cfg: motion settings.
    """
    n_frames = max(int(round(seconds * fps)), 1)
    betas = np.asarray(betas, dtype=np.float64)
    calib = dataclasses.replace(_calibrate(body, betas, spec), head_top=_head_top(body, betas))
    plan = _Planner(spec, cfg, calib, fps, rng)
    plan.build(n_frames)
    xy, yaw, ch, lock, on_furniture, segments = plan.arrays(n_frames)
    clips = scripted_clips(plan, n_frames)

    tilt, euler = _joint_angles(ch, calib, cfg)
    body_pose = Rotation.from_euler("XYZ", euler.reshape(-1, 3)).as_rotvec().reshape(n_frames, 69)
    go = _global_orient(yaw, tilt, ch)
    J0 = np.asarray(body.pelvis_offset(betas), dtype=np.float64).reshape(3)
    transl = _place(body, betas, go, body_pose, xy, lock, on_furniture, J0, spec, cfg.chunk_frames)
    transl[:, 2] = lift_envelope(transl[:, 2], ch["body_tilt"] != 0.0, fps)
    params = SmplParams(betas, go, body_pose, transl, fps=fps)
    log.info("scripted %d frames: %s", n_frames, ", ".join(f"{n}[{s}:{e}]" for n, s, e in segments))
    return MotionScript(params, segments, clips)


def support_height(spec: SceneSpec, points: NDArray) -> NDArray[np.float64]:
    """(...,) height of the surface under points (..., 3): the top of a support piece of
    furniture whose footprint holds the point (for a chair, only if the point is not under its
    seat slab), else the floor (0)."""
    p = np.asarray(points, dtype=np.float64)
    h = np.zeros(p.shape[:-1])
    for f in _supports(spec):
        under = _in_footprint(f, p[..., :2]) & (p[..., 2] > f.top_z - SLAB_DEPTH.get(f.name, np.inf))
        h = np.where(under, np.maximum(h, f.top_z), h)
    return h


def foot_contact_frames(
    spec: SceneSpec, vertices: NDArray, foot_ids: tuple[NDArray, NDArray], tol_m: float = 0.02
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Height of each foot above the surface under it, and which feet are in contact.

    Args:
        spec: the scene.
        vertices: (T, V, 3) posed vertices in the scene frame.
        foot_ids: (left ids, right ids) from :func:`embodmocap.body.vertex_sets.foot_vertex_ids`.
        tol_m: a foot within this height of its support counts as in contact.

    Returns:
        ``(gap (T, 2), contact (T, 2))``: per frame and foot (left, right), the smallest height
        of a foot vertex above the support under it (negative = penetration), and gap <= tol_m.
    """
    v = np.asarray(vertices, dtype=np.float64)
    gaps = []
    for ids in foot_ids:
        fv = v[:, ids]
        gaps.append(np.min(fv[..., 2] - support_height(spec, fv), axis=1))
    gap = np.stack(gaps, axis=1)
    return gap, gap <= tol_m


# --------------------------------------------------------------------------------------------
# easing helpers
# --------------------------------------------------------------------------------------------


def _bump(u: NDArray, a: float, b: float) -> NDArray:
    """0 outside [a, b], rising smoothly to 1 at the middle and back (sin^2: C1 at the ends)."""
    x = np.clip((u - a) / (b - a), 0.0, 1.0)
    return np.sin(np.pi * x) ** 2


def _wrap(a: NDArray | float) -> NDArray | float:
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


# --------------------------------------------------------------------------------------------
# planning
# --------------------------------------------------------------------------------------------


@dataclass
class _Piece:
    name: str
    xy: NDArray       # (n, 2) planned pelvis position on the floor
    yaw: NDArray      # (n,) heading
    ch: dict          # channel -> (n,)
    lock: bool = False  # feet stay put (pelvis follows them)
    on_furniture: bool = False  # part of an interaction: furniture tops hold the body up


class _Planner:
    """Builds the list of pieces; keeps the current pelvis position, heading and gait phase."""

    def __init__(self, spec: SceneSpec, cfg: MotionScriptConfig, calib: _Calib, fps: float, rng: np.random.Generator):
        self.spec, self.cfg, self.calib, self.fps, self.rng = spec, cfg, calib, fps, rng
        self.lo = np.asarray(spec.walk_area_min_xy, dtype=np.float64)
        self.hi = np.asarray(spec.walk_area_max_xy, dtype=np.float64)
        self.pieces: list[_Piece] = []
        self.xy = self.lo + rng.uniform(0.25, 0.75, size=2) * (self.hi - self.lo)
        self.yaw = float(rng.uniform(-np.pi, np.pi))
        self.phase = 0.0
        self.on_furniture = False
        # Scripted skill clips: (skill, furniture, (first piece, fraction into it), (last piece,
        # fraction), (first, last) hold piece) -- frames are known only once the pieces are cut.
        self.marks: list[tuple] = []

    # -- bookkeeping ----------------------------------------------------------------------

    @property
    def frames(self) -> int:
        return sum(len(p.yaw) for p in self.pieces)

    def _n(self, seconds: float) -> int:
        return max(int(round(seconds * self.fps)), 1)

    def _u(self, seconds: float) -> NDArray:
        n = self._n(seconds)
        return (np.arange(n) + 1.0) / n

    def _add(self, name: str, xy: NDArray, yaw: NDArray, lock: bool = False, **ch: NDArray) -> None:
        self.pieces.append(_Piece(name, xy, yaw, ch, lock, self.on_furniture))
        self.xy, self.yaw = xy[-1].copy(), float(yaw[-1])

    # -- primitive pieces -----------------------------------------------------------------

    def idle(self, seconds: float, name: str = "idle") -> None:
        n = self._n(seconds)
        self._add(name, np.repeat(self.xy[None], n, 0), np.full(n, self.yaw))

    def turn_to(self, yaw: float, end_xy: NDArray | None = None) -> None:
        """Turn on the spot to heading ``yaw``, optionally stepping to ``end_xy`` meanwhile."""
        d = float(_wrap(yaw - self.yaw))
        if abs(d) < np.deg2rad(2.0) and end_xy is None:
            return
        u = self._u(max(self.cfg.min_turn_s, abs(np.rad2deg(d)) / self.cfg.turn_speed_dps))
        end = self.xy if end_xy is None else np.asarray(end_xy, dtype=np.float64)
        xy = self.xy + _ease(u)[:, None] * (end - self.xy)
        self._add("turn", xy, self.yaw + d * _ease(u))

    def shuffle_to(self, end_xy: NDArray, seconds: float, name: str = "step_back") -> None:
        """Move the pelvis to ``end_xy`` keeping the heading, with an ease over ``seconds`` (small
        steps, no gait: for a few tens of centimetres, e.g. backwards)."""
        u = self._u(seconds)
        xy = self.xy + _ease(u)[:, None] * (np.asarray(end_xy, dtype=np.float64) - self.xy)
        self._add(name, xy, np.full(len(u), self.yaw))

    def walk_to(self, target: NDArray) -> None:
        """Turn toward ``target``, then walk there in a straight line (ease in and out)."""
        target = np.asarray(target, dtype=np.float64)
        delta = target - self.xy
        L = float(np.linalg.norm(delta))
        if L < 0.05:
            return
        self.turn_to(float(np.arctan2(delta[1], delta[0])))
        v, b = self.cfg.walk_speed_mps, self.cfg.ease_s
        D = L / v + b
        if D < 2 * b:  # too short to reach cruising speed: ease the whole way
            D = 2 * b
        t = np.arange(self._n(D) + 1) / self.fps
        D = t[-1]
        speed = np.minimum(_ease(t / b), _ease((D - t) / b))
        s = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]))])
        s = s / s[-1] * L  # distance walked, exactly L at the end
        vel = np.gradient(s, t)
        amp = np.clip(vel / v, 0.0, 1.0)[1:]
        step = v / self.cfg.cadence_steps_per_s
        phase = self.phase + np.pi * s[1:] / step
        xy = self.xy + np.outer(s[1:] / L, delta)
        self._add("walk", xy, np.full(len(xy), self.yaw), gait_amp=amp, gait_phase=phase)
        self.phase = float(phase[-1])

    def channel_piece(self, name: str, seconds: float, lock: bool, end_xy: NDArray | None = None,
                      move: tuple[float, float] = (0.0, 1.0), **curves) -> None:
        """A piece of fixed heading whose channels follow ``curves(u)``; the pelvis moves to
        ``end_xy`` with an ease over the ``move`` part of the piece."""
        u = self._u(seconds)
        start = self.xy.copy()
        end = start if end_xy is None else np.asarray(end_xy, dtype=np.float64)
        p = _ease((u - move[0]) / (move[1] - move[0]))
        xy = start + p[:, None] * (end - start)
        if "hip_x" in curves:  # the pelvis follows the IK plan along the heading
            xy = start + np.outer(curves["hip_x"](u), [np.cos(self.yaw), np.sin(self.yaw)])
        self._add(name, xy, np.full(len(u), self.yaw), lock, **{k: f(u) for k, f in curves.items()})

    # -- interactions ---------------------------------------------------------------------

    def _approach(self, point: NDArray) -> None:
        """Walk to ``point`` through the walk area (free of furniture): first into it by the
        shortest way (if outside, e.g. in front of a piece of furniture), then across it to its
        point nearest to ``point``, then out to ``point``."""
        for p in (np.clip(self.xy, self.lo, self.hi), np.clip(point, self.lo, self.hi), np.asarray(point, float)):
            if np.linalg.norm(p - self.xy) > 0.1:
                self.walk_to(p)

    def sit(self, seat: Furniture, hold: float) -> None:
        c, cfg = self.calib, self.cfg
        fwd = _heading(seat)
        # Pelvis over the seat: the heels clear of the front edge (a sofa is solid down to the
        # floor), the buttocks clear of the back edge (backrest).
        st = c.seats[seat.name]
        local = max(-seat.size[0] / 2 + st.back + 0.06, seat.size[0] / 2 + 0.25 - st.feet_ahead)
        seat_pelvis = np.asarray(seat.centre_xy) + fwd * local
        # Standing there with the feet where they will be when seated (the feet stay put). The
        # walk ends a little further out, so that the toes clear the seat while facing it, and
        # the turn steps back.
        stand = seat_pelvis + fwd * st.feet_ahead
        self._approach(stand + fwd * 0.15)
        self.turn_to(seat.yaw, stand)
        self.on_furniture = True
        T = cfg.sit_transition_s
        hip, knee = (lambda u: np.full_like(u, st.hip)), (lambda u: np.full_like(u, st.knee))
        i = len(self.pieces)
        self.channel_piece("sit_down", T, True, sit=_ease, sit_hip=hip, sit_knee=knee)
        self.channel_piece("sit", hold, True, sit=np.ones_like, sit_hip=hip, sit_knee=knee)
        self.channel_piece("stand_up", T, True, sit=lambda u: 1.0 - _ease(u), sit_hip=hip, sit_knee=knee)
        self.marks.append(("sit", seat.name, (i, 0.0), (i + 2, 1.0), (i + 1, i + 1)))
        self.on_furniture = False
        if seat.name in ("sofa", "bed"):
            # Solid down to the floor, with the calves at its front edge: the first walking step's
            # trailing heel rises behind the body, into it (3.3 cm on a bed, seed 12). One pushes
            # off such a seat with a small step forward first.
            self.shuffle_to(self.xy + fwd * 0.2, 0.6, name="step_away")
        # Walk straight away from the seat first, so that no later turn swings a heel over it.
        self.walk_to(self.xy + fwd * 0.5)

    def step_on_box(self, box: Furniture, hold: float) -> None:
        """Step onto the box with the right foot, bring the left foot up, stand, turn round and
        step down forward. Feet are placed by IK: each lifted foot clears the box edge by 8 cm
        before it crosses it, so the support under a foot never changes while it is low."""
        cfg, c = self.cfg, self.calib
        fwd = _heading(box)
        centre = np.asarray(box.centre_xy, dtype=np.float64)
        top, half = box.top_z, box.size[0] / 2
        gap = c.toe_ahead + 0.12  # ankle to box face at the start: toes 12 cm clear
        self._approach(centre + fwd * (half + gap))
        self.turn_to(box.yaw + np.pi)
        self.on_furniture = True
        on = gap + 0.12 + 0.5 * max(half - 0.12, 0.0)  # where the feet land, ahead of the start
        up = step_curves(self.calib, 0.0, on, 0.0, top, lead="r")
        i = len(self.pieces)
        self.channel_piece("step_up", cfg.step_s, False, **up)
        self.idle(max(hold * 0.5, 0.2), "stand_on_box")
        self.turn_to(box.yaw)
        # Now facing the front face; the feet are `edge` behind it.
        edge = float(np.dot(centre + fwd * half - self.xy, fwd))
        down = step_curves(self.calib, 0.0, edge + 0.3, top, 0.0, lead="r")
        self.channel_piece("step_down", cfg.step_s, False, **down)
        # The clip: the lead foot leaves the floor at 10 % of step_up (see step_curves), the
        # trailing foot is back on it at 88 % of step_down.
        self.marks.append(("climb", box.name, (i, 0.1), (len(self.pieces) - 1, 0.88), (i + 1, len(self.pieces) - 2)))
        self.on_furniture = False

    def lean_on_table(self, table: Furniture, hold: float) -> None:
        c, cfg = self.calib, self.cfg
        fwd = _heading(table)
        # Wrists 12 cm inside the front edge; the pelvis starts over the ankles.
        stand = np.asarray(table.centre_xy) + fwd * (table.size[0] / 2 - 0.12 + c.lean_reach)
        # The walk ends 30 cm further out, the performer turns to face the table there and walks
        # the last 30 cm in: swinging arms and a turn on the spot that close to the table would
        # sweep the hands through it.
        self._approach(stand + fwd * 0.3)
        self.turn_to(table.yaw + np.pi)
        self.walk_to(stand)
        T = cfg.lean_transition_s
        # The arms swing forward over the top first, elbows bent to carry the hands over the
        # edge; then the torso tilts and lowers the straightened arms onto the top (the hands
        # only go down while over it). Straightening up is the same backwards.
        arm_in, tilt_in = (lambda u: _ease(u / 0.55)), (lambda u: _ease((u - 0.35) / 0.65))
        lift_in = lambda u: _bump(u, 0.0, 0.8)  # noqa: E731
        self.channel_piece("lean_in", T, True, lean=tilt_in, lean_arm=arm_in, lean_lift=lift_in)
        self.channel_piece("lean_table", hold, True, lean=np.ones_like, lean_arm=np.ones_like)
        self.channel_piece("lean_out", T, True, lean=lambda u: tilt_in(1.0 - u),
                           lean_arm=lambda u: arm_in(1.0 - u), lean_lift=lambda u: lift_in(1.0 - u))
        # Step back (a slow shuffle: no faster than the feet's friction allows) before turning away.
        self.shuffle_to(stand + fwd * 0.3, 1.2)

    def interaction(self, name: str, hold: float) -> bool:
        f = self.spec.furniture
        if name in ("chair", "sit") and "chair" in f:
            self.sit(f["chair"], hold)
        elif name == "sofa" and ("sofa" in f or "bed" in f):
            self.sit(f.get("sofa", f.get("bed")), hold)
        elif name in ("box", "climb") and "box" in f:
            self.step_on_box(f["box"], hold)
        elif name in ("table", "support") and "table" in f:
            i = len(self.pieces)
            self.lean_on_table(f["table"], hold)
            # The support clip: from leaning in to the end of leaning out, the hold in between.
            k = i + [p.name for p in self.pieces[i:]].index("lean_in")
            self.marks.append(("support", "table", (k, 0.0), (k + 2, 1.0), (k + 1, k + 1)))
        elif name in ("lie", "prone") and "bed" in f:
            lie_on_bed(self, f["bed"], hold, prone=name == "prone")
        elif name == "follow":
            follow_path(self)
        else:
            return False
        return True

    def wander(self) -> None:
        target = self.lo + self.rng.uniform(0.1, 0.9, size=2) * (self.hi - self.lo)
        if np.linalg.norm(target - self.xy) < 0.8:  # a walk worth the name
            target = self.lo + self.hi - target
        self._approach(target)

    # -- the whole script -----------------------------------------------------------------

    def build(self, n_frames: int) -> None:
        cfg = self.cfg
        self.idle(cfg.idle_s)
        todo = [n for n in cfg.interactions if n in INTERACTIONS]
        # The nearest interaction first (so even a short clip has one), the rest in random order.
        if todo:
            dists = [self._distance_to(n) for n in todo]
            first = todo.pop(int(np.argmin(dists)))
            todo = [first] + [todo[i] for i in self.rng.permutation(len(todo))]
        done = 0
        for name in todo:
            if self.frames >= n_frames:
                break
            saved = (list(self.pieces), self.xy.copy(), self.yaw, self.phase, list(self.marks))
            if not self.interaction(name, cfg.hold_s):
                continue
            if self.frames > n_frames and done > 0:
                # Does not fit: undo it and spend the time walking instead.
                self.pieces, self.xy, self.yaw, self.phase, self.marks = saved
                break
            if self.frames > n_frames:
                # The first interaction must fit: redo it with a short hold if that is enough.
                over = (self.frames - n_frames) / self.fps
                self.pieces, self.xy, self.yaw, self.phase, self.marks = saved
                self.marks = list(self.marks)
                self.interaction(name, max(cfg.hold_s - over, 0.2))
            done += 1
            if self.frames < n_frames:
                self.wander()
        while self.frames < n_frames:
            before = self.frames
            self.wander()
            if self.frames == before:
                self.idle(1.0)

    def _distance_to(self, name: str) -> float:
        f = self.spec.furniture
        if name == "follow":
            return 0.0
        key = {"sofa": "sofa" if "sofa" in f else "bed", "sit": "chair", "climb": "box", "support": "table",
               "lie": "bed", "prone": "bed"}.get(name, name)
        if key not in f:
            return np.inf
        return float(np.linalg.norm(np.asarray(f[key].centre_xy) - self.xy))

    def arrays(self, n_frames: int):
        """Concatenate the pieces and cut to ``n_frames``: xy (T,2), yaw (T,), channels dict,
        lock: (T,) segment id of a locked piece or -1, on_furniture (T,) bool, segments."""
        xy = np.concatenate([p.xy for p in self.pieces])[:n_frames]
        yaw = np.concatenate([p.yaw for p in self.pieces])[:n_frames]
        ch = {}
        for name in CHANNELS:
            ch[name] = np.concatenate([p.ch.get(name, np.zeros(len(p.yaw))) for p in self.pieces])[:n_frames]
        lock = np.concatenate([np.full(len(p.yaw), i if p.lock else -1) for i, p in enumerate(self.pieces)])[:n_frames]
        on_furniture = np.concatenate([np.full(len(p.yaw), p.on_furniture) for p in self.pieces])[:n_frames]
        segments, start = [], 0
        for p in self.pieces:
            end = min(start + len(p.yaw), n_frames)
            if end > start:
                segments.append((p.name, start, end))
            start = end
        # Consecutive locked pieces (sit_down, sit, stand_up) share one anchor: the feet stay
        # where they were when the first of them began.
        for i in range(1, len(self.pieces)):
            if self.pieces[i].lock and self.pieces[i - 1].lock:
                lock[lock == i] = _first_locked(self.pieces, i)
        return xy, yaw, ch, lock, on_furniture, segments


def _first_locked(pieces: list[_Piece], i: int) -> int:
    while i > 0 and pieces[i - 1].lock:
        i -= 1
    return i
