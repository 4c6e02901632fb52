"""Stage III's decisions as pure functions: arrays, typed stage data and configs in, results out.

No function here takes a path, opens a file or touches a manifest: :mod:`embodmocap.calibrate.stage`
loads Stage I/II's files with :mod:`embodmocap.io.stage_files`, calls these one step at a time
(so each step is fingerprinted and resumable) and writes what they return. :func:`solve` chains the
same steps in memory, for the benchmark's variants and for tests:

1. :func:`register_view`: a sample of a view's frames registered into the scene index, checked
   against the view's own VIO (a view that disagrees comes back with ``disagreement`` set);
   :func:`place_by_performer` places such a view through the performer the other view films;
   :func:`registration_file` is what ``registration.npz`` holds;
2. :func:`initial_offsets`: per view, the yaw-only offset of its VIO-consistent chain;
3. :func:`refine_report`: both views refined jointly (``calibration.json``'s content);
4. :func:`geometric_sync`: the sub-frame sync from both views' keypoint rays, the final sync
   record and the per-frame cameras in the scene's world (``cameras_world.npz``).

A view's Stage II data is a :class:`ViewInputs`: its VIO cameras and keypoints as arrays, and its
depth, masks and colour frames as functions of the sequence frame (so a long view is read frame
by frame, from whatever holds it: memory-mapped files in the stage, arrays in a test).
"""

from __future__ import annotations

import logging
from concurrent.futures import Executor, Future
from dataclasses import dataclass, field, replace
from typing import Mapping

import numpy as np
from numpy.typing import NDArray

from embodmocap.calibrate.config import CalibrateConfig
from embodmocap.calibrate.consistency import VioCheck, check_against_vio, off_chain_frames
from embodmocap.calibrate.final_sync import GeosyncResult, geometric_sync  # noqa: F401 (step 4 of this stage)
from embodmocap.calibrate.inputs import ViewInputs
from embodmocap.calibrate.offset import YawOffset, chain_yaw_offset
from embodmocap.calibrate.refine import ViewData, refine_offsets
from embodmocap.calibrate.register import FrameFeatures, Registration, frame_features, register_frames, select_frames
from embodmocap.errors import InputError
from embodmocap.geometry.transforms import rotation_angle
from embodmocap.io.layout import VIEWS
from embodmocap.io.stage_files import CameraFile, RegistrationFile
from embodmocap.sequence.sync_record import UNPAIRED_SLICING
from embodmocap.types import Intrinsics

log = logging.getLogger(__name__)

CALIBRATION_VERSION = 1
REGISTER_VERSION = 3


@dataclass(frozen=True)
class RegisteredView:
    """A view's registration and its check against the view's VIO.

    Attributes:
        reg: the registered frames and their 2D-3D matches; check: the VIO check per registered frame.
        off_chain: (R,) bool frames kept by the run check but off the whole chain's offset; None
            when ``disagreement`` is set.
        disagreement: the error to raise when the view cannot be placed otherwise: its registrations
            disagree with its VIO almost everywhere (:func:`place_by_performer` may still place it).
    """

    reg: Registration
    check: VioCheck
    off_chain: NDArray | None = None
    disagreement: InputError | None = None


class VioDisagreement(InputError):
    """The view's registered frames disagree with its VIO (a view the performer may still place)."""


def registration_frames(cfg: CalibrateConfig, view: ViewInputs) -> list[tuple[int, NDArray, NDArray | None]]:
    """The frames :func:`register_view` registers: ``(t, rgb, person mask)`` of a sample of the
    view's frames spread along its VIO path (read from the capture: the video decoded up to the
    last one)."""
    T_vio = np.asarray(view.cameras["T_world_cam"], dtype=np.float64)
    ts = select_frames(T_vio, cfg.register.num_frames)
    return [(int(t), np.asarray(view.rgb(int(t))), view.mask(int(t))) for t in ts]


def registration_features(cfg: CalibrateConfig, view: ViewInputs, pool: Executor,
                          reader: Executor) -> Future[list[Future[FrameFeatures]]]:
    """The frames of :func:`registration_frames`, each handed to ``pool`` for its features
    (:func:`~embodmocap.calibrate.register.frame_features`) as soon as ``reader`` (a thread of its
    own per view) has decoded it, so that decoding the video and detecting run side by side;
    :func:`register_view` takes the futures. The caller keeps OpenCV on one thread meanwhile
    (:func:`~embodmocap.calibrate.register.one_library_thread`).

    The person masks are read here, on the calling thread: reading one parses its stack's ``.npy``
    header, and CPython 3.11's parser is not safe to run on two threads at once (it failed with
    "AST constructor recursion depth mismatch" when both views' readers read masks)."""
    T_vio = np.asarray(view.cameras["T_world_cam"], dtype=np.float64)
    ts = [int(t) for t in select_frames(T_vio, cfg.register.num_frames)]
    masks = [view.mask(t) for t in ts]

    def read() -> list[Future[FrameFeatures]]:
        return [pool.submit(frame_features, (t, np.asarray(view.rgb(t)), m), cfg.register) for t, m in zip(ts, masks)]

    return reader.submit(read)


def register_view(cfg: CalibrateConfig, view: ViewInputs, index, *, view_name: str, label: str,
                  source: object = None, frames: list | None = None, pool: Executor | None = None) -> RegisteredView:
    """Register a sample of one view's frames into the scene index and check them against its VIO.

    Args:
        cfg: Stage III settings (``register``, the VIO limits, the minimum fractions).
        view: the view's Stage II data (``rgb`` and ``mask`` are read for the sampled frames).
        index: the scene's registration index (:func:`embodmocap.calibrate.scene_index.build_scene_index`).
        view_name: ``v1`` or ``v2`` (error messages); label: ``"<seq> <view>"`` (log lines).
        source: what an error names (the view's capture).
        frames: :func:`registration_frames` of the view, when already read, or
            :func:`registration_features` (futures; their features are computed once for every
            try); None: read here.
        pool: threads for the frames (:func:`~embodmocap.calibrate.register.register_frames`).

    Raises:
        InputError: too few frames registered (names ``source`` and the likely causes).
    """
    T_vio = np.asarray(view.cameras["T_world_cam"], dtype=np.float64)
    K = Intrinsics.from_K(view.cameras["K"], int(view.cameras["width"]), int(view.cameras["height"]))
    frames = registration_frames(cfg, view) if frames is None else [
        f.result() if isinstance(f, Future) else f for f in frames]
    reg = register_frames_of_view(cfg, frames, K, index, T_vio, label, pool)
    check = check_against_vio(reg.T_world_cam, T_vio[reg.t], reg.inliers,
                              cfg.vio_max_disagreement_m, cfg.vio_max_disagreement_deg)
    try:
        check_view(cfg, source, view_name, reg, check)
    except VioDisagreement as err:
        return RegisteredView(reg, check, None, err)
    # Frames the run check kept but that sit off the whole chain's offset (an error ramping up
    # along a run passes the neighbour-to-neighbour test): out of the fit as well.
    off = off_chain_frames(reg.T_world_cam, T_vio[reg.t], check.accepted, cfg.vio_max_disagreement_m,
                           cfg.vio_max_disagreement_deg, offset_cfg=cfg.offset)
    return RegisteredView(reg, check, off)


def register_frames_of_view(cfg: CalibrateConfig, frames, K, index, T_vio: np.ndarray, name: str,
                            pool: Executor | None = None) -> Registration:
    """Register one view's frames: a few by retrieval first, the rest by pose from their coarse,
    VIO-checked offset; frames that still fail are retried against more retrieval candidates.

    Retrieval ranks key frames by appearance, which repetitive or plain walls fool; once a coarse
    offset is known, the key frames that see what each VIO camera sees are the right candidates.
    """
    rc = cfg.register
    pick = np.zeros(len(frames), dtype=bool)
    pick[np.unique(np.linspace(0, len(frames) - 1, min(rc.coarse_frames, len(frames))).round().astype(int))] = True
    retrieval = replace(rc, candidates="retrieval")
    first = register_frames([f for f, p in zip(frames, pick) if p], K, index, retrieval, pool=pool)
    coarse = coarse_offset(cfg, first, T_vio)
    if coarse is None:  # retrieval failed on the sample: try it with more candidates
        wider = replace(retrieval, num_candidates=rc.num_candidates * cfg.retry_candidates_factor)
        log.info("%s: no VIO-consistent coarse offset from %d frames; retrying with %d candidates", name,
                 int(pick.sum()), wider.num_candidates)
        first = register_frames([f for f, p in zip(frames, pick) if p], K, index, wider, pool=pool)
        coarse = coarse_offset(cfg, first, T_vio)
    rest = [f for f, p in zip(frames, pick) if not p]
    if coarse is None:
        log.info("%s: still no coarse offset; registering every frame by retrieval", name)
        reg = first.merged(register_frames(rest, K, index, retrieval, pool=pool))
    else:
        predicted = {int(f[0]): coarse.apply(T_vio[int(f[0])]) for f in rest}
        reg = first.merged(register_frames(rest, K, index, replace(rc, candidates="auto"), predicted, pool))
    if reg.registered_fraction < cfg.retry_below_fraction:
        # Rare now: retry only the frames that failed, against more retrieval candidates.
        failed = set(int(t) for t in reg.attempted) - set(int(t) for t in reg.t)
        wider = replace(retrieval, num_candidates=rc.num_candidates * cfg.retry_candidates_factor)
        log.info("%s: %.0f%% registered; retrying %d frames with %d candidates", name, 100 * reg.registered_fraction,
                 len(failed), wider.num_candidates)
        retry = register_frames([f for f in frames if int(f[0]) in failed], K, index, wider, pool=pool)
        keep = ~np.isin(reg.attempted, retry.attempted)
        reg = Registration(reg.attempted[keep], reg.attempted_inliers[keep], reg.t, reg.T_world_cam, reg.inliers,
                           reg.reproj_error_px, reg.correspondences, (), reg.seconds).merged(retry)
    return reg


def coarse_offset(cfg: CalibrateConfig, reg: Registration, T_vio: np.ndarray) -> YawOffset | None:
    """The offset of the VIO-consistent frames of a first registration, or None when fewer than 3
    frames agree (or they cannot fix the yaw)."""
    if len(reg.t) < 3:
        return None
    check = check_against_vio(reg.T_world_cam, T_vio[reg.t], reg.inliers, cfg.vio_max_disagreement_m,
                              cfg.vio_max_disagreement_deg)
    if check.accepted.sum() < 3:
        return None
    try:
        return chain_yaw_offset(T_vio[reg.t[check.accepted]], reg.T_world_cam[check.accepted], cfg.offset).offset
    except ValueError:
        return None


def check_view(cfg: CalibrateConfig, source: object, v: str, reg: Registration, check) -> None:
    """One clear error for a view that cannot be calibrated (names ``source``, the view's capture,
    and the likely cause); :class:`VioDisagreement` when its registrations disagree with its VIO."""
    n_tried, n_reg = len(reg.attempted), len(reg.t)
    if n_reg < cfg.min_registered_frames or n_reg < cfg.min_registered_fraction * max(n_tried, 1):
        raise InputError(source, f"view {v}: only {n_reg} of {n_tried} sampled frames registered to the scene model "
                         f"(need {100 * cfg.min_registered_fraction:.0f} %)", "likely causes: too little background "
                         "texture, the wrong scene capture, very different lighting, or the performer filling the view")
    n_ok = int(check.accepted.sum())
    if n_ok < cfg.min_registered_frames or n_ok < cfg.min_consistent_fraction * n_reg:
        raise VioDisagreement(source, f"view {v}: its registered frames disagree with its own VIO motion almost everywhere "
                              f"(largest consistent group {n_ok} of {n_reg} frames, {check.runs} runs)",
                              "likely causes: the sequence was not filmed in this scene (wrong scene capture in "
                              "session.toml), broken VIO poses, or too little background texture / very different "
                              "lighting for registration to be reliable")


def registration_file(reg: Registration, check=None, off_chain=None, T_world_vio_performer=None) -> RegistrationFile:
    """What ``registration.npz`` holds: registered poses and their 2D-3D inlier matches (flattened
    with a frame column), and the VIO check's verdict per registered frame (``accepted``: kept by
    the run check and on the whole chain's offset; ``run``; ``off_chain``: kept by the run check but
    off the chain)."""
    fr = np.concatenate([np.full(len(c.xy), c.t) for c in reg.correspondences]) if reg.correspondences else np.zeros(0, int)
    xy = np.concatenate([c.xy for c in reg.correspondences]) if reg.correspondences else np.zeros((0, 2))
    xyz = np.concatenate([c.xyz for c in reg.correspondences]) if reg.correspondences else np.zeros((0, 3))
    acc = np.ones(len(reg.t), dtype=bool) if check is None else check.accepted
    run = np.zeros(len(reg.t), dtype=np.int64) if check is None else check.run
    off = np.zeros(len(reg.t), dtype=bool) if off_chain is None else np.asarray(off_chain, dtype=bool)
    acc = acc & ~off
    return RegistrationFile(
        version=np.int64(REGISTER_VERSION), attempted=reg.attempted, attempted_inliers=reg.attempted_inliers,
        t=reg.t, T_world_cam=reg.T_world_cam, inliers=reg.inliers, reproj_error_px=reg.reproj_error_px,
        match_frames=fr, match_xy=xy, match_xyz=xyz, accepted=acc, run=run, off_chain=off,
        T_world_vio_performer=None if T_world_vio_performer is None else np.asarray(T_world_vio_performer))


def performer_registration(rv: RegisteredView, T_world_vio: NDArray) -> RegistrationFile:
    """The registration file of a view placed through the performer: none of its frames is
    trusted (all stay out of the fit), the offset is the placement."""
    return registration_file(rv.reg, replace(rv.check, accepted=np.zeros(len(rv.reg.t), dtype=bool)), None, T_world_vio)


def register_figures(v: str, rv: RegisteredView, placed_by_performer: bool = False) -> dict:
    """The stage manifest's figures of a view's registration."""
    reg, check = rv.reg, rv.check
    figures = {f"{v}_frames_tried": int(len(reg.attempted)), f"{v}_frames_registered": int(len(reg.t)),
               f"{v}_registered_fraction": round(reg.registered_fraction, 3)}
    if placed_by_performer:
        figures[f"{v}_placed_by_performer"] = True
    else:
        figures.update({f"{v}_vio_rejected_runs": check.rejected_runs, f"{v}_vio_rejected_frames": check.rejected_frames,
                        f"{v}_vio_off_chain_frames": int(rv.off_chain.sum())})
    figures[f"{v}_register_seconds"] = {k: round(s, 2) for k, s in reg.seconds.items()}
    return figures


def yaw_offset_of(T: np.ndarray) -> YawOffset:
    """The yaw offset of a (4, 4) Z-up rigid transform."""
    T = np.asarray(T, dtype=np.float64)
    return YawOffset(float(np.arctan2(T[1, 0], T[0, 0])), T[:3, 3].copy(), 1.0)


def scene_points(cfg: CalibrateConfig, vertices: NDArray, faces: NDArray):
    """The scene mesh sampled for the Chamfer term (:class:`embodmocap.calibrate.losses.ScenePoints`)."""
    from embodmocap.calibrate import losses as L

    return L.ScenePoints.from_mesh(vertices, faces, cfg.scene_points)


def track_pairs(views: Mapping[str, ViewInputs], max_frames: int = 0, residual_s: float = 0.0, fps: float = 30.0):
    """Cross-view performer correspondences from the Stage II keypoints, back-projected with depth;
    from at most ``max_frames`` evenly spread frames (0 = all); None when there are none.

    ``residual_s``: view 2's sub-frame sync (its time minus view 1's for one instant, on top of the
    slicing; :func:`embodmocap.calibrate.presync.presync_residual`); when not 0, view 2's points are
    taken at view 1's instants (:func:`embodmocap.calibrate.presync.track_pairs_on_clock`), else the
    two views' points of the same sequence frame are paired. ``fps``: the sequence frame rate."""
    from embodmocap.calibrate import losses as L
    from embodmocap.calibrate.presync import track_pairs_on_clock

    kp = {v: views[v].keypoints for v in VIEWS}
    cams = {v: views[v].cameras for v in VIEWS}
    src = L.KeypointCorrespondences(kp["v1"], kp["v2"])
    n = min(len(kp["v1"]), len(kp["v2"]))
    if residual_s != 0.0:
        frames = np.arange(len(kp["v1"]))
        if 0 < max_frames < len(frames):
            frames = np.unique(np.linspace(0, n - 1, max_frames).round().astype(np.int64))
        return track_pairs_on_clock(views, frames, residual_s, fps, src)
    corr = src.correspondences()
    if 0 < max_frames < n:
        keep = np.isin(corr.frames, np.unique(np.linspace(0, n - 1, max_frames).round().astype(np.int64)))
        corr = replace(corr, frames=corr.frames[keep], xy_a=corr.xy_a[keep], xy_b=corr.xy_b[keep],
                       weight=corr.weight[keep], behind_surface_m=corr.behind_surface_m[keep],
                       track=None if corr.track is None else corr.track[keep])
    if len(corr.frames) == 0:
        return None
    return L.track_pairs_from_depth(
        corr, VIEWS, tuple(views[v].depth_m for v in VIEWS),
        tuple(cams[v]["K"] for v in VIEWS),
        tuple((int(cams[v]["width"]), int(cams[v]["height"])) for v in VIEWS),
    )


def build_view_data(cfg: CalibrateConfig, view: ViewInputs, init: YawOffset, reg) -> ViewData:
    """The refinement's input for one view: initial cameras, background cloud, registered matches.

    Args:
        view: the view's Stage II data; init: its initial offset; reg: its registration (a
            :class:`RegistrationFile` or the same keys in a mapping).
    """
    from embodmocap.calibrate import losses as L

    cams = view.cameras
    T = len(cams["raw_frames"])
    frames = np.unique(np.linspace(0, T - 1, min(cfg.chamfer_frames, T)).astype(np.int64))
    cloud = L.background_cloud(view.depth_m, view.mask, frames, cams["K_depth"],
                               points_per_frame=cfg.chamfer_points_per_frame)
    # Only matches of frames whose registration agrees with the offset: a wrongly registered frame
    # brings 2D-3D matches that are consistent with a wrong pose, and through the VIO pose they
    # reproject hundreds of pixels off (seen: one such frame outweighed every other term).
    agree = np.linalg.norm(init.apply_points(cams["T_world_cam"][reg["t"], :3, 3]) - reg["T_world_cam"][:, :3, 3], axis=1)
    accepted = np.asarray(reg["accepted"], dtype=bool) if "accepted" in reg else np.ones(len(reg["t"]), bool)
    # Frames of runs the VIO check rejected never reach the fit, however close they happen to be.
    ok_frames = np.asarray(reg["t"])[(agree <= cfg.offset.inlier_threshold_m) & accepted]
    keep = np.isin(reg["match_frames"], ok_frames)
    matches = L.Matches2D3D.from_arrays(reg["match_frames"][keep], reg["match_xy"][keep], reg["match_xyz"][keep])
    return ViewData(T_world_cam=init.apply(cams["T_world_cam"]), K=cams["K"], background=cloud,
                    matches=matches, T_world_vio_init=init.T)


def place_by_performer(cfg: CalibrateConfig, v: str, views: Mapping[str, ViewInputs], regs: Mapping,
                       err: InputError, slicing_source: str, points, label: str) -> np.ndarray:
    """``T_world_vio`` (4, 4) of view ``v`` from the performer both views film, or ``err`` raised.

    The other view's offset comes from its own VIO-consistent registrations; each cross-view
    keypoint pair (back-projected with depth) gives a point in the world through the other view
    and the same point in ``v``'s VIO world; the robust yaw fit of the second onto the first
    places ``v``. Kept only when ``v``'s background depth then lies on the scene mesh (a capture
    of another scene does not).

    Args:
        regs: view -> registration of the views registered so far; slicing_source: ``sync.json``'s
        slicing source (``start``: no laser event, so frame pairs are not simultaneous);
        points: the scene mesh's :func:`scene_points`, or a function returning them (called only
        when the placement gets that far); label: the sequence (log lines).
    """
    from embodmocap.calibrate.offset import robust_yaw_offset

    others = [w for w in VIEWS if w != v and w in regs]
    note = "; placing it through the performer filmed by the other view did not fit the scene either"
    if not others or slicing_source in UNPAIRED_SLICING:
        raise err
    w = others[0]
    r = regs[w]
    cams = {x: views[x].cameras for x in (v, w)}
    acc = np.asarray(r["accepted"], dtype=bool)
    T_w = chain_yaw_offset(cams[w]["T_world_cam"][r["t"][acc]], r["T_world_cam"][acc], cfg.offset).offset.T
    tracks = track_pairs(views, cfg.track_frames)
    if tracks is None or len(tracks) < 20:
        raise InputError(err.path, err.problem + note, err.fix) from err
    f = tracks.frames.numpy()
    p = {tracks.view_a: tracks.p_a.numpy(), tracks.view_b: tracks.p_b.numpy()}

    def world(T_cams, pts):
        return np.einsum("nij,nj->ni", T_cams[f, :3, :3], pts) + T_cams[f, :3, 3]

    target = world(T_w @ cams[w]["T_world_cam"], p[w])
    fit = robust_yaw_offset(world(cams[v]["T_world_cam"], p[v]), target, cfg.offset)
    # Check on the scene mesh: the view's background through the placement.
    data = build_view_data(cfg, views[v], fit.offset, {**{"t": np.zeros(0, np.int64)},
                           "accepted": np.zeros(0, bool), "match_frames": np.zeros(0, np.int64),
                           "match_xy": np.zeros((0, 2)), "match_xyz": np.zeros((0, 3)),
                           "T_world_cam": np.zeros((0, 4, 4))})
    points = points() if callable(points) else points

    def on_mesh(data) -> float:
        """Share of a view's background points within ``performer_on_mesh_m`` of the mesh."""
        bg = data.background
        if bg is None or not len(bg):
            return 0.0
        Tc = np.asarray(data.T_world_cam)[bg.frames.numpy()]
        q = np.einsum("nij,nj->ni", Tc[:, :3, :3], bg.p_cam.numpy()) + Tc[:, :3, 3]
        d, _ = points.tree.query(q, distance_upper_bound=cfg.performer_on_mesh_m, workers=1)
        return float(np.mean(np.isfinite(d)))

    on = on_mesh(data)
    # The registered view's own share is the yardstick: a scan that missed part of what the views
    # see lowers both alike, a view of another scene only its own.
    on_w = on_mesh(build_view_data(cfg, views[w], yaw_offset_of(T_w), r))
    log.info("%s %s: placed through the performer in %s (%d keypoint pairs, %d inliers); %.0f%% of its background "
             "on the scene mesh (%s: %.0f%%)", label, v, w, len(f), fit.num_inliers, 100 * on, w, 100 * on_w)
    if fit.num_inliers < 20 or on < cfg.performer_min_on_mesh * on_w:
        raise InputError(err.path, err.problem + note + f" ({100 * on:.0f} % of its background on the mesh)",
                         err.fix) from err
    log.warning("%s %s: %s; placed through the performer instead (%.0f%% of its background on the scene mesh)",
                label, v, err.problem, 100 * on)
    return fit.offset.T


def initial_offsets(cfg: CalibrateConfig, views: Mapping[str, ViewInputs], regs: Mapping) -> tuple[dict, dict]:
    """Per view, the yaw-only offset of its VIO-consistent chain of registrations (or its
    placement through the performer), and the offset fit's report.

    Returns:
        (view -> :class:`YawOffset`, view -> report dict with ``vio_check``).
    """
    init: dict[str, YawOffset] = {}
    init_report = {}
    for v in views:
        cams = views[v].cameras
        r = regs[v]
        acc = np.asarray(r["accepted"], dtype=bool)
        runs = np.asarray(r["run"])
        off = np.asarray(r["off_chain"], dtype=bool)
        if "T_world_vio_performer" in r:  # placed through the performer (step 1): no frame of its own
            init[v] = yaw_offset_of(r["T_world_vio_performer"])
            init_report[v] = {"inliers": 0, "registered": int(len(r["t"])), "vio_consistent": 0,
                              "median_residual_m": None, "placement": "performer"}
        else:
            # Only the VIO-consistent chain: frames of rejected runs never reach the fit.
            fit = chain_yaw_offset(cams["T_world_cam"][r["t"][acc]], r["T_world_cam"][acc], cfg.offset)
            init[v] = fit.offset
            init_report[v] = {"inliers": int(fit.num_inliers), "registered": int(len(r["t"])),
                              "vio_consistent": int(acc.sum()),
                              "median_residual_m": float(np.median(fit.residuals_m[fit.inliers])) if fit.num_inliers else None,
                              "placement": "registration"}
        by_runs = ~acc & ~off  # rejected by the run check (off-chain frames are counted apart)
        init_report[v]["vio_check"] = {
            "runs": int(len(np.unique(runs))), "rejected_runs": int(len(np.unique(runs[by_runs]))),
            "rejected_frames": int((~acc).sum()), "off_chain_frames": int(off.sum()),
            "max_disagreement_m": cfg.vio_max_disagreement_m, "max_disagreement_deg": cfg.vio_max_disagreement_deg}
    return init, init_report


def refine_report(cfg: CalibrateConfig, views: Mapping[str, ViewInputs], init: dict, regs: Mapping,
                  init_report: dict, points=None, use_tracks: bool = True, *, sequence: str = "",
                  scene: str = "", presync: tuple[float, dict] | None = None, fps: float = 30.0) -> dict:
    """The views' offsets refined jointly (one view: alone, no track term); returns
    ``calibration.json``'s content (``one_view`` true for one view).

    Args:
        points: the scene mesh's :func:`scene_points` (or a function returning them; needed when
            ``cfg.refine_views``); use_tracks: use the cross-view keypoint pairs (False when the
            views were sliced from their first frames, i.e. not simultaneous frame by frame);
        sequence, scene: names written into the report.
        presync: :func:`embodmocap.calibrate.presync.presync_residual`'s (residual_s, record): the
            track term pairs view 2's points at view 1's instants by it (None: frame pairs, as
            without ``cfg.presync``); fps: the sequence frame rate.
    """
    from concurrent.futures import ThreadPoolExecutor

    warnings: list[str] = []
    names = [v for v in VIEWS if v in views]
    result = None
    # The scene's points (the mesh read and sampled, its KD-tree built) on a second thread while
    # this one reads the views' depth for the clouds and the track pairs: NumPy and SciPy release
    # the GIL, so the two use both cores; the values are the same as one after the other.
    with ThreadPoolExecutor(1, thread_name_prefix="refine-points") as pool:
        scene_points_ = pool.submit(points) if cfg.refine_views and callable(points) else None
        data = {v: build_view_data(cfg, views[v], init[v], regs[v]) for v in names}
        if cfg.refine_views:
            shift = presync[0] if presync is not None else 0.0
            tracks = track_pairs(views, cfg.track_frames, shift, fps) if use_tracks and len(names) > 1 else None
        points = scene_points_.result() if scene_points_ is not None else points
    if cfg.refine_views:
        if not use_tracks and len(names) > 1:
            warnings.append("no laser sync: the views were sliced from their first frames, so cross-view keypoint "
                            "pairs are not used by the refinement")
        result = refine_offsets(data, cfg.refine, scene=points, tracks=tracks)
        warnings += list(result.warnings)
        if result.diverged:
            warnings.append(f"refinement diverged ({result.message}); the registration-only offsets are kept")
    report = {"version": CALIBRATION_VERSION, "sequence": sequence, "scene": scene, "one_view": len(names) == 1,
              "views": {}, "warnings": warnings}
    for v in names:
        T0 = init[v].T
        T1 = result.views[v].T_world_vio if result is not None and not result.diverged else T0
        D = T1 @ np.linalg.inv(T0)
        shift, yaw = float(np.linalg.norm(D[:3, 3])), float(np.degrees(rotation_angle(D[:3, :3])))
        if shift > cfg.max_refine_shift_m or yaw > cfg.max_refine_yaw_deg:
            warnings.append(f"view {v}: refinement disagrees with registration by {100 * shift:.1f} cm / {yaw:.2f} deg "
                            f"(limits {100 * cfg.max_refine_shift_m:.0f} cm / {cfg.max_refine_yaw_deg} deg)")
        report["views"][v] = {
            "T_world_vio_registration": T0.tolist(), "T_world_vio": T1.tolist(),
            **({"drift": drift_record(result.views[v])} if result is not None and not result.diverged
               and len(result.views[v].knot_frames) > 1 else {}),
            "refine_shift_m": round(shift, 5), "refine_yaw_deg": round(yaw, 4),
            "registered_fraction": float(len(regs[v]["t"]) / max(len(regs[v]["attempted"]), 1)),
            "vio_check": init_report[v]["vio_check"],
            "offset_fit": init_report[v],
        }
    if presync is not None:
        report["presync"] = presync[1]
    if result is not None:
        report["refine"] = {
            "solver": result.solver, "iterations": result.iterations, "loss_before": result.loss_before,
            "loss_after": result.loss_after, "terms_before": result.terms_before, "terms_after": result.terms_after,
            "residuals_before": result.stats_before, "residuals_after": result.stats_after,
            "diverged": result.diverged, "message": result.message,
            **({"phase_frames": round(result.phase_frames, 4)} if result.phase_frames is not None else {}),
            "solvers": {k: {"loss": r.loss_final, "iterations": r.iterations, "seconds": round(r.seconds, 3)}
                        for k, r in result.runs.items()},
        }
    return report


def presync_step(cfg: CalibrateConfig, record: dict, views: Mapping[str, ViewInputs], init: Mapping[str, YawOffset],
                 fps: float, label: str = "", subframe_sync: bool = True, sync_force: bool = False):
    """The sub-frame sync on the registration-only cameras (:mod:`embodmocap.calibrate.presync`),
    ``refine_report``'s ``presync``; None when ``cfg.presync`` is off or there is one view."""
    from embodmocap.calibrate.presync import presync_residual

    if not cfg.presync or len(views) < 2:
        return None
    return presync_residual(cfg, record, views, {v: init[v].T for v in views}, fps, label, subframe_sync, sync_force)


def sync_measure_cameras(cfg: CalibrateConfig, views: Mapping[str, ViewInputs], report: dict):
    """Step 4's ``measure_on``: the registration-only cameras (views, offsets) with
    ``cfg.sync_cameras = "registration"``, else None (the refined cameras)."""
    if cfg.sync_cameras != "registration":
        return None
    return views, {v: np.asarray(report["views"][v]["T_world_vio_registration"]) for v in report["views"]}


def drift_record(offset) -> dict:
    """``calibration.json``'s ``drift`` of a view refined with drift knots (a
    :class:`~embodmocap.calibrate.refine.ViewOffset`): the knots' frames, their ``[yaw, tx, ty, tz]``
    (pivot form, on top of ``T_world_vio_registration``) and the pivot."""
    return {"knot_frames": [int(k) for k in offset.knot_frames], "knots": np.asarray(offset.knots).tolist(),
            "pivot": np.asarray(offset.pivot).tolist()}


def world_cameras(view_report: dict, T_vio_cam: NDArray) -> NDArray:
    """(T, 4, 4) a view's cameras in the scene's world from its ``calibration.json`` entry: each
    frame's drift correction on the registration offset when the view has ``drift``, else the one
    ``T_world_vio``."""
    from embodmocap.calibrate.drift import drift_transforms

    T_vio_cam = np.asarray(T_vio_cam, dtype=np.float64)
    d = view_report.get("drift")
    if d is None:
        return np.asarray(view_report["T_world_vio"]) @ T_vio_cam
    D = drift_transforms(np.asarray(d["knot_frames"]), np.asarray(d["knots"]), np.asarray(d["pivot"]), len(T_vio_cam))
    return D @ np.asarray(view_report["T_world_vio_registration"]) @ T_vio_cam


def drift_corrected(views: Mapping[str, ViewInputs], report: dict) -> dict[str, ViewInputs]:
    """The views with their VIO cameras corrected for the refined drift, so that the one
    ``T_world_vio`` of ``report`` puts every frame where :func:`world_cameras` does (what step 4,
    the geometric sync and ``cameras_world.npz``, takes). Views without drift are returned as they are."""
    out = dict(views)
    for v, vr in report["views"].items():
        if "drift" in vr:
            cams = views[v].cameras
            T = np.linalg.inv(np.asarray(vr["T_world_vio"])) @ world_cameras(vr, cams["T_world_cam"])
            out[v] = replace(views[v], cameras=replace(cams, T_world_cam=T))
    return out


def refine_cameras(views: Mapping[str, ViewInputs], init: Mapping[str, YawOffset], regs: Mapping, refine_cfg,
                   cfg: CalibrateConfig, points=None, tracks=None) -> dict[str, NDArray]:
    """view -> (T, 4, 4) cameras in the scene's world after refining the views of ``init`` (one
    alone, or both jointly) with ``refine_cfg`` (the registration-only offsets when it diverges).
    The benchmark's Stage III variants (single view, loss ablation)."""
    data = {v: build_view_data(cfg, views[v], init[v], regs[v]) for v in init}
    res = refine_offsets(data, refine_cfg, scene=points, tracks=tracks)
    return {v: res.views[v].T_world_cam if not res.diverged else data[v].T_world_vio_init @ views[v].cameras.T_world_cam
            for v in init}


@dataclass(frozen=True)
class CalibrateInputs:
    """Everything Stage III reads, in memory.

    Attributes:
        sequence, scene: names (reports and messages).
        views: view -> its Stage II data (with ``rgb`` for the registration).
        index: the scene's registration index.
        mesh_vertices, mesh_faces: (N, 3), (F, 3) the Stage I mesh (``mesh_raw.ply``).
        sync_record: Stage II's ``sync.json``.
        fps: the sequence frame rate.
        sources: view -> what an error about the view names (its capture).
        contact_sheets: view -> the laser contact sheet's path (text for the sync messages).
        laser_dots: view -> its last sighting of the laser dot, read from its capture
            (:func:`embodmocap.sequence.laser_check.observe_laser_dots`; None: no same-dot check).
        subframe_sync, sync_force: the sequence's session.toml keys for manual sync frames
            (:func:`embodmocap.sequence.sync_record.decide`).
    """

    sequence: str
    scene: str
    views: dict[str, ViewInputs]
    index: object
    mesh_vertices: NDArray
    mesh_faces: NDArray
    sync_record: dict
    fps: float
    sources: dict[str, object] = field(default_factory=dict)
    contact_sheets: dict[str, str] = field(default_factory=dict)
    laser_dots: dict | None = None
    subframe_sync: bool = True
    sync_force: bool = False


@dataclass(frozen=True)
class CalibrateResult:
    """What Stage III decides for one sequence (the content of its files).

    Attributes:
        registrations: view -> ``registration.npz``.
        report: ``calibration.json``.
        sync_record: the final ``sync.json``.
        cameras_world: view -> ``cameras_world.npz``.
        T_world_vio: view -> (4, 4) the refined offset.
    """

    registrations: dict[str, RegistrationFile]
    report: dict
    sync_record: dict
    cameras_world: dict[str, CameraFile]
    T_world_vio: dict[str, NDArray]


def solve(cfg: CalibrateConfig, inputs: CalibrateInputs) -> CalibrateResult:
    """Stage III in memory: the same steps, in the same order, as :func:`embodmocap.calibrate.stage.run`."""
    points_cache: list = []

    def points():
        if not points_cache:
            points_cache.append(scene_points(cfg, inputs.mesh_vertices, inputs.mesh_faces))
        return points_cache[0]

    files: dict[str, RegistrationFile] = {}
    regs: dict = {}
    pending = {}
    names = [v for v in VIEWS if v in inputs.views]
    for v in names:
        rv = register_view(cfg, inputs.views[v], inputs.index, view_name=v, label=f"{inputs.sequence} {v}",
                           source=inputs.sources.get(v))
        if rv.disagreement is not None:
            if not cfg.place_by_performer:
                raise rv.disagreement
            pending[v] = rv
            continue
        files[v] = registration_file(rv.reg, rv.check, rv.off_chain)
        regs[v] = dict(files[v].items())
    slicing = inputs.sync_record["slicing"]["source"]
    for v, rv in pending.items():
        T_place = place_by_performer(cfg, v, inputs.views, regs, rv.disagreement, slicing, points, inputs.sequence)
        files[v] = performer_registration(rv, T_place)
        regs[v] = dict(files[v].items())
    init, init_report = initial_offsets(cfg, inputs.views, regs)
    use_tracks = slicing not in UNPAIRED_SLICING and len(names) > 1
    pre = presync_step(cfg, inputs.sync_record, inputs.views, init, inputs.fps, inputs.sequence,
                       inputs.subframe_sync, inputs.sync_force) if use_tracks else None
    report = refine_report(cfg, inputs.views, init, regs, init_report, points, use_tracks,
                           sequence=inputs.sequence, scene=inputs.scene, presync=pre, fps=inputs.fps)
    T_world_vio = {v: np.asarray(report["views"][v]["T_world_vio"]) for v in names}
    geo = geometric_sync(cfg, inputs.sync_record, drift_corrected(inputs.views, report), T_world_vio, inputs.fps,
                         inputs.contact_sheets, inputs.sequence, inputs.laser_dots, inputs.subframe_sync,
                         inputs.sync_force, sync_measure_cameras(cfg, inputs.views, report))
    return CalibrateResult({v: files[v] for v in names}, report, geo.record, geo.cameras_world, T_world_vio)
