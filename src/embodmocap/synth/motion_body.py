"""The scripted performer's body side (:mod:`embodmocap.synth.motion`): angles calibrated on the
body and the furniture, per-frame joint angles from the motion channels, the legs' IK and the
global orientation. Private to the studio: :mod:`embodmocap.synth.motion` imports it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from embodmocap.geometry.transforms import R_ZUP_YUP, rot_z
from embodmocap.synth.motion_base import MotionScriptConfig
from embodmocap.synth.spec import SceneSpec


# SMPL joint ids used below (body_pose holds joints 1..23).
_L_HIP, _R_HIP, _SPINE1, _L_KNEE, _R_KNEE, _SPINE2, _L_ANKLE, _R_ANKLE, _SPINE3 = 1, 2, 3, 4, 5, 6, 7, 8, 9
_NECK, _HEAD, _L_SHOULDER, _R_SHOULDER, _L_ELBOW, _R_ELBOW = 12, 15, 16, 17, 18, 19


# --------------------------------------------------------------------------------------------
# calibration: angles that depend on the body and the furniture
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Calib:
    """Body-dependent angles (radians) and offsets (metres, along the heading)."""

    seats: dict             # seat name -> _Seat
    lean_a: float
    lean_g: float
    lean_reach: float       # leaning: wrists ahead of the ankles
    thigh: float            # hip to knee
    shin: float             # knee to ankle
    ankle_h: float          # ankle above the sole
    hip_h: float            # hip joint above the sole, standing
    toe_ahead: float        # toes ahead of the ankle
    head_top: float = 0.75  # top of the head above the pelvis joint, standing (set by the script)


@dataclass(frozen=True)
class _Seat:
    """Seated posture fitted to one seat height (angles in radians, offsets in metres)."""

    hip: float
    knee: float
    feet_ahead: float       # ankles ahead of the pelvis
    back: float             # buttocks behind the pelvis


def _pose_batch(body, betas, hips, knees, tilts, arm_flex, elbow, lower=np.deg2rad(75.0)):
    """Pose the body on a batch of symmetric candidate postures; returns (joints, vertices) numpy
    in the SMPL frame rotated to Z up, facing +X (heading 0)."""
    n = len(hips)
    e = np.zeros((n, 23, 3))
    for hip, knee, ankle in ((_L_HIP, _L_KNEE, _L_ANKLE), (_R_HIP, _R_KNEE, _R_ANKLE)):
        e[:, hip - 1, 0] = -(hips + tilts)
        e[:, knee - 1, 0] = knees
        e[:, ankle - 1, 0] = hips - knees
    e[:, _L_SHOULDER - 1, 0] = e[:, _R_SHOULDER - 1, 0] = -arm_flex
    e[:, _L_SHOULDER - 1, 2], e[:, _R_SHOULDER - 1, 2] = -lower, lower
    e[:, _L_ELBOW - 1, 1], e[:, _R_ELBOW - 1, 1] = -elbow, elbow
    pose = Rotation.from_euler("XYZ", e.reshape(-1, 3)).as_rotvec().reshape(n, 69)
    go = _global_orient(np.zeros(n), tilts, {})
    out = body.forward(betas, go, pose, np.zeros((n, 3)))
    return out.joints.detach().cpu().numpy().astype(np.float64), out.vertices.detach().cpu().numpy().astype(np.float64)


def _calibrate(body, betas: NDArray, spec: SceneSpec) -> _Calib:
    """Fit the seated and leaning postures to this body and this furniture; measure the legs."""
    deg = np.deg2rad

    # Seated: a grid of hip and knee angles; per seat keep the one whose feet reach the floor
    # when the buttocks touch the seat, preferring horizontal thighs (hip 90 deg). Feet a little
    # short of the floor are better than too long (which would lift the buttocks off the seat).
    H, K = np.meshgrid(deg(np.arange(70, 101, 5)), deg(np.arange(60, 131, 2)), indexing="ij")
    H, K = H.ravel(), K.ravel()
    j, v = _pose_batch(body, betas, H, K, np.zeros_like(H), np.full_like(H, deg(30)), np.full_like(H, deg(50)))
    pel = j[:, 0]
    knee_fwd = 0.5 * (j[:, _L_KNEE, 0] + j[:, _R_KNEE, 0]) - pel[:, 0]
    rel = v - pel[:, None]
    seat_set = (rel[..., 0] < knee_fwd[:, None] - 0.12) & (rel[..., 2] > -0.35)
    buttock = -np.where(seat_set, rel[..., 2], np.inf).min(axis=1)          # pelvis above the seat
    feet = -rel[..., 2].min(axis=1)                                          # pelvis above the soles
    seats = {}
    for name, f in spec.furniture.items():
        if name not in ("chair", "sofa", "bed"):
            continue
        excess = feet - (f.top_z + buttock)  # > 0: the feet would push the buttocks up
        score = np.abs(excess) + 5.0 * np.maximum(excess, 0.0) + 0.3 * np.abs(H - deg(90)) + 0.05 * np.abs(K - deg(90))
        i = int(np.argmin(score))
        seats[name] = _Seat(
            hip=float(H[i]), knee=float(K[i]),
            feet_ahead=float(0.5 * (j[i, _L_ANKLE, 0] + j[i, _R_ANKLE, 0]) - pel[i, 0]),
            back=float(-(rel[i, :, 0][seat_set[i]]).min()),
        )

    # Leaning on the table: torso forward by a (hips flex), arms forward of vertical by g.
    A, G, reach = _solve_lean(body, betas, spec.furniture["table"].top_z if "table" in spec.furniture else 0.75)

    # Leg segment lengths for the stepping IK (rest pose).
    j, v = _pose_batch(body, betas, np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1))
    j, v = j[0], v[0]
    thigh = float(np.linalg.norm(j[_L_HIP] - j[_L_KNEE]))
    shin = float(np.linalg.norm(j[_L_KNEE] - j[_L_ANKLE]))
    sole = v[:, 2].min()
    toe_ahead = float(v[:, 0].max() - j[_L_ANKLE, 0])
    return _Calib(
        seats=seats, lean_a=A, lean_g=G, lean_reach=reach,
        thigh=thigh, shin=shin, ankle_h=float(j[_L_ANKLE, 2] - sole), hip_h=float(j[_L_HIP, 2] - sole),
        toe_ahead=toe_ahead,
    )


#: Leaning: the hands' lowest point this far above the table top (they rest on it), metres.
LEAN_HAND_GAP_M = 0.002


def hand_vertex_ids(body) -> NDArray[np.int64]:
    """Vertex ids of both hands: vertices skinned mostly to a wrist or a hand joint (20-23)."""
    return np.nonzero(np.isin(np.asarray(body.lbs_weights).argmax(axis=1), (20, 21, 22, 23)))[0]


def _lean_pose(body, betas, A: NDArray, G: NDArray) -> tuple[NDArray, NDArray]:
    """The leaning posture (tilt A, arms A + G forward, elbows 10 deg) on a batch (n,) of angles:
    height of the hands' lowest vertex above the soles (n,), wrists ahead of the ankles (n,)."""
    zero = np.zeros_like(A)
    j, v = _pose_batch(body, betas, zero, zero, A, A + G, np.full_like(A, np.deg2rad(10.0)))
    hands = v[:, hand_vertex_ids(body)]
    floor = v[..., 2].min(axis=1)
    reach = 0.5 * (j[:, 20, 0] + j[:, 21, 0]) - 0.5 * (j[:, _L_ANKLE, 0] + j[:, _R_ANKLE, 0])
    return hands[..., 2].min(axis=1) - floor, reach


def _solve_lean(body, betas, table_top: float, iters: int = 12) -> tuple[float, float, float]:
    """Leaning posture for this body and this table: tilt a, arm angle g (radians) and the
    wrists' reach ahead of the ankles (metres).

    For each tilt a on a 5-degree grid the arm angle g is solved continuously (vectorised secant
    on the hands' lowest vertex, not the wrist: fingers hang below it) so that the hands rest on
    the top, :data:`LEAN_HAND_GAP_M` above it; then the tilt whose solution reaches far enough
    ahead of the feet for the toes to clear the table (35 cm), with the smallest tilt, wins."""
    deg = np.deg2rad
    A = deg(np.arange(10.0, 61.0, 5.0))
    target = table_top + LEAN_HAND_GAP_M
    g0, g1 = np.full_like(A, deg(0.0)), np.full_like(A, deg(40.0))
    h0, h1 = _lean_pose(body, betas, A, g0)[0] - target, _lean_pose(body, betas, A, g1)[0] - target
    for _ in range(iters):
        slope = np.where(np.abs(h1 - h0) > 1e-9, (h1 - h0) / np.where(g1 != g0, g1 - g0, 1.0), 1.0)
        g2 = np.clip(g1 - h1 / np.where(np.abs(slope) > 1e-6, slope, 1e-6), deg(-30.0), deg(90.0))
        g0, h0 = g1, h1
        g1 = g2
        h1 = _lean_pose(body, betas, A, g1)[0] - target
        if np.all(np.abs(h1) < 1e-4):
            break
    reach = _lean_pose(body, betas, A, g1)[1]
    ok = np.abs(h1) < 1e-3  # reachable: the hands can touch the top at this tilt
    score = np.where(ok, 0.0, 10.0 + np.abs(h1)) + 0.5 * np.maximum(0.0, 0.35 - reach) + 0.05 * A
    i = int(np.argmin(score))
    return float(A[i]), float(g1[i]), float(reach[i])


# --------------------------------------------------------------------------------------------
# joint angles
# --------------------------------------------------------------------------------------------


def _joint_angles(ch: dict, c: _Calib, cfg: MotionScriptConfig) -> tuple[NDArray, NDArray]:
    """Channels -> pelvis tilt (T,) and per-joint XYZ Euler angles (T, 23, 3), radians.

    Sign conventions (SMPL frame, rotations about the joint's x axis): hip flexion is a negative
    x angle, knee flexion positive, ankle plantar flexion positive; a positive pelvis tilt leans
    the body forward, so the hips flex by the tilt as well to keep the legs where they were.
    """
    deg = np.deg2rad
    a, ph = ch["gait_amp"], ch["gait_phase"]
    sit, lean = ch["sit"], ch["lean"]
    # The arms have their own lean channel: they reach over the table's edge before the torso
    # tilts (and leave after it has straightened), so the hands never cut through the top.
    lean_arm = ch.get("lean_arm", lean)
    T = len(a)
    t = np.arange(T)

    # Pelvis tilt: walking lean, leaning on the table, and a forward lean while sitting down or
    # standing up (sin(pi s) is 0 when standing or seated).
    tilt = deg(3.0) * a + lean * c.lean_a + deg(25.0) * np.sin(np.pi * sit)

    e = np.zeros((T, 23, 3))
    ik = ch["ik"]
    sides = (
        (_L_HIP, _L_KNEE, _L_ANKLE, ph + np.pi, ch["al_x"], ch["al_z"]),
        (_R_HIP, _R_KNEE, _R_ANKLE, ph, ch["ar_x"], ch["ar_z"]),
    )
    for hip, knee, ankle, phi, ax, az in sides:  # two legs
        g_hip = a * (deg(5.0) + deg(cfg.hip_swing_deg) * np.sin(phi))
        g_knee = a * (deg(5.0) + deg(cfg.knee_swing_deg) * ((1.0 + np.cos(phi)) / 2.0) ** 3)
        ik_hip, ik_knee = _leg_ik(ax - ch["hip_x"], ch["hip_z"] - az, c.thigh, c.shin)
        flex = g_hip + sit * ch["sit_hip"] + ik * ik_hip
        knee_f = g_knee + sit * ch["sit_knee"] + ik * ik_knee
        # Feet stay level for the postures; the gait adds a small ankle roll-off.
        ankle_x = sit * (ch["sit_hip"] - ch["sit_knee"]) + ik * (ik_hip - ik_knee) + a * deg(8.0) * np.sin(phi - 0.6)
        e[:, hip - 1, 0] = -(flex + tilt)
        e[:, knee - 1, 0] = knee_f
        e[:, ankle - 1, 0] = ankle_x

    # Arms: lowered from the T-pose, swinging against the legs; forward onto the thighs when
    # seated, forward onto the table when leaning.
    swing = a * deg(cfg.arm_swing_deg)
    arm = {
        _L_SHOULDER: -swing * np.sin(ph + np.pi), _R_SHOULDER: -swing * np.sin(ph),
    }
    for sh, el, side in ((_L_SHOULDER, _L_ELBOW, 1.0), (_R_SHOULDER, _R_ELBOW, -1.0)):
        flex = arm[sh] + sit * deg(30.0) + lean_arm * (c.lean_a + c.lean_g) + deg(20.0) * np.sin(np.pi * sit)
        e[:, sh - 1, 0] = -flex
        e[:, sh - 1, 2] = -side * deg(75.0)
        elbow = deg(15.0) + a * deg(10.0) + sit * deg(35.0) - lean_arm * deg(5.0) + ch.get("lean_lift", 0.0 * lean) * deg(45.0)
        e[:, el - 1, 1] = -side * elbow

    # Breathing and a little sway, always on, so that no frame is perfectly still; the chest's
    # breathing fades out while leaning on the table (1 degree there moves the braced hands
    # about 7 mm up and down through the top).
    e[:, _SPINE2 - 1, 0] += deg(1.0) * np.sin(2 * np.pi * t / 110.0) * (1.0 - lean)
    e[:, _NECK - 1, 1] += deg(4.0) * np.sin(2 * np.pi * t / 170.0 + 1.0)
    e[:, _HEAD - 1, 0] += deg(3.0) * np.sin(2 * np.pi * t / 130.0 + 2.0) - deg(5.0) * lean
    # Torso counter-rotation against the pelvis while walking.
    e[:, _SPINE3 - 1, 1] += -a * deg(4.0) * np.sin(ph)
    e[:, _L_ANKLE - 1, 0] += ch.get("point_toes", 0.0)
    e[:, _R_ANKLE - 1, 0] += ch.get("point_toes", 0.0)
    e[:, _NECK - 1, 1] += ch.get("head_turn", 0.0)
    # Lying down pitches the whole body, legs included: added after the hips compensated the tilt.
    return tilt + ch.get("body_tilt", 0.0), e


def _leg_ik(fwd: NDArray, down: NDArray, thigh: float, shin: float) -> tuple[NDArray, NDArray]:
    """Two-link leg IK in the sagittal plane: hip and knee flexion (radians, >= 0) that put the
    ankle ``fwd`` ahead of and ``down`` below the hip joint (an out-of-reach target gives the
    straight leg pointing at it). The knee bends forward.

    Near full extension the knee angle changes infinitely fast with the reach (it goes like
    sqrt(L - r)), so the reach is softly saturated at 99 % of the leg length: the knee never
    locks straight and its speed stays bounded."""
    L = thigh + shin
    r0, rmax = 0.9 * L, 0.99 * L
    r = np.hypot(fwd, down)
    r = np.where(r > r0, r0 + (rmax - r0) * np.tanh((r - r0) / (rmax - r0)), r)
    r = np.maximum(r, abs(thigh - shin) + 1e-3)
    knee = np.pi - np.arccos(np.clip((thigh**2 + shin**2 - r**2) / (2 * thigh * shin), -1.0, 1.0))
    hip = np.arctan2(fwd, down) + np.arccos(np.clip((thigh**2 + r**2 - shin**2) / (2 * thigh * r), -1.0, 1.0))
    return hip, knee


def _head_top(body, betas: NDArray) -> float:
    """Top of the head above the pelvis joint in the rest pose, metres."""
    j, v = _pose_batch(body, betas, np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1))
    return float(v[0, :, 2].max() - j[0, 0, 2])


def _global_orient(yaw: NDArray, tilt: NDArray, ch: dict) -> NDArray:
    """(T, 3) axis-angle: heading ``yaw`` about +Z, forward tilt, small gait twist."""
    yaw = np.asarray(yaw, dtype=np.float64)
    twist = ch["gait_amp"] * np.deg2rad(4.0) * np.sin(ch["gait_phase"]) if ch else np.zeros_like(yaw)
    local = Rotation.from_euler("XY", np.stack([tilt, twist], -1)).as_matrix()
    R = rot_z(yaw + np.pi / 2) @ R_ZUP_YUP @ local
    return Rotation.from_matrix(R).as_rotvec()
