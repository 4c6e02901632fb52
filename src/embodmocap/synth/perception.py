"""What real detectors would output, made from the synthetic ground truth.

The studio renders the performer, so it knows the true 2D joints, the true person mask and the true
SMPL parameters. Real detectors are worse in characteristic ways, and the pipeline must cope with
those ways, so each function here degrades the truth the way a detector does:

- :func:`joint_visibility`: which joints a camera can see (inside the image, not hidden behind a
  surface);
- :func:`noisy_keypoints`: a ViTPose/OpenPose-like 2D detector (pixel jitter that scales with the
  person's size, low confidence under occlusion, outliers, left/right swaps, missed frames);
- :func:`noisy_mask`: a segmentation model's mask (boundary a few pixels off, jagged edge);
- :func:`body_prior`: a VIMO/HMR-like camera-space regressor (correlated joint-angle errors, shape
  noise, depth wrong by ~10 % along the camera ray).

All functions are vectorised over frames and draw only from the ``rng`` they are given.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter, gaussian_filter1d
from scipy.spatial.transform import Rotation

from embodmocap.geometry.transforms import invert_T
from embodmocap.io.body_prior import BodyPriorSeq
from embodmocap.types import SmplParams

#: COCO-17 index pairs (left, right) swapped together when a detector confuses the sides of a
#: limb: arms (elbow, wrist) and legs (knee, ankle).
SWAP_GROUPS: tuple[tuple[tuple[int, int], ...], ...] = (
    ((7, 8), (9, 10)),
    ((13, 14), (15, 16)),
)


# --------------------------------------------------------------------------------------------
# visibility
# --------------------------------------------------------------------------------------------


def joint_visibility(
    points_world: NDArray,
    K: NDArray,
    T_world_cam: NDArray,
    depth_m,
    margin_m: float = 0.1,
    border_frac: float = 0.02,
) -> NDArray[np.float64]:
    """How visible each joint is to a camera: (T, J) in [0, 1].

    A joint is visible (1) when it projects inside the image and its depth is not more than
    ``margin_m`` behind the rendered surface at its pixel. The body's own skin lies in front of
    its joints (a hip joint is ~8-12 cm inside the body), so the margin must be about a limb's
    half-thickness: 0.1 m lets a joint be seen through its own flesh but not through the torso or
    a piece of furniture. Visibility falls linearly to 0 between ``margin_m`` and ``2 * margin_m``
    behind the surface, and over a band of ``border_frac * max(W, H)`` pixels inside the image
    border (detectors lose points near the border gradually). Pixels with depth 0 (nothing hit,
    e.g. sky) hide nothing.

    Args:
        points_world: (T, J, 3) joint positions in the world, metres.
        K: (3, 3) intrinsics of the image the depth maps were rendered at.
        T_world_cam: (T, 4, 4) camera-to-world poses (OpenCV camera axes).
        depth_m: (T, H, W) array, or a list of T (H, W) arrays, rendered depth in metres
            (0 = no surface), at the resolution ``K`` describes.
        margin_m: how far behind the surface a joint may be and still count as visible, metres.
        border_frac: width of the soft image border as a fraction of the image's larger side.
    """
    P = np.asarray(points_world, dtype=np.float64)
    depth = np.asarray(depth_m, dtype=np.float64)
    T, J = P.shape[:2]
    if depth.ndim != 3 or len(depth) != T:
        raise ValueError(f"depth_m must hold {T} maps (T, H, W), got {depth.shape}")
    H, W = depth.shape[1:]
    T_cam_world = invert_T(np.asarray(T_world_cam, dtype=np.float64))
    pc = np.einsum("tij,tnj->tni", T_cam_world[:, :3, :3], P) + T_cam_world[:, None, :3, 3]
    z = pc[..., 2]
    in_front = z > 1e-6
    zs = np.where(in_front, z, 1.0)
    uv = np.einsum("ij,tnj->tni", np.asarray(K, dtype=np.float64)[:2], np.concatenate([pc[..., :2] / zs[..., None], np.ones((T, J, 1))], -1))

    # Soft border: 1 at least `band` px inside the image, 0 at its edge and outside.
    band = max(border_frac * max(W, H), 1e-6)
    dist_in = np.minimum.reduce([uv[..., 0] + 0.5, W - 0.5 - uv[..., 0], uv[..., 1] + 0.5, H - 0.5 - uv[..., 1]])
    v_border = np.clip(dist_in / band, 0.0, 1.0)

    # Occlusion: compare with the rendered surface at the joint's pixel.
    ui = np.clip(np.rint(uv[..., 0]), 0, W - 1).astype(np.int64)
    vi = np.clip(np.rint(uv[..., 1]), 0, H - 1).astype(np.int64)
    surf = depth[np.arange(T)[:, None], vi, ui]
    behind = np.where(surf > 0, z - surf, -np.inf)
    v_occ = np.clip((2.0 * margin_m - behind) / margin_m, 0.0, 1.0)
    return np.where(in_front, v_border * v_occ, 0.0)


# --------------------------------------------------------------------------------------------
# 2D keypoints
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class KeypointNoiseConfig:
    """How a 2D keypoint detector's output differs from the truth."""

    rel_std: float = 0.011
    """Per-axis Gaussian jitter of a visible point, as a fraction of the person's height in the
    image (the extent of the true keypoints). Top-down detectors work on a person crop, so their
    pixel error scales with the person's size: 0.011 is ~3 px for a person 270 px tall (about 3 m
    away in a 640x480 image), and scales with the image size like the person does."""
    occluded_std_scale: float = 3.0
    """Jitter multiplier for a fully occluded point (interpolated by visibility): a detector
    guesses hidden joints from context, so they are noisier."""
    conf_visible: tuple[float, float] = (0.7, 0.95)
    """Range of the (uniform) confidence of a fully visible point."""
    conf_occluded: tuple[float, float] = (0.05, 0.4)
    """Range of the (uniform) confidence of a fully occluded point; partly visible points blend."""
    outlier_rate: float = 0.02
    """Probability that a point is an outlier: moved far away, yet with moderate confidence."""
    outlier_jump: tuple[float, float] = (0.1, 0.3)
    """Range of an outlier's displacement, as a fraction of the person's height."""
    outlier_conf: tuple[float, float] = (0.4, 0.7)
    """Range of an outlier's confidence."""
    swap_rate: float = 0.01
    """Per frame and limb group (arms: elbows+wrists; legs: knees+ankles), the probability that a
    left/right swap starts (the detector confuses the sides)."""
    swap_frames: tuple[int, int] = (2, 6)
    """Range (inclusive) of how many frames a swap lasts."""
    min_visible_frac: float = 0.3
    """A frame whose mean joint visibility is below this has no person at all (all zeros): the
    detector misses a person mostly out of view or hidden."""
    miss_rate: float = 0.005
    """Probability that the detector misses the person in a frame anyway (a miss starts; see
    ``miss_frames``)."""
    miss_frames: tuple[int, int] = (1, 1)
    """Range (inclusive) of how many frames a whole-body miss lasts (motion blur, a detector that
    loses the person for a moment)."""
    small_person_px: float = 0.0
    """Distance: below this person height in the image (pixels) the jitter grows as
    ``small_person_px / height`` (a top-down detector working on a low-resolution crop is less
    precise relative to the person's size); 0 = off."""
    missed_joint_rate: float = 0.0
    """Probability that a fully visible joint is not output at all (confidence 0)."""
    missed_occluded_rate: float = 0.0
    """Probability that a fully occluded joint is not output (blended by visibility)."""
    occluded_wrong_rate: float = 0.0
    """Per frame and joint, the probability that a run starts in which the joint, while occluded
    (by the scene's furniture or the body), is put at a wrong place with a middling confidence
    instead of a low one: a detector's confident guess of a hidden joint."""
    occluded_wrong_frames: tuple[int, int] = (5, 20)
    """Range (inclusive) of how many frames such a wrong guess lasts."""
    occluded_wrong_jump: tuple[float, float] = (0.08, 0.2)
    """Range of a wrong guess's displacement, as a fraction of the person's height."""
    occluded_wrong_conf: tuple[float, float] = (0.3, 0.6)
    """Range of a wrong guess's confidence."""


#: The adversities of real detectors, all on (``embodmocap synth --perception hard``). Figures
#: follow published behaviour of top-down detectors (HRNet / ViTPose / OpenPose on COCO and on
#: in-the-wild video): about 1-2 % of the person's height of jitter on visible joints, several
#: times that on occluded ones, a few % gross outliers, left/right limb confusions lasting up to a
#: second, joints dropped under occlusion, and whole-body misses of a few frames.
HARD_KEYPOINT_NOISE = KeypointNoiseConfig(
    rel_std=0.013, occluded_std_scale=4.0, conf_occluded=(0.05, 0.35), outlier_rate=0.04,
    outlier_jump=(0.1, 0.4), swap_rate=0.008, swap_frames=(5, 30), miss_rate=0.006, miss_frames=(2, 12),
    small_person_px=300.0, missed_joint_rate=0.02, missed_occluded_rate=0.4, occluded_wrong_rate=0.01,
)


def noisy_keypoints(
    gt_px: NDArray, visibility: NDArray, rng: np.random.Generator, cfg: KeypointNoiseConfig = KeypointNoiseConfig()
) -> NDArray[np.float64]:
    """Degrade true COCO-17 pixels like a 2D detector: (T, 17, 3) x px, y px, confidence.

    Args:
        gt_px: (T, 17, 2) true projections, pixels.
        visibility: (T, 17) in [0, 1] from :func:`joint_visibility`.
        rng: random generator (the only source of randomness).
        cfg: noise settings.

    Returns:
        (T, 17, 3); frames where the person is missed are all zero (OpenPose writes no person).
    """
    gt = np.asarray(gt_px, dtype=np.float64)
    vis = np.clip(np.asarray(visibility, dtype=np.float64), 0.0, 1.0)
    T, J = gt.shape[:2]
    scale = person_height_px(gt)  # (T,)

    std = cfg.rel_std * scale[:, None] * (1.0 + (cfg.occluded_std_scale - 1.0) * (1.0 - vis))
    if cfg.small_person_px > 0:
        std = std * np.maximum(cfg.small_person_px / np.maximum(scale, 1.0), 1.0)[:, None]
    xy = gt + rng.normal(size=(T, J, 2)) * std[..., None]
    conf = vis * rng.uniform(*cfg.conf_visible, size=(T, J)) + (1.0 - vis) * rng.uniform(*cfg.conf_occluded, size=(T, J))

    # Outliers: a far jump in a random direction with a middling confidence.
    out = rng.random((T, J)) < cfg.outlier_rate
    ang = rng.uniform(0.0, 2.0 * np.pi, size=(T, J))
    jump = rng.uniform(*cfg.outlier_jump, size=(T, J)) * scale[:, None]
    xy = np.where(out[..., None], xy + jump[..., None] * np.stack([np.cos(ang), np.sin(ang)], -1), xy)
    conf = np.where(out, rng.uniform(*cfg.outlier_conf, size=(T, J)), conf)

    kp = np.concatenate([xy, conf[..., None]], axis=-1)
    kp = _apply_swaps(kp, swap_mask(T, rng, cfg))

    if cfg.miss_frames == (1, 1):
        missed = (vis.mean(axis=1) < cfg.min_visible_frac) | (rng.random(T) < cfg.miss_rate)
    else:
        missed = (vis.mean(axis=1) < cfg.min_visible_frac) | runs(T, 1, cfg.miss_rate, cfg.miss_frames, rng)[:, 0]
    kp[missed] = 0.0
    if cfg.occluded_wrong_rate > 0:
        # A hidden joint guessed at a wrong place, consistently over a run of frames.
        wrong = runs(T, J, cfg.occluded_wrong_rate, cfg.occluded_wrong_frames, rng) & (vis < 0.5)
        ang = rng.uniform(0.0, 2.0 * np.pi, size=J)
        jump = rng.uniform(*cfg.occluded_wrong_jump, size=J)[None] * scale[:, None]
        off = jump[..., None] * np.stack([np.cos(ang), np.sin(ang)], -1)[None]
        wrong &= ~missed[:, None]
        kp[..., :2] = np.where(wrong[..., None], kp[..., :2] + off, kp[..., :2])
        kp[..., 2] = np.where(wrong, rng.uniform(*cfg.occluded_wrong_conf, size=(T, J)), kp[..., 2])
    if cfg.missed_joint_rate > 0 or cfg.missed_occluded_rate > 0:
        p = cfg.missed_joint_rate + (cfg.missed_occluded_rate - cfg.missed_joint_rate) * (1.0 - vis)
        drop = rng.random((T, J)) < p
        kp[drop] = 0.0
    return kp


#: COCO-17 (elbow, wrist) of the left and right arm.
LEFT_ARM, RIGHT_ARM = (7, 9), (8, 10)


def edge_limb_trouble(kps: dict[str, NDArray], first: dict[str, int], frames: int, mode: str,
                      rng: np.random.Generator) -> dict[str, NDArray]:
    """The sequence's start made hard for one limb (issue 29): over the ``frames`` frames from
    ``first[v]`` (each view's sync frame: the sequence's first frames), view 2 sees the left arm
    only weakly (occluded: confidence 0.05-0.3, 6 % of the person's height of jitter) while view 1
    sees it clearly but, with ``mode = "mislabelled"``, labels the two arms the wrong way round
    (what a detector does on an arm crossing the body) or, with ``"occluded"``, misses the left arm.

    Args:
        kps: view -> (T_v, 17, 3) detector keypoints (COCO-17 order), each view's raw frames;
        first: view -> its first frame of the trouble; mode: ``mislabelled`` or ``occluded``;
        rng: the only source of randomness. Returns new arrays (inputs unchanged).
    """
    if mode not in ("mislabelled", "occluded"):
        raise ValueError(f"edge limb mode must be 'mislabelled' or 'occluded', got {mode!r}")
    out = {v: np.array(k, dtype=np.float64, copy=True) for v, k in kps.items()}
    v1, v2 = sorted(out)
    a = out[v2]
    sel = slice(first[v2], min(first[v2] + frames, len(a)))
    n = len(a[sel])
    seen = a[sel][..., 2] > 0
    scale = person_height_px(a[sel][:, :, :2])  # (n,)
    for j in LEFT_ARM:
        a[sel, j, :2] += rng.normal(size=(n, 2)) * 0.06 * scale[:, None]
        a[sel, j, 2] = np.where(seen[:, j], rng.uniform(0.05, 0.3, size=n), 0.0)
    b = out[v1]
    sel = slice(first[v1], min(first[v1] + frames, len(b)))
    if mode == "mislabelled":
        for left, right in zip(LEFT_ARM, RIGHT_ARM):
            b[sel, left], b[sel, right] = kps[v1][sel, right], kps[v1][sel, left]
    else:
        b[sel, list(LEFT_ARM)] = 0.0
    return out


def runs(T: int, n: int, rate: float, frames: tuple[int, int], rng: np.random.Generator) -> NDArray[np.bool_]:
    """(T, n) True inside random runs: per frame and column a run starts with probability
    ``rate`` and lasts a random number of frames in ``frames`` (inclusive)."""
    starts = rng.random((T, n)) < rate
    lengths = rng.integers(frames[0], frames[1] + 1, size=(T, n))
    diff = np.zeros((T + frames[1] + 1, n), dtype=np.int64)
    t_idx, g_idx = np.nonzero(starts)
    np.add.at(diff, (t_idx, g_idx), 1)
    np.add.at(diff, (t_idx + lengths[t_idx, g_idx], g_idx), -1)
    return np.cumsum(diff, axis=0)[:T] > 0


def coco17_to_body25(kp17: NDArray) -> NDArray[np.float64]:
    """(..., 17, 3) COCO-17-ordered points (with BODY_25 hips) -> (..., 25, 3) OpenPose BODY_25.

    The neck and mid-hip are the midpoints of the shoulders and the hips (confidence: the lower
    of the two; 0 when either is missing); the six foot points are written as not detected.
    """
    from embodmocap.io.openpose import COCO17_FROM

    kp17 = np.asarray(kp17, dtype=np.float64)
    out = np.zeros(kp17.shape[:-2] + (25, 3))
    out[..., list(COCO17_FROM["BODY_25"]), :] = kp17
    for dst, (a, b) in ((1, (5, 6)), (8, (11, 12))):
        c = np.minimum(kp17[..., a, 2], kp17[..., b, 2])
        out[..., dst, :2] = np.where((c > 0)[..., None], 0.5 * (kp17[..., a, :2] + kp17[..., b, :2]), 0.0)
        out[..., dst, 2] = c
    return out


def person_height_px(gt_px: NDArray) -> NDArray[np.float64]:
    """(T,) size of the person in the image: the larger extent of the true keypoints, px."""
    gt = np.asarray(gt_px, dtype=np.float64)
    ext = gt.max(axis=1) - gt.min(axis=1)
    return ext.max(axis=-1)


def swap_mask(T: int, rng: np.random.Generator, cfg: KeypointNoiseConfig) -> NDArray[np.bool_]:
    """(T, G) True where limb group g (of :data:`SWAP_GROUPS`) is swapped left/right in frame t.

    Swap events start with probability ``cfg.swap_rate`` per frame and group and last a random
    number of frames in ``cfg.swap_frames``.
    """
    G = len(SWAP_GROUPS)
    starts = rng.random((T, G)) < cfg.swap_rate
    lengths = rng.integers(cfg.swap_frames[0], cfg.swap_frames[1] + 1, size=(T, G))
    # A frame is swapped if some event began at most (length - 1) frames before it: mark each
    # event's end with a difference array and integrate (vectorised, no loop over frames).
    diff = np.zeros((T + cfg.swap_frames[1] + 1, G), dtype=np.int64)
    t_idx, g_idx = np.nonzero(starts)
    np.add.at(diff, (t_idx, g_idx), 1)
    np.add.at(diff, (t_idx + lengths[t_idx, g_idx], g_idx), -1)
    return np.cumsum(diff, axis=0)[:T] > 0


def _apply_swaps(kp: NDArray, mask: NDArray[np.bool_]) -> NDArray:
    out = kp.copy()
    for g, pairs in enumerate(SWAP_GROUPS):  # two groups: a loop over limbs, not frames
        sel = mask[:, g]
        for left, right in pairs:
            out[sel, left], out[sel, right] = kp[sel, right], kp[sel, left]
    return out


# --------------------------------------------------------------------------------------------
# masks
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MaskNoiseConfig:
    """How a segmentation model's person mask differs from the truth."""

    max_shift_px: int = 3
    """The whole boundary moves in or out by a random 0..max_shift_px pixels (erode or dilate)."""
    min_shift_px: int = 1
    """Smallest boundary move, pixels (0 allows an unchanged boundary)."""
    edge_band_px: int = 2
    """Half-width of the band around the boundary where the edge is made jagged, pixels."""
    edge_flip_frac: float = 0.3
    """Fraction of the band's pixels flipped (in blobs), giving a jagged, uneven edge."""
    blob_sigma_px: float = 1.5
    """Size of the flipped blobs (Gaussian smoothing of the random field), pixels."""


def noisy_mask(mask: NDArray, rng: np.random.Generator, cfg: MaskNoiseConfig = MaskNoiseConfig()) -> NDArray[np.bool_]:
    """Degrade a true (H, W) bool person mask like a segmentation model; returns a new mask.

    The boundary first moves in or out by 1-3 px (morphological erode or dilate with a disc), then
    blobs of the pixels within ``edge_band_px`` of the new boundary are flipped. Changes never
    reach further than ``max_shift_px + edge_band_px`` from the true boundary.
    """
    import cv2

    m = np.asarray(mask, dtype=bool)
    if not m.any():
        return m.copy()
    r = int(rng.integers(cfg.min_shift_px, cfg.max_shift_px + 1))
    m8 = m.astype(np.uint8)
    if r > 0:
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        m8 = cv2.dilate(m8, disc) if rng.random() < 0.5 else cv2.erode(m8, disc)
    b = cfg.edge_band_px
    if b > 0 and cfg.edge_flip_frac > 0:
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * b + 1, 2 * b + 1))
        band = cv2.dilate(m8, disc) != cv2.erode(m8, disc)
        field = gaussian_filter(rng.normal(size=m.shape), cfg.blob_sigma_px)
        # Flip the band pixels where the smooth field is in its top `edge_flip_frac` quantile.
        thr = np.quantile(field[band], 1.0 - cfg.edge_flip_frac) if band.any() else np.inf
        flip = band & (field > thr)
        m8 = np.where(flip, 1 - m8, m8)
    return m8.astype(bool)


# --------------------------------------------------------------------------------------------
# camera-space body prior
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PriorNoiseConfig:
    """How a camera-space SMPL regressor's (VIMO/HMR-like) output differs from the truth."""

    pose_std_deg: float = 7.0
    """Std of the per-joint rotation error of ``body_pose`` (each axis-angle component), degrees."""
    orient_std_deg: float = 4.0
    """Std of the root-orientation error (each component), degrees."""
    betas_std: float = 0.3
    """Std of the per-frame shape error added to each beta."""
    depth_rel_std: float = 0.1
    """Std of the relative depth error: the pelvis is moved along its camera ray by this fraction
    of its distance (the 2D projection stays right, the depth is wrong, as monocular methods are)."""
    xy_std_m: float = 0.01
    """Std of an extra error of the pelvis across the ray, metres."""
    corr_s: float = 0.5
    """Correlation time of all errors, seconds (Gaussian smoothing of white noise): regressors run
    on short windows, so their errors drift slowly rather than jitter."""
    betas_bias_std: float = 0.0
    """Std of a per-session constant offset added to every frame's betas (one person, one wrong
    shape: a real regressor's persistent shape error). The body it believes in is then placed
    where it looks as large as in the image: the pelvis depth is multiplied by
    ``stature(betas + offset) / stature(betas)``, so this error cannot be seen in 2D (it is the
    metric scale error no image can correct). 0 = off (no random draw: the other errors stay the
    same for a given seed)."""


#: The realistic regressor plus a persistent, size-consistent shape error ("realistic+shape bias"):
#: a per-session betas offset of std 0.52, whose rest-pose height error has a std of 3.0 % on the
#: studio's body model (20000 draws around a studio performer's shape: std 0.5 gives 2.9 %, 0.8
#: gives 4.6 %; checked in tests/test_mono_refine.py), the depth scaled with it.
HARD_PRIOR_NOISE = PriorNoiseConfig(betas_bias_std=0.52)

#: A poor regressor (``embodmocap synth --body-prior poor``): depth 20 % off, 15 degrees per joint.
POOR_PRIOR_NOISE = PriorNoiseConfig(pose_std_deg=15.0, orient_std_deg=10.0, betas_std=0.6, depth_rel_std=0.2,
                                    xy_std_m=0.03)


def body_prior(
    params: SmplParams,
    T_world_cam: NDArray,
    body,
    rng: np.random.Generator,
    cfg: PriorNoiseConfig = PriorNoiseConfig(),
    frame_ids: NDArray | None = None,
) -> BodyPriorSeq:
    """The camera-space body prior a regressor would give for world-space ``params`` seen by a camera.

    Args:
        params: true SMPL params in the world (scene) frame, T frames.
        T_world_cam: (T, 4, 4) camera-to-world poses of the same frames.
        body: the body model (for the rest-pose pelvis, which ``transl`` is relative to).
        rng: random generator.
        cfg: noise settings.
        frame_ids: (T,) frame index of each row; default 0..T-1.

    Returns:
        :class:`BodyPriorSeq`: global orientation and ``transl`` in the camera frame, noisy
        body pose and per-frame betas.
    """
    T = len(params)
    T_wc = np.asarray(T_world_cam, dtype=np.float64)
    if T_wc.shape != (T, 4, 4):
        raise ValueError(f"T_world_cam must be ({T}, 4, 4), got {T_wc.shape}")
    sigma = max(cfg.corr_s * params.fps, 1e-6)
    T_cw = invert_T(T_wc)
    R_cw = T_cw[:, :3, :3]

    # Truth in the camera frame: SMPL rotates about the rest-pose pelvis J0, then translates,
    # so the pelvis sits at J0 + transl and moves rigidly with the frame change.
    betas = np.asarray(params.betas, dtype=np.float64)
    J0, dJ0 = _pelvis_affine(body, len(betas))
    pelvis_w = J0 + betas @ dJ0 + params.transl
    pelvis_c = np.einsum("tij,tj->ti", R_cw, pelvis_w) + T_cw[:, :3, 3]
    # (copies: scipy's rotations refuse the read-only arrays of SmplParams)
    R_go_c = R_cw @ Rotation.from_rotvec(np.array(params.global_orient)).as_matrix()

    # Errors: smooth random processes with the configured stds.
    d_orient = _smooth_noise(rng, (T, 3), sigma) * np.deg2rad(cfg.orient_std_deg)
    d_pose = _smooth_noise(rng, (T, 23, 3), sigma) * np.deg2rad(cfg.pose_std_deg)
    d_betas = _smooth_noise(rng, (T, len(betas)), sigma) * cfg.betas_std
    depth_scale = 1.0 + _smooth_noise(rng, (T,), sigma) * cfg.depth_rel_std
    d_xy = _smooth_noise(rng, (T, 2), sigma) * cfg.xy_std_m

    go = (Rotation.from_rotvec(d_orient) * Rotation.from_matrix(R_go_c)).as_rotvec()
    pose = Rotation.from_rotvec(d_pose.reshape(-1, 3)) * Rotation.from_rotvec(np.array(params.body_pose).reshape(-1, 3))
    betas_t = betas[None] + d_betas
    size = 1.0
    if cfg.betas_bias_std > 0:
        from embodmocap.body.stature import stature

        bias = rng.normal(size=len(betas)) * cfg.betas_bias_std
        betas_t = betas_t + bias[None]
        # the body it believes in (its size) placed where it looks as large as in the image
        size = float(stature(body, betas + bias) / stature(body, betas))
    pelvis_noisy = pelvis_c * (np.maximum(depth_scale, 0.2) * size)[:, None]
    pelvis_noisy[:, :2] += d_xy
    transl_c = pelvis_noisy - (J0 + betas_t @ dJ0)
    ids = np.arange(T) if frame_ids is None else np.asarray(frame_ids)
    return BodyPriorSeq(go, pose.as_rotvec().reshape(T, 69), betas_t, transl_c, ids)


def _pelvis_affine(body, n_betas: int) -> tuple[NDArray, NDArray]:
    """The rest-pose pelvis as an affine function of betas: ``J0(b) = J0 + b @ dJ0``.

    The SMPL joint regressor and shape blend shapes are linear, so n+1 evaluations give the exact
    map; this lets per-frame betas be handled without a model call per frame.
    """
    zero = np.asarray(_np(body.pelvis_offset(np.zeros(n_betas))), dtype=np.float64).reshape(3)
    eye = np.stack([np.asarray(_np(body.pelvis_offset(e)), dtype=np.float64).reshape(3) for e in np.eye(n_betas)])
    return zero, eye - zero


def _np(x):
    return x.detach().cpu().numpy() if hasattr(x, "detach") else x


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, ...], sigma_frames: float) -> NDArray:
    """Unit-variance Gaussian noise of ``shape``, smoothed along axis 0 with a Gaussian of
    ``sigma_frames`` and rescaled so that each sample still has variance 1."""
    white = rng.normal(size=shape)
    if sigma_frames < 0.5:
        return white
    smooth = gaussian_filter1d(white, sigma_frames, axis=0, mode="reflect")
    # Variance after filtering is the sum of the squared kernel weights: rescale by it.
    delta = np.zeros(int(8 * sigma_frames) + 1)
    delta[len(delta) // 2] = 1.0
    kernel = gaussian_filter1d(delta, sigma_frames, mode="constant")
    return smooth / np.sqrt(np.sum(kernel**2))
