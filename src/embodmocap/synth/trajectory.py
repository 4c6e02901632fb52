"""Camera trajectories of the synthetic studio, VIO worlds with drift, and IMU readings.

All poses are ``T_scene_cam`` (or ``T_vio_cam``): (T, 4, 4) camera-to-world, Z-up metres, OpenCV
camera axes (x right, y down, z forward). Every function is deterministic given its generator.

- :func:`scene_walk`: one handheld phone walking a loop around the free centre of the empty scene,
  looking out at the walls and furniture and in across the floor the performer will walk on (for
  the scene capture: TSDF + SfM).
- :func:`follow_views`: two operators walking around the performer, 60-120 degrees apart, aiming
  at the pelvis with a small lag.
- :func:`random_T_scene_vio`, :func:`add_drift`: each recording's own gravity-aligned VIO world and
  its slow drift.
- :func:`synth_imu`: accelerometer (specific force) and gyroscope readings in the camera frame.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter1d

from embodmocap.geometry.transforms import look_at_R, make_T, rot_z
from embodmocap.synth.spec import SceneSpec

log = logging.getLogger(__name__)

GRAVITY_MPS2 = 9.81
"""Magnitude of gravity used for the IMU's specific force."""


# ------------------------------------------------------------------------------------------------
# Shared pieces


def _smooth_noise(n: int, sigma_frames: float, rng: np.random.Generator, dims: int) -> NDArray[np.float64]:
    """(n, dims) band-limited noise with unit standard deviation (Gaussian-filtered white noise)."""
    pad = int(4 * sigma_frames) + 1
    w = rng.standard_normal((n + 2 * pad, dims))
    s = gaussian_filter1d(w, sigma_frames, axis=0, mode="wrap")[pad:pad + n] if sigma_frames > 0 else w[pad:pad + n]
    return s / max(float(s.std()), 1e-12)


def _small_rotations(rotvec: NDArray) -> NDArray[np.float64]:
    """Rotation matrices (T, 3, 3) of rotation vectors (T, 3) (Rodrigues)."""
    from embodmocap.geometry.rotations import rotvec_to_matrix

    return rotvec_to_matrix(rotvec)


@dataclass(frozen=True)
class ShakeConfig:
    """Hand shake: small, fast, random motion of a handheld phone."""

    trans_sigma_m: float = 0.003
    """Standard deviation of the positional jitter, metres."""
    rot_sigma_deg: float = 0.3
    """Standard deviation of the rotational jitter about each camera axis, degrees."""
    smooth_s: float = 0.06
    """Gaussian smoothing of the jitter, seconds (sets its frequency content: ~2-8 Hz)."""


def _add_shake(T_world_cam: NDArray, fps: float, rng: np.random.Generator, cfg: ShakeConfig) -> NDArray[np.float64]:
    n = len(T_world_cam)
    sig = cfg.smooth_s * fps
    dt = _smooth_noise(n, sig, rng, 3) * cfg.trans_sigma_m
    dr = _small_rotations(_smooth_noise(n, sig, rng, 3) * np.deg2rad(cfg.rot_sigma_deg))
    out = np.array(T_world_cam, dtype=np.float64, copy=True)
    out[:, :3, :3] = out[:, :3, :3] @ dr  # jitter about the camera's own axes
    out[:, :3, 3] += dt
    return out


# ------------------------------------------------------------------------------------------------
# The scene capture


@dataclass(frozen=True)
class SceneWalkConfig:
    """The empty-scene capture's walk."""

    speed_mps: tuple[float, float] = (0.3, 0.5)
    """Walking speed range, m/s; a loop shorter than ``speed * seconds`` is walked more than once."""
    corner_radius_m: float = 0.6
    """Radius of the loop's rounded corners, metres (bounds the turning rate)."""
    height_m: tuple[float, float] = (1.25, 1.55)
    """Range of the phone's height, metres."""
    target_height_m: tuple[float, float] = (0.35, 1.3)
    """Range of the height of the point looked at (on the walls / furniture), metres."""
    sweep_deg: float = 55.0
    """Amplitude of the left-right sweep of the view about the loop's outward normal, degrees."""
    sweep_period_s: float = 12.0
    """Period of that sweep, seconds."""
    max_pitch_deg: float = 40.0
    """The view never points more than this far below the horizon, degrees."""
    turns_per_lap: float = 1.0
    """Turns of the view about the vertical, relative to the loop's outward normal, per lap
    walked (the same way round as the walk; the sweep still rides on it). With 1 the phone looks
    out at the walls near it, then along the loop, then in across the walk area (its floor in the
    lower part of the frame, the far walls and furniture in the upper part: ``across_pitch_deg``),
    then along the loop again: every wall is seen from near and from across the room, the way the
    performers' phones see it, and the floor where the performer walks is seen without stopping.
    0 = always outwards (the earlier scan, which never sees the middle of the room)."""
    across_pitch_deg: float = 28.0
    """How far below the horizon the view points while looking in across the loop, degrees (with
    a 4:3 frame at 67 deg across, 28 puts the horizon near the top edge: floor from ~1.2 m out,
    walls and furniture up to about the phone's height)."""
    glance_every_s: float = 0.0
    """One look back across the loop at the floor inside it per this many seconds (at least one
    per capture; 15 is a good value): looking outwards only, the phone never sees the middle of the
    room, where the performer walks. 0 = never (the default: in a 15 s scan the stop takes 9 s
    from the walls and furniture, and Stage III then registered only 7 of 16 view frames of
    tests/test_calibrate_register.py's session, which needs >= 90 %; ``turns_per_lap`` sees that
    floor while walking instead)."""
    glance_turn_s: float = 3.0
    """Time to turn round for a glance, and to turn back, seconds (slow: a handheld phone's turn
    rate stays under ~120 deg/s with the loop's own turning)."""
    glance_hold_s: float = 0.8
    """Time spent looking back at the floor about 1.6 m away, seconds."""
    shake: ShakeConfig = ShakeConfig()
    """Hand shake."""


def _rounded_rect(lo: NDArray, hi: NDArray, radius: float, s: NDArray) -> tuple[NDArray, NDArray]:
    """Points (T, 2) and outward unit normals (T, 2) at arc lengths ``s`` (T,) along a rounded
    rectangle (counter-clockwise, starting at the middle of the bottom side)."""
    r = float(min(radius, 0.49 * np.min(hi - lo)))
    a, b = (hi - lo - 2 * r)  # straight lengths along x and y
    quarter = np.pi * r / 2
    seg = np.array([a, quarter, b, quarter, a, quarter, b, quarter])
    L = seg.sum()
    s = np.mod(s + a / 2, L)  # start at the middle of the bottom side
    ends = np.cumsum(seg)
    k = np.searchsorted(ends, s, side="right").clip(0, 7)
    u = s - (ends[k] - seg[k])  # arc length inside segment k
    # Corner centres (bottom-right, top-right, top-left, bottom-left) and the normal's start angle.
    cc = np.array([[hi[0] - r, lo[1] + r], [hi[0] - r, hi[1] - r], [lo[0] + r, hi[1] - r], [lo[0] + r, lo[1] + r]])
    side_start = np.array([[lo[0] + r, lo[1]], [hi[0], lo[1] + r], [hi[0] - r, hi[1]], [lo[0], hi[1] - r]])
    side_dir = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])
    side_normal = np.array([[0.0, -1.0], [1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]])
    i = k // 2
    straight = k % 2 == 0
    ang = -np.pi / 2 + i * np.pi / 2 + u / max(r, 1e-9)
    arc_n = np.stack([np.cos(ang), np.sin(ang)], axis=-1)
    p = np.where(straight[:, None], side_start[i] + side_dir[i] * u[:, None], cc[i] + r * arc_n)
    n = np.where(straight[:, None], side_normal[i], arc_n)
    return p, n


#: Time to come to a stop before a glance (and to walk on after it), seconds.
_GLANCE_STOP_S = 1.2


def _glances(n: int, fps: float, cfg: SceneWalkConfig, rng: np.random.Generator,
             sweep: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Looks back across the loop, one per ``glance_every_s`` at a random place in its slot:
    ``(weight, turn, still)``, each (n,). The operator slows to a stop (``still`` 0 -> 1), the view
    turns round by pi (quintic ease; ``turn`` in radians) the way the ``sweep`` (n,) is turned at
    the time (so that fading the sweep out slows the turn down instead of adding to it), holds,
    and goes on turning the same way back to outwards (a full turn on the spot: every direction
    is seen once more), then the walk resumes. ``weight`` (0 outside, 1 while looking back) fades
    the sweep out and the floor look in."""
    w, turn, still = np.zeros(n), np.zeros(n), np.zeros(n)
    seconds = n / fps
    if _glance_seconds(seconds, cfg) == 0:
        return w, turn, still
    length = 2 * cfg.glance_turn_s + cfg.glance_hold_s + 2 * _GLANCE_STOP_S
    k = round(_glance_seconds(seconds, cfg) / length)
    slot = seconds / k
    t = np.arange(n) / fps

    def ramp(x):
        x = np.clip(x, 0.0, 1.0)
        return x * x * x * (x * (6.0 * x - 15.0) + 10.0)

    for i in range(k):
        start = i * slot + rng.uniform(0.0, max(slot - length, 0.0))
        t0 = start + _GLANCE_STOP_S
        sign = 1.0 if sweep[min(int(t0 * fps), n - 1)] >= 0 else -1.0
        up = ramp((t - t0) / cfg.glance_turn_s)
        down = ramp((t - t0 - cfg.glance_turn_s - cfg.glance_hold_s) / cfg.glance_turn_s)
        w = np.maximum(w, up - down)
        turn += sign * np.pi * (up + down)
        still = np.maximum(still, ramp((t - start) / _GLANCE_STOP_S) - ramp((t - start - length + _GLANCE_STOP_S) / _GLANCE_STOP_S))
    return w, turn, still


def _glance_seconds(seconds: float, cfg: SceneWalkConfig) -> float:
    """Time a capture of ``seconds`` spends stopped for its glances back across the loop."""
    length = 2 * cfg.glance_turn_s + cfg.glance_hold_s + 2 * _GLANCE_STOP_S
    if cfg.glance_every_s <= 0 or seconds < length + 5.0:
        return 0.0
    return max(int(seconds // cfg.glance_every_s), 1) * length


def _exit_distance(p: NDArray, d: NDArray, lo: NDArray, hi: NDArray) -> NDArray:
    """Distance (T,) from points p (T, 2) inside [lo, hi] along unit directions d (T, 2) to the boundary."""
    with np.errstate(divide="ignore"):
        t = np.abs(np.where(d > 0, hi - p, lo - p) / d)
    return t.min(axis=1)


def scene_walk(spec: SceneSpec, seconds: float, fps: float, rng: np.random.Generator,
               cfg: SceneWalkConfig = SceneWalkConfig()) -> NDArray[np.float64]:
    """A handheld phone walking loops around the free centre of the scene: (T, 4, 4) ``T_scene_cam``.

    The phone follows a rounded rectangle just inside the walk area (away from furniture and
    walls), at 1.25-1.55 m, looking at the walls and furniture with a slow left-right sweep and a
    slowly changing pitch (floor, furniture tops, walls), plus hand shake. The view turns round
    relative to the walk ``turns_per_lap`` times per lap: out at the walls near it (1-4 m away),
    along the loop, in across the walk area (pitched down ``across_pitch_deg``: the floor where
    the performer will walk below, the far walls above), along again. With ``turns_per_lap=0`` it
    only looks outwards. Once per ``glance_every_s`` (off by default) the operator stops, turns
    round and looks at the floor inside the loop, then turns back. ``T = round(seconds * fps)``.
    """
    n = max(int(round(seconds * fps)), 2)
    t = np.arange(n) / fps
    lo = np.asarray(spec.walk_area_min_xy, float) + 0.1
    hi = np.asarray(spec.walk_area_max_xy, float) - 0.1
    # Shrink the loop about its centre until one lap fits in the recording at the top speed: the
    # phone looks outwards, so a whole lap is what makes every wall visible.
    outward_s = n / fps - _glance_seconds(n / fps, cfg)
    lap_max = 0.9 * cfg.speed_mps[1] * n / fps
    if 2 * (hi - lo).sum() > lap_max:
        mid, half = (lo + hi) / 2, (hi - lo) / 2
        half = np.maximum(half * lap_max / (2 * (hi - lo).sum()), 0.3)
        lo, hi = mid - half, mid + half
    r = cfg.corner_radius_m
    loop = 2 * (hi - lo).sum() - (8 - 2 * np.pi) * min(r, 0.49 * np.min(hi - lo))
    v = float(np.clip(1.05 * loop / outward_s, *cfg.speed_mps))
    speed = v * (1.0 + 0.12 * _smooth_noise(n, 1.5 * fps, rng, 1)[:, 0])
    s0 = rng.uniform(0, loop)
    spin = -1.0 if rng.random() < 0.5 else 1.0  # clockwise / counter-clockwise loop
    ph = rng.uniform(0, 2 * np.pi, 3)
    sweep = np.deg2rad(cfg.sweep_deg) * np.sin(2 * np.pi * t / cfg.sweep_period_s + ph[0])
    # Glances back across the loop: the operator stops and turns round on the spot (the sweep
    # fading out meanwhile), looks at the floor, turns on round to outwards, walks on.
    glance, back, still = _glances(n, fps, cfg, rng, sweep)
    s = spin * (s0 + np.cumsum(speed * (1.0 - still)) / fps)
    xy, outward = _rounded_rect(lo, hi, r, s)
    # Turning the view round relative to the walk (turns_per_lap): out, along, in across the loop.
    rel = 2 * np.pi * cfg.turns_per_lap * (s - s[0]) / loop
    turn = (1.0 - glance) * (sweep + rel) + back
    inward = 0.5 * (1.0 - np.cos(rel + sweep)) * (1.0 - glance)  # 0 looking out, 1 looking in
    c, sn = np.cos(turn), np.sin(turn)
    look = np.stack([c * outward[:, 0] - sn * outward[:, 1], sn * outward[:, 0] + c * outward[:, 1]], axis=-1)
    floor_lo, floor_hi = np.asarray(spec.floor_min_xy, float), np.asarray(spec.floor_max_xy, float)
    dist = 0.9 * _exit_distance(xy, look, floor_lo, floor_hi)
    # Stopped, the phone looks down as far as it goes (the pitch limit) during the whole turn, so
    # the turn sees the floor all round the stop from ~0.6 m out (the loop the performer walks).
    dist = (1.0 - still) * dist + still * np.minimum(dist, 1.0)
    h0, h1 = cfg.height_m
    height = (h0 + h1) / 2 + (h1 - h0) / 2 * np.sin(2 * np.pi * t / 11.0 + ph[1])
    g0, g1 = cfg.target_height_m
    tz = (g0 + g1) / 2 + (g1 - g0) / 2 * np.sin(2 * np.pi * t / 6.5 + ph[2])
    tz = (1.0 - still) * tz  # a glance looks at the floor
    # Looking in across the loop: pitched down so the floor fills the lower part of the frame.
    if cfg.turns_per_lap:
        pitch = (1.0 - inward) * np.arctan2(height - tz, dist) + inward * np.deg2rad(cfg.across_pitch_deg)
        tz = height - np.tan(pitch) * dist
    tz = np.maximum(tz, height - np.tan(np.deg2rad(cfg.max_pitch_deg)) * dist)
    centres = np.column_stack([xy, height])
    targets = np.column_stack([xy + look * dist[:, None], tz])
    T = make_T(look_at_R(centres, targets), centres)
    return _add_shake(T, fps, rng, cfg.shake)


# ------------------------------------------------------------------------------------------------
# The two operators following the performer


@dataclass(frozen=True)
class FollowConfig:
    """The two operators who film the performer."""

    dist_m: tuple[float, float] = (2.0, 3.2)
    """Range of each operator's preferred horizontal distance to the performer, metres (the
    product assumes 1.5-4 m; the margin absorbs smoothing and the performer's sway)."""
    dist_limits_m: tuple[float, float] = (1.75, 3.6)
    """Hard limits of the distance when stepping in or out to avoid obstacles, metres."""
    sep_deg: tuple[float, float] = (75.0, 105.0)
    """Range of the azimuth separation of the two operators about the performer, degrees."""
    height_m: tuple[float, float] = (1.35, 1.55)
    """Range of the phones' heights, metres."""
    orbit_deg_s: tuple[float, float] = (3.0, 8.0)
    """Range of the speed at which the pair slowly circles the performer, degrees per second."""
    margin_m: float = 0.35
    """Minimum distance of an operator to the walls / fence, metres."""
    furniture_margin_m: float = 0.25
    """Operators avoid furniture footprints grown by this much, metres."""
    lag_s: float = 0.15
    """Time constant of the aim's lag behind the performer's pelvis, seconds."""
    smooth_s: float = 0.5
    """Gaussian smoothing of the operators' paths, seconds."""
    bins: int = 72
    """Number of azimuth bins of the path search (72 = 5 degrees)."""
    step_s: float = 0.2
    """Time step of the path search, seconds."""
    max_orbit_deg_s: float = 50.0
    """Fastest the pair may circle the performer, degrees per second."""
    shake: ShakeConfig = ShakeConfig()
    """Hand shake."""


def _operator_cost(spec: SceneSpec, pts: NDArray, cfg: FollowConfig) -> NDArray:
    """Penalty (...) of operator positions pts (..., 2): outside the room (hard) or in furniture (soft)."""
    lo = np.asarray(spec.floor_min_xy, float) + cfg.margin_m
    hi = np.asarray(spec.floor_max_xy, float) - cfg.margin_m
    out = np.maximum(lo - pts, 0).sum(-1) + np.maximum(pts - hi, 0).sum(-1)
    cost = np.where(out > 0, 100.0 + 100.0 * out, 0.0)
    for f in spec.furniture.values():
        c, s = np.cos(f.yaw), np.sin(f.yaw)
        rel = pts - np.asarray(f.centre_xy, float)
        lx, ly = c * rel[..., 0] + s * rel[..., 1], -s * rel[..., 0] + c * rel[..., 1]
        half = np.asarray(f.size[:2], float) / 2 + cfg.furniture_margin_m
        cost = cost + np.where((np.abs(lx) < half[0]) & (np.abs(ly) < half[1]), 20.0, 0.0)
    return cost


def _viterbi(unary: NDArray, step_cost: NDArray) -> NDArray[np.int64]:
    """Minimum-cost path through (T, A) unary costs with (A, A) transition costs (from, to)."""
    n, A = unary.shape
    acc = unary[0].copy()
    back = np.zeros((n, A), dtype=np.int64)
    for i in range(1, n):  # sequential by nature; each step is vectorised over the A x A grid
        total = acc[:, None] + step_cost
        back[i] = np.argmin(total, axis=0)
        acc = total[back[i], np.arange(A)] + unary[i]
    path = np.zeros(n, dtype=np.int64)
    path[-1] = int(np.argmin(acc))
    for i in range(n - 1, 0, -1):
        path[i - 1] = back[i, path[i]]
    return path


def follow_views(spec: SceneSpec, performer_xyz: NDArray, fps: float, rng: np.random.Generator,
                 cfg: FollowConfig = FollowConfig()) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Two operators filming the performer: ``(T_scene_cam_v1, T_scene_cam_v2)``, each (T, 4, 4).

    The pair stands ``sep`` (75-105 deg) apart in azimuth about the performer at 2-3.2 m, slowly
    circling. Their common azimuth is chosen per frame by a shortest-path search over azimuth bins
    that keeps both inside the room (``margin_m`` from the walls) and off the furniture, moving
    smoothly; the paths are then smoothed. Each aims at the performer's pelvis (lagged by
    ``lag_s``) from 1.35-1.55 m height, with hand shake.

    Args:
        performer_xyz: (T, 3) pelvis positions in the scene frame, metres.
    """
    P = np.asarray(performer_xyz, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or len(P) < 2:
        raise ValueError(f"performer_xyz must be (T >= 2, 3), got shape {P.shape}")
    n = len(P)
    t = np.arange(n) / fps
    centre = gaussian_filter1d(P[:, :2], cfg.smooth_s * fps, axis=0, mode="nearest")

    d0, d1 = cfg.dist_m
    dist = (d0 + d1) / 2 + (d1 - d0) / 2 * np.clip(_smooth_noise(n, 2.0 * fps, rng, 2), -1, 1)  # (T, 2)
    s0, s1 = np.deg2rad(cfg.sep_deg)
    half_sep = ((s0 + s1) / 2 + (s1 - s0) / 2 * np.clip(_smooth_noise(n, 2.0 * fps, rng, 1)[:, 0], -1, 1)) / 2

    # Path search over the pair's mid azimuth, on a coarse time grid (every ``step_s``) so that the
    # per-step bin limit bounds the orbiting speed; then interpolated to every frame.
    A = cfg.bins
    k = max(int(round(cfg.step_s * fps)), 1)
    coarse = np.arange(0, n, k)
    psi = np.arange(A) * 2 * np.pi / A  # candidate mid azimuths
    hs = half_sep[coarse, None, None]
    # Each operator may step in or out from the preferred distance to keep off furniture and walls.
    scale = np.array([1.0, 0.85, 1.15, 0.72, 1.3])
    radii = np.clip(dist[coarse][:, :, None] * scale, cfg.dist_limits_m[0], cfg.dist_limits_m[1])  # (Tc, 2, R)
    costs, chosen = [], []
    for op, sign in enumerate((1.0, -1.0)):
        ang = psi[None, :, None] + sign * hs  # (Tc, A, 1)
        r = radii[:, None, op, :]  # (Tc, 1, R)
        pts = centre[coarse, None, None, :] + r[..., None] * np.stack([np.cos(ang), np.sin(ang)], -1)
        c = _operator_cost(spec, pts, cfg) + 2.0 * np.abs(r - dist[coarse, None, op, None])  # (Tc, A, R)
        j = np.argmin(c, axis=-1)
        costs.append(np.take_along_axis(c, j[..., None], -1)[..., 0])
        chosen.append(np.take_along_axis(np.broadcast_to(r, c.shape), j[..., None], -1)[..., 0])  # (Tc, A)
    unary = costs[0] + costs[1]
    # A mild pull towards a slow orbit, so the pair does not stand still when it could move.
    orbit = np.deg2rad(rng.uniform(*cfg.orbit_deg_s)) * (1 if rng.random() < 0.5 else -1)
    wanted = rng.uniform(0, 2 * np.pi) + orbit * t[coarse]
    gap = np.angle(np.exp(1j * (psi[None, :] - wanted[:, None])))
    unary = unary + 0.05 * gap**2
    step = np.angle(np.exp(1j * (psi[None, :] - psi[:, None]))) / (2 * np.pi / A)  # bins moved
    max_bins = np.deg2rad(cfg.max_orbit_deg_s) * cfg.step_s / (2 * np.pi / A)
    step_cost = np.where(np.abs(step) <= max_bins + 1e-9, 0.2 * step**2, np.inf)
    path = _viterbi(unary, step_cost)
    best = np.unwrap(psi[path])
    frames = np.arange(n)
    mid_raw = np.interp(frames, coarse, best)
    dist = np.column_stack([np.interp(frames, coarse, ch[np.arange(len(coarse)), path]) for ch in chosen])
    dist = gaussian_filter1d(dist, cfg.smooth_s * fps, axis=0, mode="nearest")

    mid = gaussian_filter1d(mid_raw, cfg.smooth_s * fps, mode="nearest")
    lo = np.asarray(spec.floor_min_xy, float) + cfg.margin_m
    hi = np.asarray(spec.floor_max_xy, float) - cfg.margin_m
    aim = _lagged(P, cfg.lag_s * fps)
    h0, h1 = cfg.height_m
    poses = []
    for k, sign in enumerate((1.0, -1.0)):
        ang = mid + sign * half_sep
        xy = centre + dist[:, k:k + 1] * np.column_stack([np.cos(ang), np.sin(ang)])
        xy = np.clip(xy, lo, hi)
        height = (h0 + h1) / 2 + (h1 - h0) / 2 * np.clip(_smooth_noise(n, 1.5 * fps, rng, 1)[:, 0], -1, 1)
        centres = np.column_stack([xy, height])
        T = make_T(look_at_R(centres, aim), centres)
        poses.append(_add_shake(T, fps, rng, cfg.shake))
    return poses[0], poses[1]


def _lagged(x: NDArray, tau_frames: float) -> NDArray:
    """First-order low-pass (exponential lag) of (T, D) signals along time, starting at x[0]."""
    from scipy.signal import lfilter

    if tau_frames <= 0:
        return np.array(x, dtype=np.float64)
    a = 1.0 - np.exp(-1.0 / tau_frames)
    y, _ = lfilter([a], [1.0, a - 1.0], x, axis=0, zi=(1.0 - a) * x[:1])
    return y


def turn_away(T_scene_cam: NDArray, from_frame: int, fps: float, angle_deg: float = 120.0,
              ramp_s: float = 0.7) -> NDArray[np.float64]:
    """Cameras (T, 4, 4) that turn ``angle_deg`` about the world's Z axis from ``from_frame`` on.

    The turn ramps in smoothly over ``ramp_s`` (an operator looking elsewhere, the "built to fail"
    session with the performer out of one view); positions are untouched.
    """
    T = np.array(T_scene_cam, dtype=np.float64, copy=True)
    s = np.clip((np.arange(len(T)) - from_frame) / max(ramp_s * fps, 1.0), 0.0, 1.0)
    yaw = np.deg2rad(angle_deg) * (3 * s**2 - 2 * s**3)
    T[:, :3, :3] = rot_z(yaw) @ T[:, :3, :3]
    return T


# ------------------------------------------------------------------------------------------------
# VIO worlds, drift, IMU


def random_T_scene_vio(rng: np.random.Generator, max_offset_m: float = 3.0) -> NDArray[np.float64]:
    """A gravity-aligned VIO world: (4, 4) ``T_scene_vio`` = a yaw about +Z (uniform over the
    full circle) and an offset with x, y uniform in [-max, max] and z uniform in [-max/3, max/3]."""
    yaw = rng.uniform(-np.pi, np.pi)
    off = rng.uniform(-1.0, 1.0, 3) * max_offset_m * np.array([1.0, 1.0, 1.0 / 3.0])
    return make_T(rot_z(yaw), off)


@dataclass(frozen=True)
class DriftConfig:
    """Slow VIO drift: a random walk of the VIO world against the true one."""

    trans_sigma_m_per_10s: float = 0.0075
    """Standard deviation of the horizontal translation drift after 10 s, metres (grows as sqrt(t))."""
    vertical_scale: float = 0.5
    """Vertical drift relative to horizontal (gravity keeps VIO height better)."""
    yaw_sigma_deg_per_10s: float = 0.075
    """Standard deviation of the yaw drift after 10 s, degrees (about the first camera position)."""
    smooth_s: float = 0.5
    """Gaussian smoothing of the random walks, seconds (drift has no jumps)."""


def add_drift(T_vio_cam: NDArray, fps: float, rng: np.random.Generator, cfg: DriftConfig = DriftConfig()) -> NDArray[np.float64]:
    """Apply slow drift: ``D(t) @ T_vio_cam(t)`` with ``D(0) = I``; (T, 4, 4) in and out.

    ``D(t)`` is a yaw ``psi(t)`` about the first camera centre plus a translation ``d(t)``; both are
    zero-mean random walks with the configured spread after 10 s.
    """
    T = np.asarray(T_vio_cam, dtype=np.float64)
    n = len(T)
    per_frame = np.sqrt(1.0 / (10.0 * fps))  # random-walk step for unit spread after 10 s
    steps = rng.standard_normal((n, 4)) * per_frame
    steps[0] = 0.0
    walk = np.cumsum(steps, axis=0)
    if cfg.smooth_s > 0 and n > 1:
        walk = gaussian_filter1d(walk, cfg.smooth_s * fps, axis=0, mode="nearest")
        walk -= walk[0]
    d = walk[:, :3] * cfg.trans_sigma_m_per_10s * np.array([1.0, 1.0, cfg.vertical_scale])
    psi = walk[:, 3] * np.deg2rad(cfg.yaw_sigma_deg_per_10s)
    Rz = rot_z(psi)
    p0 = T[0, :3, 3]
    D = make_T(Rz, p0 - Rz @ p0 + d)
    return D @ T


def synth_imu(T_world_cam: NDArray, fps: float, rng: np.random.Generator, rate_hz: float = 100.0,
              accel_sigma: float = 0.02, gyro_sigma: float = 0.002, accel_bias_sigma: float = 0.02,
              gyro_bias_sigma: float = 0.001) -> tuple[NDArray, NDArray, NDArray]:
    """IMU readings implied by a camera trajectory (cubic splines through the poses).

    Args:
        T_world_cam: (T, 4, 4) poses at ``fps`` (frame i at time i / fps), Z-up world.
        rate_hz: IMU sample rate.
        accel_sigma / gyro_sigma: white noise per sample (m/s^2, rad/s).
        accel_bias_sigma / gyro_bias_sigma: spread of a constant bias per recording.

    Returns:
        ``t`` (N,) seconds from the first frame, ``accel_mps2`` (N, 3) specific force (acceleration
        minus gravity; +9.81 along world up at rest) and ``gyro_radps`` (N, 3) angular rate, both in
        the camera frame (OpenCV axes).
    """
    from scipy.interpolate import CubicSpline
    from scipy.spatial.transform import Rotation, RotationSpline

    T = np.asarray(T_world_cam, dtype=np.float64)
    if len(T) < 2:
        raise ValueError("synth_imu needs at least 2 poses")
    tf = np.arange(len(T)) / fps
    t = np.arange(0.0, tf[-1] + 1e-9, 1.0 / rate_hz)
    acc_w = CubicSpline(tf, T[:, :3, 3], axis=0)(t, 2)
    rs = RotationSpline(tf, Rotation.from_matrix(T[:, :3, :3]))
    R = rs(t).as_matrix()  # camera-to-world at the IMU times
    f_w = acc_w + np.array([0.0, 0.0, GRAVITY_MPS2])
    accel = np.einsum("nji,nj->ni", R, f_w)  # R^T f: into the camera frame
    gyro = rs(t, 1)  # body-frame angular rate
    accel += rng.normal(0.0, accel_bias_sigma, 3) + rng.normal(0.0, accel_sigma, accel.shape)
    gyro += rng.normal(0.0, gyro_bias_sigma, 3) + rng.normal(0.0, gyro_sigma, gyro.shape)
    return t, accel, gyro


def walk_area_floor_seen(spec, T_world_cam: NDArray, hfov_deg: float, max_depth_m: float = 5.0,
                         stride: int = 3, cell_m: float = 0.05) -> float:
    """Share of the walk area's floor (a ``cell_m`` grid at z = 0) inside the depth frustum (4:3,
    ``hfov_deg`` wide, out to ``max_depth_m``) of some frame of a scan, every ``stride``-th frame.

    The studio's own coverage measure of a scan path (tests and benchmarks), no rendering.

    Args:
        spec: the scene's :class:`~embodmocap.synth.spec.SceneSpec` (its walk area).
        T_world_cam: (N, 4, 4) camera-to-world poses (OpenCV cameras, Z-up world).
    """
    lo, hi = np.asarray(spec.walk_area_min_xy), np.asarray(spec.walk_area_max_xy)
    g = np.stack(np.meshgrid(np.arange(lo[0], hi[0], cell_m), np.arange(lo[1], hi[1], cell_m), indexing="ij"), -1)
    P = np.column_stack([g.reshape(-1, 2), np.zeros(g.shape[0] * g.shape[1])])
    tx = np.tan(np.radians(hfov_deg / 2))
    seen = np.zeros(len(P), bool)
    for Tk in np.asarray(T_world_cam)[::stride]:  # a loop over frames: (cells x frames) would not fit
        pc = (P - Tk[:3, 3]) @ Tk[:3, :3]
        z = pc[:, 2]
        seen |= (z > 0.05) & (z < max_depth_m) & (np.abs(pc[:, 0]) < tx * z) & (np.abs(pc[:, 1]) < 0.75 * tx * z)
    return float(seen.mean())
