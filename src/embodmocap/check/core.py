"""`embodmocap check`: is this take usable, before the team leaves the place?

Per sequence, on a sample of frames and without running Stages II-IV:

1. **sync**: the laser-dot event of each view (the same detector as Stage II); the views sliced
   from it (or from their first frames when a view has none);
2. **performer**: the precomputed keypoints of session.toml (at most ``max_frames`` per view,
   evenly subsampled), linked into tracks and the performer chosen as Stage II does; the fraction
   of the time both views see the performer;
3. **registration**: ``register_frames`` frames per view registered to the scene's sparse model
   (Stage I must have run for the scene: it is the scene capture a team processes first, and it is
   what every view is measured against); a yaw-only offset from the VIO poses of the registered
   frames puts every sampled frame in the scene's world. Without Stage I outputs the checks below
   are skipped with a warning (never a silent pass);
4. **geometry**: the angle between the two views at the performer over time (the paper asks for
   60-120 degrees), and the geometric sync (rays meeting, :mod:`embodmocap.sequence.geosync`) on
   the subsampled timeline, checked against the laser (two views only);
5. **tracking jumps**: VIO poses that move or turn faster than a hand can (relocalisation jumps).

Every finding is a reason for one verdict: ``usable`` (none), ``usable with warnings`` or
``reshoot``; exit status 0 / 1 / 2. A one-phone sequence is checked the same way on its one view
(the performer's share of the view's time against the both-views limits; no angle and no sync to
check) and gets a note saying what one view cannot give (:data:`ONE_VIEW_NOTE`).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap.check.config import CheckConfig
from embodmocap.errors import InputError
from embodmocap.io.layout import VIEWS, SessionLayout

log = logging.getLogger(__name__)

VERDICTS = ("usable", "usable with warnings", "reshoot")

#: What ``check`` says of every one-phone sequence (a note: it does not change the verdict).
ONE_VIEW_NOTE = ("one phone: no sync needed, but no triangulation: each joint's depth comes from the phone's LiDAR "
                 "at the keypoint, and a limb hidden from the one view (behind the body or furniture) from the "
                 "2D keypoints, smoothness and the body prior only, so the motion is less accurate than with two "
                 "phones (1.8x the two-phone W-MPJPE on average on the studio benchmark, up to 2.6x; README)")

#: COCO-17 hips and shoulders: the performer's position for the view angle.
TORSO = (5, 6, 11, 12)


@dataclass
class SequenceCheck:
    """The check of one sequence: verdict, reasons and the figures behind them."""

    name: str
    verdict: str = "usable"
    reasons: list[str] = field(default_factory=list)
    figures: dict = field(default_factory=dict)
    seconds: float = 0.0
    notes: list[str] = field(default_factory=list)
    """What the capture cannot give by design (e.g. one phone), said without changing the verdict."""
    skipped: list[dict] = field(default_factory=list)
    """Checks not made: ``{"checks": [names], "reason": why, "enable": what to do or run}`` each."""

    def warn(self, msg: str) -> None:
        self.reasons.append(f"warning: {msg}")
        if self.verdict == "usable":
            self.verdict = "usable with warnings"

    def skip(self, checks: list[str], reason: str, enable: str) -> None:
        """``checks`` not made for ``reason`` (a warning: never a silent pass); ``enable`` says what
        to add or run so the next check makes them."""
        self.skipped.append({"checks": list(checks), "reason": reason, "enable": enable})
        self.warn(f"{reason}: {', '.join(checks)} not checked")

    def fail(self, msg: str) -> None:
        self.reasons.append(f"reshoot: {msg}")
        self.verdict = "reshoot"

    @property
    def exit_status(self) -> int:
        return VERDICTS.index(self.verdict)

    def to_json(self) -> dict:
        return {"sequence": self.name, "verdict": self.verdict, "exit_status": self.exit_status,
                "reasons": self.reasons, "notes": self.notes, "skipped": self.skipped, "figures": self.figures,
                "seconds": round(self.seconds, 2)}


def check_session(cfg: CheckConfig, session: str | Path, seq: str | None = None) -> list[SequenceCheck]:
    """Check every sequence of the session (or only ``seq``)."""
    from embodmocap.io.manifest import load_manifest

    lay = SessionLayout(Path(session))
    manifest = load_manifest(lay.manifest)
    names = list(manifest.sequences)
    if seq is not None:
        if seq not in manifest.sequences:
            raise InputError(lay.manifest, f"no sequence named '{seq}'", f"sequences in this session: {', '.join(names)}")
        names = [seq]
    indexes: dict[str, object] = {}
    return [check_sequence(cfg, lay, manifest.sequences[n], indexes) for n in names]


def exit_status(results: list[SequenceCheck]) -> int:
    """The worst verdict's status: 0 usable, 1 usable with warnings, 2 reshoot."""
    return max((r.exit_status for r in results), default=0)


def format_text(results: list[SequenceCheck]) -> str:
    lines = []
    for r in results:
        f = r.figures
        lines.append(f"sequence {r.name}: {r.verdict.upper()}  ({r.seconds:.1f} s)")
        sync = f.get("sync", {})
        laser = sync.get("laser", {})
        lines.append("  sync: laser " + ", ".join(
            f"{v} {'frame ' + str(d['frame']) + ' (conf ' + format(d['confidence'], '.2f') + ')' if d.get('found') else 'none'}"
            for v, d in laser.items()) + (f"; geometric {sync['geometric_offset_frames']:+.2f} frames from the slicing "
                                          f"(conf {sync['geometric_confidence']:.2f})" if sync.get("geometric_offset_frames") is not None
                                          else "; geometric: n/a"))
        if f.get("one_view") and "seen_fraction" in f:
            lines.append(f"  performer in view: {100 * f['seen_fraction']['v1']:.0f}% of the time")
        if "both_seen_fraction" in f:
            lines.append(f"  performer in both views: {100 * f['both_seen_fraction']:.0f}% of the time "
                         f"(v1 {100 * f['seen_fraction']['v1']:.0f}%, v2 {100 * f['seen_fraction']['v2']:.0f}%)")
        if f.get("angle_deg"):
            a = f["angle_deg"]
            lines.append(f"  angle between views: median {a['median']:.0f} deg (range {a['min']:.0f}-{a['max']:.0f}), "
                         f"{100 * a['in_range_fraction']:.0f}% of the time in {a['range'][0]:.0f}-{a['range'][1]:.0f}")
        for v, d in f.get("registration", {}).items():
            lines.append(f"  {v} registration: {d['registered']}/{d['tried']} sample frames"
                         + (f", offset fit {d['median_residual_m'] * 100:.1f} cm" if d.get("median_residual_m") is not None else ""))
        if "tracking_jumps" in f:
            lines.append("  tracking jumps: " + ", ".join(f"{v} {n}" for v, n in f["tracking_jumps"].items()))
        lines += [f"  - {x}" for x in r.reasons]
        lines += [f"  note: {x}" for x in r.notes]
        lines += [f"  skipped: {', '.join(x['checks'])} ({x['reason']}); to check them: {x['enable']}" for x in r.skipped]
    return "\n".join(lines)


# --------------------------------------------------------------------------- one sequence


def check_sequence(cfg: CheckConfig, lay: SessionLayout, entry, indexes: dict) -> SequenceCheck:
    from embodmocap.io.captures import open_capture
    from embodmocap.sequence.slicing import slice_views
    from embodmocap.sequence.sync_record import first_record

    t0 = time.perf_counter()
    res = SequenceCheck(entry.name)
    views = entry.view_names  # ("v1", "v2"), or ("v1",) for a one-phone sequence
    caps = {v: open_capture(entry.views[v].capture) for v in views}
    res.figures["one_view"] = entry.one_view
    if entry.one_view:
        res.notes.append(ONE_VIEW_NOTE)

    # 1. Laser sync (manual frames of session.toml count as given).
    manual = {v: entry.views[v].sync_frame for v in views}
    events, record = first_record(caps, manual, cfg.sync, geometric=True, seq=entry.name, min_overlap_s=1.0)
    res.figures["sync"] = {"laser": {v: {k: d.get(k) for k in ("found", "frame", "confidence")}
                                     for v, d in record["sources"]["laser"]["views"].items()},
                           "slicing": record["slicing"]["source"]}
    try:
        maps = slice_views(caps, events, None, 1.0)
    except InputError as err:
        res.fail(f"the views do not overlap after sync: {err}")
        res.seconds = time.perf_counter() - t0
        return res
    T = len(maps[views[0]])
    stride = max(1, math.ceil(T / cfg.max_frames))
    seq_idx = np.arange(0, T, stride)
    fps = maps[views[0]].fps / stride
    res.figures.update({"frames": T, "seconds": round(T / maps[views[0]].fps, 2), "sampled_every": stride})

    # 2. Performer.
    kps = _performer(cfg, entry, caps, maps, seq_idx, res)

    # 3. Registration and world cameras of the sampled frames.
    world = _register(cfg, lay, entry, caps, maps, seq_idx, kps, indexes, res)

    # 4. Geometry: view angle, geometric sync (two views: one view has no angle and no sync).
    geo = None
    if world is not None and kps is not None and not entry.one_view:
        _angle(cfg, world, kps, caps, res)
        geo = _geosync(cfg, world, kps, caps, maps, seq_idx, fps, record, res)
    if world is not None and not entry.one_view:
        _dot_check(cfg, world, caps, maps, seq_idx, record, res)
    if entry.one_view:
        res.figures["sync"]["found"] = ["one_view"]
    else:
        _sync_verdict(cfg, record, res)
        _sync_decision(cfg, entry, record, geo, maps[VIEWS[0]].fps, res)

    # 5. Tracking jumps.
    _jumps(cfg, caps, maps, res)
    res.seconds = time.perf_counter() - t0
    log.info("check %s: %s in %.1f s", entry.name, res.verdict, res.seconds)
    return res


def _performer(cfg: CheckConfig, entry, caps, maps, seq_idx, res: SequenceCheck) -> dict | None:
    from embodmocap.perception.precomputed import PrecomputedKeypoints
    from embodmocap.perception.tracking import (performer_keypoints, select_performer, select_performer_two_views,
                                                track_people)

    views = entry.view_names
    missing = [v for v in views if entry.views[v].keypoints is None]
    if missing:
        # Real captures fresh from the phones have no keypoints yet: the check reads precomputed
        # ones only (it runs no network), so say what that leaves out and how to bring them.
        geometry = [] if entry.one_view else ["view angle", "geometric sync"]
        res.skip(["performer"] + geometry,
                 f"no keypoint folder in session.toml for {', '.join(missing)}",
                 f"add `keypoints = \"FOLDER\"` (OpenPose per-frame JSON, e.g. from OpenPose or Pose2Sim) to "
                 + " and ".join(f"[sequences.{entry.name}.views.{v}]" for v in missing)
                 + " in session.toml and run `embodmocap check` again; registration and tracking jumps are "
                 "checked without them")
        return None
    tracks, sizes = {}, {}
    for v in views:
        raw = maps[v].raw_frames[seq_idx]
        people = PrecomputedKeypoints(entry.views[v].keypoints).read(raw)
        sizes[v] = (caps[v].rgb_intrinsics.width, caps[v].rgb_intrinsics.height)
        tracks[v] = track_people(people, sizes[v])
    n = len(seq_idx)
    frames = np.arange(n)
    if len(views) == 1:
        best = (select_performer(tracks[views[0]], n, sizes[views[0]]),)
    else:
        best = select_performer_two_views(tracks["v1"], tracks["v2"], frames, frames, sizes["v1"], sizes["v2"], n, n)
    kps = {v: performer_keypoints(tr, n)[0] for v, tr in zip(views, best)}
    seen = {v: (kps[v][..., 2] >= cfg.geosync.min_keypoint_confidence).sum(axis=1) >= cfg.min_joints for v in views}
    res.figures["seen_fraction"] = {v: round(float(seen[v].mean()), 3) for v in views}
    if len(views) == 1:  # one phone: the same limits on the time the one view sees the performer
        one = float(seen[views[0]].mean()) if n else 0.0
        if one < cfg.both_seen_reshoot:
            res.fail(f"the performer is in the view only {100 * one:.0f}% of the time (need {100 * cfg.both_seen_reshoot:.0f}%)")
        elif one < cfg.both_seen_warn:
            res.warn(f"the performer is in the view only {100 * one:.0f}% of the time")
        return kps
    both = float(np.mean(seen["v1"] & seen["v2"])) if n else 0.0
    res.figures["both_seen_fraction"] = round(both, 3)
    if both < cfg.both_seen_reshoot:
        res.fail(f"the performer is in both views only {100 * both:.0f}% of the time (need {100 * cfg.both_seen_reshoot:.0f}%)")
    elif both < cfg.both_seen_warn:
        res.warn(f"the performer is in both views only {100 * both:.0f}% of the time")
    return kps


def _keypoint_mask(kp: NDArray, size: tuple[int, int], grow: float = 0.25) -> NDArray[np.bool_]:
    """(H, W) box around the confident keypoints, grown by ``grow`` of its size (the person,
    whose features must not register the view)."""
    W, H = size
    m = np.zeros((H, W), dtype=bool)
    ok = kp[:, 2] > 0.1
    if ok.sum() < 2:
        return m
    lo, hi = kp[ok, :2].min(axis=0), kp[ok, :2].max(axis=0)
    pad = grow * (hi - lo) + 20
    x0, y0 = np.maximum(lo - pad, 0).astype(int)
    x1, y1 = np.minimum(hi + pad, [W - 1, H - 1]).astype(int)
    m[y0:y1 + 1, x0:x1 + 1] = True
    return m


def _vio(cap, raw: NDArray) -> NDArray:
    traj = cap.trajectory
    row = np.clip(np.searchsorted(traj.frame_ids, raw), 0, len(traj) - 1)
    return traj.T_world_cam[row]


def _register(cfg: CheckConfig, lay: SessionLayout, entry, caps, maps, seq_idx, kps, indexes: dict,
              res: SequenceCheck) -> dict | None:
    """World cameras (sampled frames) of each view via a few registered frames; None if not possible."""
    from embodmocap.calibrate.offset import RobustOffsetConfig, robust_yaw_offset
    from embodmocap.calibrate.register import RegisterConfig, build_scene_index, register_frames

    scene = lay.scene(entry.scene)
    if not scene.sfm_model.is_dir():
        res.skip(["registration"] + ([] if entry.one_view else ["view angle", "geometric sync", "same laser dot"]),
                 f"scene {entry.scene} is not processed: no Stage I sparse model in {scene.sfm_model.parent}",
                 f"run `embodmocap scene {lay.root} --scene {entry.scene}`, then `embodmocap check` again")
        return None
    rcfg = RegisterConfig()
    if entry.scene not in indexes:
        indexes[entry.scene] = build_scene_index(scene.sfm_dir, rcfg)
    index = indexes[entry.scene]
    world, reg_fig = {}, {}
    n = len(seq_idx)
    for v in caps:
        cap = caps[v]
        size = (cap.rgb_intrinsics.width, cap.rgb_intrinsics.height)
        pick = np.unique(np.linspace(0, n - 1, min(cfg.register_frames, n)).round().astype(int))
        raw = maps[v].raw_frames[seq_idx]
        frames = [(int(i), np.asarray(cap.frames.rgb(int(raw[i]))),
                   _keypoint_mask(kps[v][i], size) if kps is not None else np.zeros(size[::-1], bool)) for i in pick]
        reg = register_frames(frames, cap.rgb_intrinsics, index, rcfg)
        if reg.registered_fraction < 0.5:
            # As Stage III does: retrieval can rank the right key frames low; try more of them.
            wider = replace(rcfg, num_candidates=3 * rcfg.num_candidates)
            retry = register_frames(frames, cap.rgb_intrinsics, index, wider)
            reg = retry if retry.registered_fraction > reg.registered_fraction else reg
        T_vio = _vio(cap, raw)
        fig = {"tried": int(len(pick)), "registered": int(len(reg.t)), "median_residual_m": None}
        frac = len(reg.t) / max(len(pick), 1)
        fit = None
        if len(reg.t) >= 2:
            try:
                fit = robust_yaw_offset(T_vio[reg.t, :3, 3], reg.T_world_cam[:, :3, 3], RobustOffsetConfig())
            except ValueError:
                fit = None
        if fit is not None and fit.num_inliers >= 2:
            fig["median_residual_m"] = round(float(np.median(fit.residuals_m[fit.inliers])), 4)
            fig["inliers"] = int(fit.num_inliers)
            frac = fit.num_inliers / max(len(pick), 1)  # wrong registrations do not count
            world[v] = fit.offset.apply(T_vio)
        reg_fig[v] = fig
        if frac < cfg.registered_reshoot:
            res.fail(f"view {v} registers to scene {entry.scene} in only {fig['registered']} of {len(pick)} sampled "
                     "frames (another place, very different lighting, or too little background)")
        elif frac < cfg.registered_warn:
            res.warn(f"view {v} registers to the scene in only {fig['registered']} of {len(pick)} sampled frames")
    res.figures["registration"] = reg_fig
    return world if len(world) == len(caps) else None


def _midpoints(world: dict, kps: dict, caps, conf: float) -> tuple[NDArray, NDArray]:
    """(n, 3) the performer's torso point from both views' rays, and (n,) where it exists."""
    from embodmocap.geometry.raycast import pixel_rays

    out, ok = [], []
    c, d = {}, {}
    for v in VIEWS:
        k = kps[v][:, TORSO]
        good = k[..., 2] >= conf
        xy = np.where(good[..., None], k[..., :2], 0).sum(1) / np.maximum(good.sum(1), 1)[:, None]
        c[v], d[v] = pixel_rays(caps[v].rgb_intrinsics.K, world[v], xy)
        ok.append(good.sum(1) >= 2)
    w0 = c["v1"] - c["v2"]
    b = np.sum(d["v1"] * d["v2"], -1)
    dd, e = np.sum(d["v1"] * w0, -1), np.sum(d["v2"] * w0, -1)
    den = np.where(1 - b * b > 1e-8, 1 - b * b, 1.0)
    s, u = (b * e - dd) / den, (e - b * dd) / den
    X = 0.5 * (c["v1"] + s[:, None] * d["v1"] + c["v2"] + u[:, None] * d["v2"])
    valid = ok[0] & ok[1] & (s > 0.3) & (u > 0.3) & (1 - b * b > 1e-8)
    return X, valid


def _angle(cfg: CheckConfig, world: dict, kps: dict, caps, res: SequenceCheck) -> None:
    X, valid = _midpoints(world, kps, caps, cfg.geosync.min_keypoint_confidence)
    if valid.sum() < 3:
        res.warn("the view angle could not be measured (too few frames with the performer's torso in both views)")
        return
    a = world["v1"][valid, :3, 3] - X[valid]
    b = world["v2"][valid, :3, 3] - X[valid]
    cos = np.sum(a * b, -1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    ang = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    lo, hi = cfg.angle_range_deg
    inr = float(np.mean((ang >= lo) & (ang <= hi)))
    res.figures["angle_deg"] = {"median": round(float(np.median(ang)), 1), "min": round(float(ang.min()), 1),
                                "max": round(float(ang.max()), 1), "in_range_fraction": round(inr, 3),
                                "range": [lo, hi], "frames": int(valid.sum()),
                                "series": np.round(ang[:: max(1, len(ang) // 60)], 1).tolist()}
    msg = (f"the views are {np.median(ang):.0f} deg apart at the performer (median), in {lo:.0f}-{hi:.0f} deg "
           f"only {100 * inr:.0f}% of the time")
    if inr < cfg.angle_in_range_reshoot:
        res.fail(msg)
    elif inr < cfg.angle_in_range_warn:
        res.warn(msg)


def _geosync(cfg: CheckConfig, world, kps, caps, maps, seq_idx, fps: float, record: dict, res: SequenceCheck) -> None:
    from embodmocap.sequence.geosync import geometric_sync
    from embodmocap.sequence.sync_record import search_half_width_s

    times = {}
    for v in VIEWS:
        cap, fm = caps[v], maps[v]
        ts = np.asarray(cap.timestamps_s, float)
        times[v] = (ts[fm.raw_frames] - ts[fm.event_frame])[seq_idx] if len(ts) >= cap.num_frames else fm.seq_times_s[seq_idx]
    search = search_half_width_s(record, cfg.geosync)
    geo = geometric_sync(caps["v1"].rgb_intrinsics.K, world["v1"], kps["v1"], times["v1"],
                         caps["v2"].rgb_intrinsics.K, world["v2"], kps["v2"], times["v2"], fps, search, cfg.geosync)
    s = res.figures["sync"]
    full_fps = maps[VIEWS[0]].fps
    s["geometric_offset_frames"] = round(geo.offset_s * full_fps, 3) if geo.found else None
    s["geometric_confidence"] = round(geo.confidence, 3)
    s["geometric_std_frames"] = round(geo.std_frames * full_fps / fps, 3) if math.isfinite(geo.std_frames) else None
    s["geometric_message"] = geo.message
    return geo


def _dot_check(cfg: CheckConfig, world, caps, maps, seq_idx, record: dict, res: SequenceCheck) -> None:
    """Stage III's same-dot check on the check's registration: one laser dot is one place in the
    scene in both views (:mod:`embodmocap.sequence.laser_check`)."""
    from embodmocap.sequence.laser_check import laser_dot_check

    # The check's offsets are rigid (no scale), so each view's VIO-to-world transform is any
    # sampled frame's world pose times the inverse of its VIO pose.
    T_world_vio = {v: world[v][0] @ np.linalg.inv(_vio(caps[v], maps[v].raw_frames[seq_idx][:1])[0]) for v in VIEWS}
    chk = laser_dot_check(record, {v: (lambda v=v: caps[v]) for v in VIEWS}, T_world_vio, cfg.geosync.laser_dot_agree_m)
    if chk is not None:
        res.figures["sync"]["laser_dot_check"] = chk.to_json()


def _sync_verdict(cfg: CheckConfig, record: dict, res: SequenceCheck) -> None:
    s = res.figures["sync"]
    laser_ok = record["sources"]["laser"]["offset_s"] is not None or record["slicing"]["source"] == "manual"
    dot = s.get("laser_dot_check") or {}
    laser_apart = dot.get("same_dot") is False and record["slicing"]["source"] == "laser"
    if laser_apart:
        laser_ok = False  # two different spots went out: the laser frames are not one instant
    geo_conf = s.get("geometric_confidence")
    geo_ok = s.get("geometric_offset_frames") is not None and geo_conf is not None and geo_conf >= cfg.geosync.min_confidence
    s["found"] = [k for k, ok in (("laser" if record["slicing"]["source"] != "manual" else "manual", laser_ok),
                                  ("geometric", geo_ok)) if ok]
    if not laser_ok and not geo_ok:
        res.fail(f"no sync: the two views' laser events are {dot['gap_m']:.2f} m apart in the scene (not one dot) "
                 "and no confident geometric sync" if laser_apart else
                 "no sync: no laser event in every view and no confident geometric sync")
    elif laser_apart:
        res.warn(f"the two views' laser events are {dot['gap_m']:.2f} m apart in the scene (not one dot); "
                 "the geometric sync will be used")
    elif not laser_ok:
        lost = [v for v, d in s["laser"].items() if not d["found"]]
        res.warn(f"no laser event in {', '.join(lost)}; the geometric sync will be used")
    # A laser event in both views is enough: the check's geometric sync rests on a handful of
    # registered frames and is reported as a cross-check, not required.


def _sync_decision(cfg: CheckConfig, entry, record: dict, geo, fps: float, res: SequenceCheck) -> None:
    """What Stage III's choice (:func:`embodmocap.sequence.sync_record.decide`) would make of the
    check's sync sources: which laser events it takes, whether the geometric offset replaces the
    laser, whether manual frames are contradicted; the check warns (or fails) where Stage III would."""
    from embodmocap.sequence.laser_check import DotCheck
    from embodmocap.sequence.sync_record import decide

    if geo is None or not geo.found:
        return
    s = res.figures["sync"]
    dot = s.get("laser_dot_check")
    try:
        rec = decide(record, geo, cfg.geosync, fps, {}, entry.name, DotCheck(**dot) if dot else None,
                     entry.subframe_sync, entry.sync_force)
    except InputError as err:
        if record["slicing"]["source"] == "manual":
            res.fail(f"manual sync frames contradicted: {err}")
        return  # no usable source: the verdict above already says so
    ch = rec["chosen"]
    s["decision"] = {"source": ch["source"], "offset_frames": round(ch["offset_s"] * fps, 3), "reason": ch["reason"],
                     "overrides_laser": ch["overrides_laser"]}
    pair = rec["sources"]["laser"].get("consistent_pair")
    if pair is not None:
        res.warn("a view has several laser events: the geometric sync supports frames "
                 + ", ".join(f"{v} {f}" for v, f in pair["frames"].items()) + ", which will be used")
    elif ch["overrides_laser"]:
        res.warn(f"laser and geometric sync disagree by {abs(rec['agreement']['laser_minus_geometric_frames']):.1f} "
                 "frames; the geometric offset will be used")
    elif rec["agreement"] is not None and not rec["agreement"]["agree"]:
        res.warn(f"laser and geometric sync disagree by {abs(rec['agreement']['laser_minus_geometric_frames']):.1f} "
                 "frames; the laser offset will be used")
    elif record["slicing"]["source"] == "candidates" and ch["source"] == "laser" \
            and "geometry_confirms" not in rec["sources"]["laser"]:
        res.warn("a view has laser events that score alike and the geometric sync cannot tell them apart; "
                 "set sync_frame in session.toml")
    elif record["slicing"]["source"] == "manual" and rec["sources"]["manual"].get("geometric_minus_manual_frames") is not None \
            and abs(rec["sources"]["manual"]["geometric_minus_manual_frames"]) > cfg.geosync.agree_frames and geo.confidence >= cfg.geosync.min_confidence:
        res.warn(f"the manual sync frames differ from the geometric sync by "
                 f"{abs(rec['sources']['manual']['geometric_minus_manual_frames']):.1f} frames")


def _jumps(cfg: CheckConfig, caps, maps, res: SequenceCheck) -> None:
    from embodmocap.geometry.transforms import rotation_angle

    out = {}
    for v in caps:
        cap, fm = caps[v], maps[v]
        lo, hi = int(fm.raw_frames.min()), int(fm.raw_frames.max())
        traj = cap.trajectory
        sel = (traj.frame_ids >= lo) & (traj.frame_ids <= hi)
        T = traj.T_world_cam[sel]
        ts = np.asarray(cap.timestamps_s, float)
        ids = np.asarray(traj.frame_ids)[sel]
        t = ts[ids] if len(ts) >= cap.num_frames else ids / cap.fps
        dt = np.maximum(np.diff(t), 1e-6)
        speed = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1) / dt
        turn = np.degrees(rotation_angle(np.swapaxes(T[:-1, :3, :3], 1, 2) @ T[1:, :3, :3])) / dt
        n = int(np.sum((speed > cfg.jump_speed_mps) | (turn > cfg.jump_turn_deg_s)))
        missing = int((hi - lo + 1) - sel.sum())
        out[v] = n
        if n > cfg.jumps_reshoot:
            res.fail(f"view {v}: {n} tracking jumps (the phone's pose jumps; VIO lost track)")
        elif n:
            res.warn(f"view {v}: {n} tracking jump(s)")
        if missing > 0.05 * (hi - lo + 1):
            res.warn(f"view {v}: {missing} frames without a tracked pose")
    res.figures["tracking_jumps"] = out
