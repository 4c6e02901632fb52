"""Pieces of the studio's planner (:mod:`embodmocap.synth.motion`, kept apart so that module
stays small; each function takes the planner ``pl``): lying on the bed on the back or the front,
walking a curved path, the feet's curves stepping onto and off the box, and the scripted skill
clips. Private to the studio."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from embodmocap.synth.motion_base import _ease, _heading
from embodmocap.synth.spec import Furniture

#: Pieces that are part of walking along a path (:attr:`MotionScript.clips` ``follow``): the
#: step back from the table and the step away from a sofa or bed move over the ground like a walk
#: (shuffles of 30 and 20 cm).
_WALKING: tuple[str, ...] = ("walk", "turn", "follow", "step_back", "step_away")

#: Thickness of the bed's headboard (:func:`embodmocap.synth.scene._piece_parts`), metres.
_HEADBOARD_M = 0.08

@dataclass(frozen=True)
class ScriptedClip:
    """One scripted interaction as a skill clip, frames end exclusive (the truth for the clip finder).

    Attributes:
        skill: ``follow``, ``sit``, ``climb``, ``lie``, ``prone`` or ``support``.
        start, end: the clip: sit / lie / prone from the start of sitting (lying) down to the end
            of standing up; climb from the lead foot's lift-off to the trailing foot's touch-down
            back on the floor; support from the start of leaning in to the end of leaning out;
            follow: a run of walking pieces (``walk``, ``follow``, ``step_back``, ``step_away``, turns between
            them), from the first piece that moves (a walk of 15 cm or more, a turn stepping 5 cm
            or more) to the last.
        contact_start, contact_end: the hold (seated, lying, standing on the box, leaning);
            None for follow.
        furniture: the piece of furniture used (a :class:`~embodmocap.synth.spec.SceneSpec`
            furniture key), None for follow.
    """

    skill: str
    start: int
    end: int
    contact_start: int | None = None
    contact_end: int | None = None
    furniture: str | None = None


def lie_on_bed(pl, bed: Furniture, hold: float, prone: bool) -> None:
    """Lie down on the bed along its length, head toward the headboard (local -y): on the back
    from standing with the back to the bed's front edge, on the front from standing facing it.

    One eased piece goes from standing to lying: a crouch (the bed's seated hip/knee angles,
    peaking half way), the whole body pitching by 90 degrees about the pelvis, the heading
    turning by 90 degrees to lie along the bed and the pelvis moving onto its middle. The
    furniture support then rests the lowest vertices on the top, so nothing sinks into it;
    getting up replays the piece backwards."""

    c, cfg = pl.calib, pl.cfg
    fwd = _heading(bed)
    side = np.array([-fwd[1], fwd[0]])  # the bed's local +y: from the headboard to the foot end
    centre = np.asarray(bed.centre_xy, dtype=np.float64)
    # Pelvis along the bed: the top of the head 12 cm clear of the headboard.
    along = -bed.size[1] / 2 + _HEADBOARD_M + 0.12 + c.head_top
    lie_xy = centre + side * along
    st = c.seats.get(bed.name)
    hip, knee = (st.hip, st.knee) if st is not None else (np.deg2rad(90.0), np.deg2rad(90.0))
    # Facing the bed (prone), the crouch brings the feet forward: start that much further out.
    gap = 0.25 + (max(st.feet_ahead, 0.0) + c.toe_ahead if prone and st is not None else 0.0)
    stand = centre + fwd * (bed.size[0] / 2 + gap) + side * along
    yaw0 = bed.yaw + (np.pi if prone else 0.0)       # facing the bed / facing away from it
    turn = np.pi / 2                                  # supine: feet to +y; prone: head to -y
    tilt = np.pi / 2 if prone else -np.pi / 2
    pl._approach(stand + fwd * 0.15)
    pl.turn_to(float(yaw0), stand)
    start = pl.xy.copy()

    def pose(u: NDArray) -> tuple[NDArray, NDArray, dict]:
        p = _ease((u - 0.2) / 0.8)
        crouch = 0.8 * np.sin(np.pi * np.clip(u, 0.0, 1.0)) ** 2
        ch = {"sit": crouch, "sit_hip": np.full_like(u, hip), "sit_knee": np.full_like(u, knee), "body_tilt": tilt * p,
              "point_toes": (1.2 if prone else 0.3) * p, "head_turn": (1.3 if prone else 0.0) * p}
        return start + p[:, None] * (lie_xy - start), yaw0 + turn * p, ch

    name = "prone" if prone else "lie"
    pl.on_furniture = True
    i = len(pl.pieces)
    u = pl._u(cfg.lie_transition_s)
    xy, yaw, ch = pose(u)
    pl._add(f"{name}_down", xy, yaw, **ch)
    n = pl._n(hold)
    xy, yaw, ch = pose(np.ones(n))
    pl._add(name, xy, yaw, **ch)
    xy, yaw, ch = pose(1.0 - u)
    pl._add("get_up", xy, yaw, **ch)
    pl.marks.append((name, bed.name, (i, 0.0), (i + 2, 1.0), (i + 1, i + 1)))
    pl.on_furniture = False
    pl.walk_to(pl.xy + fwd * 0.5)


def follow_path(pl) -> None:
    """Walk without stopping along a smooth curve through the walk area: a clamped quadratic
    B-spline whose control points are the current position and ``follow_waypoints`` random
    points of the walk area (the curve stays inside their convex hull, so inside the area), each
    turning the control polygon by at most 90 degrees."""
    from scipy.interpolate import BSpline

    cfg, rng = pl.cfg, pl.rng
    pts = [np.clip(pl.xy, pl.lo, pl.hi)]
    for _ in range(max(cfg.follow_waypoints, 2)):
        # A point worth walking to (not right next to the last one) that turns the path by at
        # most 90 degrees: the curve's sharpest bend, so the heading's turning speed, stays mild.
        best, best_turn = None, np.inf
        for _ in range(50):
            q = pl.lo + rng.uniform(0.1, 0.9, size=2) * (pl.hi - pl.lo)
            if np.linalg.norm(q - pts[-1]) < 0.8:
                continue
            turn = 0.0
            if len(pts) > 1:
                a, b = pts[-1] - pts[-2], q - pts[-1]
                turn = float(np.arccos(np.clip(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)), -1.0, 1.0)))
            if turn < best_turn:
                best, best_turn = q, turn
            if turn <= np.pi / 2:
                break
        if best is not None:
            pts.append(best)
    if len(pts) < 3:  # a walk area too small for a path: a plain walk
        pl.walk_to(pts[-1])
        return
    if np.linalg.norm(pts[0] - pl.xy) > 0.1:
        pl.walk_to(pts[0])
    P = np.asarray(pts)
    k, m = 2, len(P)
    knots = np.concatenate([np.zeros(k), np.linspace(0.0, 1.0, m - k + 1), np.ones(k)])
    curve = BSpline(knots, P, k)
    dense = curve(np.linspace(0.0, 1.0, 2000))
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=1))])
    L = float(arc[-1])
    tang = np.diff(dense, axis=0)
    head = np.unwrap(np.arctan2(tang[:, 1], tang[:, 0]))
    head = np.concatenate([head[:1], head])
    pl.turn_to(float(head[0]))
    head = head - head[0] + pl.yaw  # continuous with the current heading
    v, b = cfg.walk_speed_mps, cfg.ease_s
    D = max(L / v + b, 2 * b)
    t = np.arange(pl._n(D) + 1) / pl.fps
    D = t[-1]
    speed = np.minimum(_ease(t / b), _ease((D - t) / b))
    s = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]))])
    s = s / s[-1] * L
    amp = np.clip(np.gradient(s, t) / v, 0.0, 1.0)[1:]
    phase = pl.phase + np.pi * s[1:] / (v / cfg.cadence_steps_per_s)
    xy = np.stack([np.interp(s[1:], arc, dense[:, 0]), np.interp(s[1:], arc, dense[:, 1])], axis=1)
    pl._add("follow", xy, np.interp(s[1:], arc, head), gait_amp=amp, gait_phase=phase)
    pl.phase = float(phase[-1])


def lift_envelope(z: NDArray, lying: NDArray, fps: float, max_speed_mps: float = 1.5) -> NDArray:
    """(T,) heights ``z`` raised to the smallest curve that is nowhere below them at the ``lying``
    frames and changes no faster than ``max_speed_mps`` from there on: ``max(z(t), max over lying
    s of z(s) - max_speed * |t - s|)``.

    While lying down the furniture lifts the body as soon as a vertex below its top comes over its
    footprint (a knee or a foot swinging over the edge): a jump of tens of centimetres in one
    frame. The envelope starts rising before such a jump and comes down after it at a bounded
    speed; it never lowers the body, so nothing sinks into the furniture. Frames away from lying
    (every frame of the original four interactions) keep their heights exactly."""
    z0 = np.asarray(z, dtype=np.float64)
    z = z0.copy()
    src = np.nonzero(lying)[0]
    if len(src) == 0:
        return z
    t = np.arange(len(z))
    step = max_speed_mps / fps
    for a in range(0, len(src), 256):  # chunks bound the (T, chunk) array
        s = src[a:a + 256]
        z = np.maximum(z, (z0[s][None, :] - step * np.abs(t[:, None] - s[None, :])).max(axis=1))
    return z


def scripted_clips(pl, n_frames: int) -> list[ScriptedClip]:
    """The scripted skill clips inside the first ``n_frames`` frames, in time order."""
    starts = np.cumsum([0] + [len(p.yaw) for p in pl.pieces])
    at = lambda i, frac: int(starts[i] + round(frac * (starts[i + 1] - starts[i])))  # noqa: E731
    out = []
    for skill, furniture, (i, a), (j, b), (ci, cj) in pl.marks:
        s, e = at(i, a), at(j, b)
        if e <= n_frames:
            out.append(ScriptedClip(skill, s, e, int(starts[ci]), int(starts[cj + 1]), furniture))
    # Follow: each run of walking pieces, from the first piece that moves to the last.
    k = 0
    while k < len(pl.pieces):
        if pl.pieces[k].name not in _WALKING:
            k += 1
            continue
        run = []
        while k < len(pl.pieces) and pl.pieces[k].name in _WALKING:
            run.append(k)
            k += 1
        # A turn that steps aside moves; a walk shorter than 15 cm is a shuffle (its peak speed,
        # under 0.3 m/s, barely walking), not part of the path.
        # Only the part inside the motion counts (the last piece may be cut short).
        inside = [pl.pieces[r].xy[:max(n_frames - int(starts[r]), 0)] for r in run]
        moving = [r for r, xy in zip(run, inside) if len(xy) > 1 and np.linalg.norm(xy[-1] - xy[0])
                  > (0.05 if pl.pieces[r].name == "turn" else 0.15)]
        if moving and starts[moving[0]] < n_frames:
            out.append(ScriptedClip("follow", int(starts[moving[0]]), int(min(starts[moving[-1] + 1], n_frames))))
    return sorted(out, key=lambda c: c.start)


def step_curves(c, x0: float, x1: float, z0: float, z1: float, lead: str) -> dict:
    """IK channel curves u -> value for a two-footed step from (x0, support z0) to (x1, z1):
    the leading foot moves in the first half, the pelvis shifts over in the middle, the other
    foot follows. Each foot rises 8 cm above the higher support before moving forward and
    comes down only after it has arrived. ``c``: the body calibration (``ankle_h``, ``hip_h``)."""

    clear = max(z0, z1) + 0.08

    def foot(a: float, b: float):
        # up over the first 35 % of [a, b], across over 25-75 %, down over the last 35 %.
        w = b - a
        def x(u):
            return x0 + (x1 - x0) * _ease((u - a - 0.25 * w) / (0.5 * w))
        def z(u):
            rise = _ease((u - a) / (0.35 * w)) * (clear - z0) + z0
            fall = clear + (z1 - clear) * _ease((u - b + 0.35 * w) / (0.35 * w))
            return c.ankle_h + np.where(u < a + 0.5 * w, rise, fall)
        return x, z

    lx, lz = foot(0.1, 0.5)
    tx, tz = foot(0.5, 0.88)
    hip_x = lambda u: x0 + (x1 - x0) * _ease((u - 0.25) / 0.55)  # noqa: E731
    hip_z = lambda u: c.hip_h + z0 + (z1 - z0) * _ease((u - 0.3) / 0.45)  # noqa: E731
    lead_x, lead_z, trail_x, trail_z = ("ar_x", "ar_z", "al_x", "al_z") if lead == "r" else ("al_x", "al_z", "ar_x", "ar_z")
    # The IK legs blend in and out over the first and last 10 % (the IK knee is never quite
    # straight, the standing pose around the piece is).
    ik = lambda u: np.minimum(_ease(u / 0.1), _ease((1.0 - u) / 0.1))  # noqa: E731
    return {"ik": ik, lead_x: lx, lead_z: lz, trail_x: tx, trail_z: tz, "hip_x": hip_x, "hip_z": hip_z}
