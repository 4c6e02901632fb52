"""Skill clips from body-surface contacts: the per-skill rules (docs/skills.md).

Per frame (see :mod:`embodmocap.skills.contact`): which surface the pelvis, back, front, hands and
feet touch, the pelvis height, the torso pitch (pelvis-to-neck axis from vertical), the feet's
height above the floor and the pelvis speed over the ground. Then:

* **prone / lie / sit** (in this order of precedence): the front on a surface with the torso lying
  = prone; the back on a long surface with the torso lying = lie; the pelvis on a surface with
  the torso upright and the pelvis lowered (``lowered_m`` below its standing height) = sit. A run
  of such frames at least ``min_hold_s`` long is the hold; the clip grows from it over the
  frames with the pelvis still lowered or the posture still changing, and stops where the body
  walks off upright.
* **climb**: both feet on one raised surface (torso upright, pelvis free) for ``min_hold_s``; the
  clip spans the frames with a foot off the floor around it (lift-off to touch-down).
* **support**: both hands on one surface, both feet on the floor within ``feet_together_m``, the
  pelvis free; the clip extends from the hold while the posture keeps changing.
* **follow**: runs of the pelvis moving faster than ``follow_speed_mps`` outside the other clips,
  joined across short stops, at least ``follow_min_s`` long.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from embodmocap.skills.config import SkillsConfig
from embodmocap.skills.contact import NONE, Contacts, Surfaces
from embodmocap.io.stage_files import SkillClip, SkillObject, SkillTarget


def runs(mask: NDArray) -> list[tuple[int, int]]:
    """``[start, end)`` of each run of True in a (T,) bool array."""
    m = np.concatenate([[False], np.asarray(mask, dtype=bool), [False]])
    d = np.diff(m.astype(np.int8))
    return list(zip(np.nonzero(d == 1)[0].tolist(), np.nonzero(d == -1)[0].tolist()))


def bridge(mask: NDArray, gap: int) -> NDArray[np.bool_]:
    """``mask`` with False runs shorter than ``gap`` frames between True runs set True."""
    out = np.asarray(mask, dtype=bool).copy()
    r = runs(out)
    for (_, e), (s, _) in zip(r, r[1:]):
        if s - e < gap:
            out[e:s] = True
    return out


def _speed(x: NDArray, fps: float, win: int) -> NDArray:
    """(T,) speed of points x (T, D) averaged over ``win`` frames first, units per second."""
    from scipy.ndimage import uniform_filter1d

    if len(x) < 2:
        return np.zeros(len(x))
    xs = uniform_filter1d(np.asarray(x, dtype=np.float64), win, axis=0, mode="nearest")
    return np.linalg.norm(np.gradient(xs, axis=0), axis=-1) * fps


def _moving(speed: NDArray, floor_mps: float, factor: float) -> NDArray[np.bool_]:
    """Frames whose speed is above ``floor_mps`` and ``factor`` x the noise floor (the median of
    the quietest quarter of frames)."""
    if len(speed) == 0:
        return np.zeros(0, dtype=bool)
    quiet = np.sort(speed)[: max(len(speed) // 4, 1)]
    return speed > max(floor_mps, factor * float(np.median(quiet)))


def _pitch_deg(c: Contacts) -> NDArray:
    axis = c.neck - c.pelvis
    return np.degrees(np.arccos(np.clip(axis[:, 2] / np.maximum(np.linalg.norm(axis, axis=1), 1e-9), -1, 1)))


def _facing(c: Contacts, s: int, e: int) -> list[float]:
    """Mean 2D direction in front of the hips (``(left hip - right hip) x +Z``) over frames [s, e)."""
    left = c.hips[s:e, 0] - c.hips[s:e, 1]
    f = np.stack([left[:, 1], -left[:, 0]], axis=1).mean(axis=0)
    n = np.linalg.norm(f)
    return [round(float(x), 6) for x in (f / n if n > 0 else np.array([1.0, 0.0]))]


def _same_surface(labels: list[NDArray]) -> NDArray:
    """(T,) the surface all the given (T,) label arrays share (>= 0), else NONE."""
    first = labels[0]
    ok = first >= 0
    for other in labels[1:]:
        ok &= other == first
    return np.where(ok, first, NONE)


def find_clips(c: Contacts, surfaces: Surfaces, fps: float, cfg: SkillsConfig = SkillsConfig()) -> list[SkillClip]:
    """The skill clips of one sequence, in time order (ids numbered per skill)."""
    T = len(c.pelvis)
    if T < 2:
        return []
    gap, hold_n = max(int(round(cfg.gap_s * fps)), 1), max(int(round(cfg.min_hold_s * fps)), 1)
    p = c.part
    pitch = _pitch_deg(c)
    floor = surfaces.floor_z
    hp = c.pelvis[:, 2] - floor
    feet_floor = (c.foot_gap <= cfg.foot_on_floor_m).all(axis=1)
    free = (p["pelvis"] < 0) & (p["back"] < 0) & (p["front"] < 0)
    hands_free = (p["left_hand"] < 0) & (p["right_hand"] < 0)
    upright = pitch < cfg.upright_pitch_deg
    lying = pitch > cfg.lying_pitch_deg
    standing = feet_floor & upright & free & hands_free
    h_stand = float(np.median(hp[standing])) if standing.sum() >= hold_n else float(np.percentile(hp, 90))
    top = np.array([b.top_z for b in surfaces.boxes] + [floor])  # by label; the floor label (-1) -> floor
    long_side = np.array([b.size[0] for b in surfaces.boxes] + [0.0])

    found: list[tuple[str, int, int, int, int, int, float]] = []  # skill, s, e, cs, ce, surface, score
    taken = np.zeros(T, dtype=bool)
    xy = c.pelvis[:, :2]
    win = max(int(round(cfg.smooth_s * fps)), 1)
    speed = _speed(xy, fps, win)
    # The posture is changing (speed), or away from the standing posture (the median posture of
    # the frames standing still: a fit's jitter moves the joints fast but not far).
    moving = _moving(c.posture_speed(fps, cfg.smooth_s), cfg.posture_speed_mps, cfg.noise_factor)
    still = standing & (speed < cfg.follow_speed_mps)
    if still.sum() >= hold_n:
        from scipy.ndimage import uniform_filter1d

        post = uniform_filter1d(c.posture, win, axis=0, mode="nearest")
        away = np.linalg.norm(post - np.median(post[still], axis=0), axis=-1).mean(axis=1)
        moving |= away > max(cfg.posture_away_m, cfg.noise_factor * float(np.median(away[still])))
    lowered = hp < h_stand - cfg.lowered_m
    # Walking off ends a clip: upright, the pelvis at standing height and moving over the ground
    # with a gait (one foot planted while the other swings, double support bridged). Sitting down
    # moves the pelvis with both feet planted; sliding onto a bed moves both feet with it.
    foot_speed = np.stack([_speed(c.ankles[:, k, :2], fps, 3) for k in (0, 1)], axis=1)
    gait = ((foot_speed.min(axis=1) < 0.5 * speed) & (foot_speed.max(axis=1) > 1.2 * speed)
            & _moving(speed, cfg.follow_speed_mps, cfg.noise_factor))
    gait = bridge(gait, 2 * gap)
    for s_, e_ in runs(gait):  # about a step at least: shorter runs are jitter, not walking
        if e_ - s_ < int(round(0.3 * fps)):
            gait[s_:e_] = False
    walking_off = gait & upright & ~lowered

    posture_speed = c.posture_speed(fps, cfg.smooth_s)
    settle = max(int(round(0.5 * fps)), 1)

    def widen(a: int, b: int, inside: NDArray) -> tuple[int, int]:
        """The hold [a, b) grown outward over the frames still ``inside`` the interaction or
        changing posture, never into another clip nor into walking off. Where walking off stops
        it, the boundary moves to the quietest posture frame of the half second before the walk
        (the body pauses, if briefly, between getting up and walking away)."""
        grow = (inside | moving) & ~walking_off & ~taken
        a0, b0 = a, b
        while a > 0 and grow[a - 1]:
            a -= 1
        if a > 0 and walking_off[a - 1]:
            lo = min(a + settle, a0)
            a = a + int(np.argmin(posture_speed[a:lo])) if lo > a else a
        while b < T and grow[b]:
            b += 1
        if b < T and walking_off[b]:
            hi = max(b - settle, b0)
            b = hi + int(np.argmin(posture_speed[hi:b])) + 1 if b > hi else b
        return a, b

    # prone / lie / sit: a contact hold, grown over the lowered pelvis and the posture change.
    front, back, seat = p["front"], p["back"], p["pelvis"]
    is_long = lambda lab: (lab >= 0) & (long_side[np.maximum(lab, 0)] >= cfg.long_surface_m)  # noqa: E731
    rules = (("prone", (front >= 0) & lying, front), ("lie", (back >= 0) & lying & is_long(back), back),
             ("sit", (seat >= 0) & upright & lowered, seat))
    for skill, frames, surf in rules:
        for s, e in runs(bridge(frames & ~taken, gap)):
            if e - s < hold_n or taken[s:e].any():
                continue
            vals = surf[s:e][surf[s:e] >= 0]
            k = int(np.bincount(vals).argmax())
            a, b = widen(s, e, lowered)
            found.append((skill, a, b, s, e, k, float(frames[s:e].mean())))
            taken[a:b] = True

    # climb: both feet on one raised surface.
    on = _same_surface([p["left_foot"], p["right_foot"]])
    raised = (on >= 0) & (top[np.maximum(on, 0)] - floor >= cfg.climb_min_height_m) & upright & free
    off = ~feet_floor
    for s, e in runs(bridge(raised, gap)):
        if e - s < hold_n or taken[s:e].any():
            continue
        k = int(np.bincount(on[s:e][on[s:e] >= 0]).argmax())
        r = next(((a, b) for a, b in runs(off) if a <= s and b >= e), (s, e))
        found.append(("climb", r[0], r[1], s, e, k, float(raised[s:e].mean())))
        taken[r[0]:r[1]] = True

    # support: both hands bearing on one surface, feet together on the floor.
    hands = _same_surface([p["left_hand"], p["right_hand"]])
    together = np.linalg.norm(c.ankles[:, 0, :2] - c.ankles[:, 1, :2], axis=1) <= cfg.feet_together_m
    sup = (hands >= 0) & feet_floor & together & (seat < 0)  # a deep lean may pitch the torso past upright
    for s, e in runs(bridge(sup, gap)):
        if e - s < hold_n or taken[s:e].any():
            continue
        k = int(np.bincount(hands[s:e][hands[s:e] >= 0]).argmax())
        a, b = widen(s, e, (p["left_hand"] == k) | (p["right_hand"] == k))
        found.append(("support", a, b, s, e, k, float(sup[s:e].mean())))
        taken[a:b] = True

    # follow: walking runs outside the other clips.
    walking = _moving(speed, cfg.follow_speed_mps, cfg.noise_factor) & ~taken
    joined = bridge(walking, int(round(cfg.follow_gap_s * fps))) & ~taken
    for s, e in runs(joined):
        if (e - s) / fps < cfg.follow_min_s:
            continue
        found.append(("follow", s, e, -1, -1, NONE, float(walking[s:e].mean())))

    out, count = [], {}
    for skill, s, e, cs, ce, k, score in sorted(found, key=lambda f: f[1]):
        n = count.get(skill, 0)
        count[skill] = n + 1
        if skill == "follow":
            t = np.arange(s, e - 1e-9, cfg.path_dt_s * fps)
            path = np.stack([np.interp(t, np.arange(T), xy[:, 0]), np.interp(t, np.arange(T), xy[:, 1])], axis=1)
            out.append(SkillClip(f"follow_{n:02d}", "follow", s, e, None, None, None,
                                 SkillTarget(None, [[round(float(a), 6), round(float(b), 6)] for a, b in path], None),
                                 ["left_foot", "right_foot"], round(score, 4)))
            continue
        box = surfaces.boxes[k]
        above = {"sit": cfg.sit_target_above_m, "climb": cfg.climb_target_above_m, "lie": cfg.lie_target_above_m,
                 "prone": cfg.lie_target_above_m, "support": 0.0}[skill]
        pos = [float(box.center[0]), float(box.center[1]), float(box.top_z + above)]
        if skill == "support":
            # The hand joints' centre over the hold: the supplement's "object surface centre" is
            # the centre of what the hands bear on (its support objects are small; on a table the
            # centre of the whole top is out of reach). Its height is the hand joints' while they
            # rest on the top (a palm's thickness above it, which depends on the body), so the
            # 10 cm success test measures where the hands are, not the body's proportions.
            pos = [float(x) for x in c.hands[cs:ce].mean(axis=(0, 1))]
        parts = [name for name, lab in p.items() if np.mean(lab[cs:ce] == k) >= 0.5]
        out.append(SkillClip(f"{skill}_{n:02d}", skill, s, e, cs, ce, SkillObject.of_box(box, f"surface_{k:02d}"),
                             SkillTarget([round(x, 6) for x in pos], None, _facing(c, cs, ce)), parts, round(score, 4)))
    return out


__all__ = ["find_clips", "runs", "bridge"]
