"""Stage II: synchronised, sliced per-view data with the performer's observations.

``run(config, session, seq)`` reads top to bottom as the recipe:

1. ``sync``: the laser-dot event of each view (session.toml's frames override detection), with a
   contact sheet per view for a person to confirm (``sync.json``, ``sync_<view>.png``). Without a
   laser event the views are sliced from their first frames and Stage III finds the offset from
   the registered cameras and the keypoints (:mod:`embodmocap.sequence.sync_record`);
2. ``slice``: one sequence timeline from the event on, mapped to each view's raw frames through
   timestamps (different rates and dropped frames handled); the view's intrinsics and VIO poses
   for those frames (``<view>/frame_map.json``, ``<view>/cameras.npz``);
3. ``keypoints``: every person's COCO-17 keypoints per frame from the chosen backend, linked into
   tracks, and the performer's track chosen consistently across both views
   (``<view>/keypoints2d.npz``: keypoints (T, 17, 3) and boxes (T, 4));
4. ``masks``, ``depth``, ``body_prior``: the other observations, per sliced frame.

Frames stream through in chunks, so memory does not grow with the sequence length. Each step is
skipped when its fingerprint matches the manifest and its outputs exist.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from embodmocap.errors import InputError
from embodmocap.io.atomic import write_json
from embodmocap.io.frame_stack import depth_mm, pack_mask, write_stack
from embodmocap.io.body_prior import BodyPriorSeq, write_body_prior
from embodmocap.io.captures import open_capture
from embodmocap.io.layout import VIEWS, SequenceLayout, SessionLayout, ViewLayout
from embodmocap.io.manifest import SequenceEntry, load_manifest
from embodmocap.io.stage_files import (
    CameraFile, Keypoints2DFile, read_keypoints2d, write_cameras, write_keypoints2d,
)
from embodmocap.io.stage_manifest import StageManifest, fingerprint, path_fingerprint, tracked_stage
from embodmocap.perception.tracking import performer_keypoints, select_performer_two_views, track_people
from embodmocap.sequence.config import SequenceConfig
from embodmocap.sequence.slicing import FrameMap, frame_map_from_json, frame_map_to_json, slice_views
from embodmocap.sequence.sync import SyncEvent, write_contact_sheet
from embodmocap.sequence.sync_record import SYNC_RECORD_VERSION, events_from_record, first_record
from embodmocap.types import Capture

log = logging.getLogger(__name__)

STAGE_VERSION = 1


@dataclass(frozen=True)
class SequenceOutputs:
    """What Stage II produced for one sequence."""

    name: str
    layout: SequenceLayout
    figures: dict
    skipped: tuple[str, ...]


@tracked_stage
def run(cfg: SequenceConfig, session: str | Path, seq: str | None = None, *, force: bool = False) -> SequenceOutputs:
    """Run Stage II for sequence ``seq`` of the session (the only one when None)."""
    lay = SessionLayout(Path(session))
    entry = load_manifest(lay.manifest).sequence(seq)
    out = lay.sequence(entry.name)
    out.root.mkdir(parents=True, exist_ok=True)
    sm = StageManifest(out.manifest, "sequence", cfg, root=lay.root, inputs=[
        p for v in VIEWS for p in (entry.views[v].capture, entry.views[v].keypoints, entry.views[v].masks,
                                   entry.views[v].depth, entry.views[v].body_prior)])
    captures = {v: open_capture(entry.views[v].capture) for v in VIEWS}
    skipped: list[str] = []

    def step(name: str, fp: str) -> bool:
        """True when the step must run (and logs a skip otherwise)."""
        if not force and sm.is_current(name, fp):
            skipped.append(name)
            return False
        return True

    # 1. Sync.
    manual = {v: entry.views[v].sync_frame for v in VIEWS}
    geometric = cfg.sync_without_laser == "geometric"
    fp_sync = fingerprint("sync", STAGE_VERSION, SYNC_RECORD_VERSION, {v: path_fingerprint(captures[v].path) for v in VIEWS},
                          manual, cfg.sync, geometric)
    if step("sync", fp_sync):
        t0 = time.perf_counter()
        events, record = first_record(captures, manual, cfg.sync, geometric, seq=entry.name)
        sheets = []
        for v in VIEWS:
            # The sheet shows the laser event when there is one (what a person confirms), else the
            # manual frame; a view sliced from its first frame has nothing to confirm.
            lz = record["sources"]["laser"]["views"][v]
            ev = (SyncEvent(lz["frame"], lz["confidence"], tuple(lz["dot_xy_before"]) if lz["dot_xy_before"] else None,
                            lz["frames_seen"]) if lz["found"] else events[v] if events[v].method == "manual" else None)
            if ev is None:
                log.warning("%s %s: no laser event; the geometric sync in Stage III decides the offset", entry.name, v)
                continue
            sheets.append(write_contact_sheet(captures[v], ev, out.root / f"sync_{v}.png"))
            lz["contact_sheet"] = sheets[-1].name
            log.info("%s %s: sync frame %d (%s, confidence %.2f); check %s", entry.name, v, ev.frame,
                     ev.method, ev.confidence, sheets[-1])
        write_json(out.sync, record)
        sm.record("sync", fp_sync, [out.sync, *sheets], time.perf_counter() - t0, {
            f"{v}_sync_frame": events[v].frame for v in VIEWS} | {
            f"{v}_sync_confidence": round(events[v].confidence, 3) for v in VIEWS} | {
            "sync_slicing": record["slicing"]["source"]})
    events = events_from_record(json.loads(out.sync.read_text()), out.sync)

    # 2. Slice.
    fp_slice = fingerprint("slice", fp_sync, cfg.fps, cfg.min_overlap_s)
    if step("slice", fp_slice):
        t0 = time.perf_counter()
        maps = slice_views(captures, events, cfg.fps, cfg.min_overlap_s)
        outs = []
        for v in VIEWS:
            vl = out.view(v)
            vl.root.mkdir(parents=True, exist_ok=True)
            write_json(vl.frame_map, frame_map_to_json(maps[v]))
            _write_cameras(vl, captures[v], maps[v])
            outs += [vl.frame_map, vl.cameras]
        T = len(maps[VIEWS[0]].raw_frames)
        sm.record("slice", fp_slice, outs, time.perf_counter() - t0, {
            "frames": T, "fps": maps[VIEWS[0]].fps,
            **{f"{v}_dropped_frames": int(maps[v].dropped.sum()) for v in VIEWS}})
    maps = {v: frame_map_from_json(json.loads(out.view(v).frame_map.read_text()), out.view(v).frame_map) for v in VIEWS}
    T = len(maps[VIEWS[0]].raw_frames)

    # 3. Keypoints and the performer's identity.
    fp_kp = fingerprint("keypoints", fp_slice, cfg.keypoints, cfg.detector, cfg.keypoints_model, cfg.detector_model,
                        cfg.tracking, {v: path_fingerprint(entry.views[v].keypoints) if entry.views[v].keypoints else None
                                       for v in VIEWS})
    if step("keypoints", fp_kp):
        t0 = time.perf_counter()
        figs = _keypoints_step(cfg, entry, captures, maps, out)
        sm.record("keypoints", fp_kp, [out.view(v).keypoints for v in VIEWS], time.perf_counter() - t0, figs)

    # 4. Masks, depth, body prior (per view; each its own step so a change redoes only it).
    for v in VIEWS:
        vl, view, cap, fm = out.view(v), entry.views[v], captures[v], maps[v]
        if cfg.masks != "none":
            fp = fingerprint("masks", fp_kp, cfg.masks, cfg.masks_model, path_fingerprint(view.masks) if view.masks else None)
            if step(f"masks_{v}", fp):
                t0 = time.perf_counter()
                missing = _masks_step(cfg, view, cap, fm, vl)
                sm.record(f"masks_{v}", fp, [vl.masks], time.perf_counter() - t0, {f"{v}_frames_missing_mask": missing})
        fp = fingerprint("depth", fp_slice, cfg.depth, cfg.depth_model, cfg.min_depth_confidence,
                         path_fingerprint(view.depth) if view.depth else None)
        if step(f"depth_{v}", fp):
            t0 = time.perf_counter()
            missing = _depth_step(cfg, view, cap, fm, vl)
            sm.record(f"depth_{v}", fp, [vl.depth], time.perf_counter() - t0, {f"{v}_frames_missing_depth": missing})
        if cfg.body_prior != "none" and view.body_prior is not None:
            fp = fingerprint("body_prior", fp_slice, path_fingerprint(view.body_prior))
            if step(f"body_prior_{v}", fp):
                t0 = time.perf_counter()
                missing = _body_prior_step(view, fm, vl)
                sm.record(f"body_prior_{v}", fp, [vl.body_prior], time.perf_counter() - t0,
                          {f"{v}_frames_missing_body_prior": missing})

    if skipped:
        log.info("sequence %s: up to date, skipped: %s", entry.name, ", ".join(skipped))
    return SequenceOutputs(entry.name, out, sm.figures(), tuple(skipped))


# ------------------------------------------------------------------------------------------------
# steps


def _write_cameras(vl: ViewLayout, cap: Capture, fm: FrameMap) -> None:
    """Intrinsics and the VIO poses of the sliced frames (nearest tracked pose by frame index)."""
    traj = cap.trajectory
    row = np.searchsorted(traj.frame_ids, fm.raw_frames)
    row = np.clip(row, 0, len(traj) - 1)
    untracked = traj.frame_ids[row] != fm.raw_frames
    if untracked.any():
        log.warning("%s: %d sliced frames have no pose of their own; the nearest pose is used",
                    cap.path, int(untracked.sum()))
    K, Kd = cap.rgb_intrinsics, cap.depth_intrinsics
    write_cameras(vl.cameras, CameraFile(
        version=np.int64(1), K=K.K, width=np.int64(K.width), height=np.int64(K.height),
        K_depth=Kd.K, depth_width=np.int64(Kd.width), depth_height=np.int64(Kd.height),
        T_world_cam=traj.T_world_cam[row], raw_frames=fm.raw_frames, timestamps_s=fm.seq_times_s,
        frame_times_s=_frame_times(cap, fm), untracked=untracked, fps=np.float64(fm.fps)))


def _frame_times(cap: Capture, fm: FrameMap) -> np.ndarray:
    """(T,) each sliced raw frame's own time after the view's event frame, seconds (equal to the
    sequence times unless frames were dropped or the rates differ): what sub-frame sync resamples on."""
    ts = np.asarray(cap.timestamps_s, dtype=np.float64)
    if len(ts) < cap.num_frames or cap.num_frames == 0:
        return np.asarray(fm.seq_times_s, dtype=np.float64)
    return ts[fm.raw_frames] - ts[fm.event_frame]


def _chunks(n: int, size: int):
    for s in range(0, n, size):
        yield np.arange(s, min(n, s + size))


def _keypoints_step(cfg: SequenceConfig, entry: SequenceEntry, captures, maps, out: SequenceLayout) -> dict:
    """Every person per frame -> tracks -> the performer (one identity, consistent across views)."""
    people, tracks, layouts = {}, {}, {}
    figs: dict = {}
    for v in VIEWS:
        fm, cap = maps[v], captures[v]
        people[v], missing, layouts[v] = _all_people(cfg, entry.views[v], cap, fm)
        tracks[v] = track_people(people[v], (cap.rgb_intrinsics.width, cap.rgb_intrinsics.height), cfg.tracking)
        figs[f"{v}_frames_missing_keypoint_file"] = missing
        if missing:
            log.warning("%s %s: %d of %d frames have no keypoint file (kept as zero confidence)",
                        entry.name, v, missing, len(fm.raw_frames))
    T = len(maps[VIEWS[0]].raw_frames)
    frames = np.arange(T)
    sizes = {v: (captures[v].rgb_intrinsics.width, captures[v].rgb_intrinsics.height) for v in VIEWS}
    best = select_performer_two_views(tracks["v1"], tracks["v2"], frames, frames, sizes["v1"], sizes["v2"], T, T)
    for v, track in zip(VIEWS, best):
        kp, boxes = performer_keypoints(track, T)
        seen = kp[..., 2].max(axis=1) > 0
        frac = float(seen.mean()) if T else 0.0
        gap = _longest_run(~seen) / maps[v].fps
        if frac < cfg.min_person_fraction:
            raise InputError(captures[v].path, f"the performer is seen in only {100 * frac:.0f}% of the "
                             f"{T} sliced frames of view {v}",
                             "check the view's keypoint folder / detector, or the sync frames")
        if gap > cfg.long_gap_s:
            log.warning("%s %s: no performer for %.1f s in a row (longest gap)", entry.name, v, gap)
        conf = kp[..., 2][seen]
        write_keypoints2d(out.view(v).keypoints, Keypoints2DFile(
            version=np.int64(1), keypoints=kp, boxes=boxes, raw_frames=maps[v].raw_frames, seen=seen,
            track_id=np.int64(track.track_id if track else -1), layout=np.array(layouts[v])))
        figs.update({
            f"{v}_frames_with_person": int(seen.sum()),
            f"{v}_mean_keypoint_confidence": round(float(conf.mean()) if conf.size else 0.0, 4),
            f"{v}_longest_gap_s": round(gap, 2),
            f"{v}_tracks": len(tracks[v]),
        })
    return figs


def _all_people(cfg: SequenceConfig, view, cap: Capture, fm: FrameMap) -> tuple[list[np.ndarray], int, str]:
    """Per sliced frame, (N, 17, 3) keypoints of everyone the backend sees; missing files; the
    layout of the detector that produced them (its hip definition matters to Stage IV)."""
    if cfg.keypoints == "precomputed":
        if view.keypoints is None:
            raise InputError(cap.path, "keypoints = precomputed but the view names no keypoint folder",
                             "add `keypoints = \"...\"` for the view in session.toml, or pick a model backend")
        from embodmocap.perception.precomputed import PrecomputedKeypoints

        src = PrecomputedKeypoints(view.keypoints)
        people = src.read(fm.raw_frames)
        return people, len(src.missing_frames), src.layout or "COCO17"
    detector, estimator = _model_backends(cfg, view)
    people = []
    for idx in _chunks(len(fm.raw_frames), cfg.batch_size):
        ids = [int(i) for i in fm.raw_frames[idx]]
        frames = [cap.frames.rgb(i) for i in ids]
        boxes = detector.detect(frames, ids)
        kps = estimator.estimate(frames, ids, [b[:, :4] for b in boxes])
        people += [np.asarray(k, dtype=np.float64).reshape(-1, 17, 3) for k in kps]
    return people, 0, "COCO17"


def _model_backends(cfg: SequenceConfig, view):
    if cfg.keypoints == "mediapipe" or cfg.detector == "mediapipe":
        from embodmocap.perception.mediapipe_backend import MediaPipePose

        mp = MediaPipePose()
    if cfg.detector == "precomputed":
        from embodmocap.perception.precomputed import PrecomputedDetector

        if view.keypoints is None:
            raise InputError(None, "detector = precomputed needs the view's keypoint folder", "pick detector = rtdetr or mediapipe")
        detector = PrecomputedDetector(view.keypoints)
    elif cfg.detector == "rtdetr":
        from embodmocap.perception.hf_backends import make_backend

        detector = make_backend("detector", "rtdetr", model=cfg.detector_model, device=cfg.device)
    else:
        detector = mp
    if cfg.keypoints == "vitpose":
        from embodmocap.perception.hf_backends import make_backend

        estimator = make_backend("keypoints", "vitpose", model=cfg.keypoints_model, device=cfg.device)
    else:
        estimator = mp
    return detector, estimator


def _masks_step(cfg: SequenceConfig, view, cap: Capture, fm: FrameMap, vl: ViewLayout) -> int:
    """Person masks of the sliced frames (bit-packed stack, ``io.frame_stack``); returns frames missing."""
    size = (cap.rgb_intrinsics.width, cap.rgb_intrinsics.height)
    boxes = read_keypoints2d(vl.keypoints).boxes
    if cfg.masks == "precomputed":
        if view.masks is None:
            raise InputError(cap.path, "masks = precomputed but the view names no mask folder",
                             "add `masks = \"...\"` for the view in session.toml, or use --masks none")
        from embodmocap.perception.precomputed import PrecomputedMasks

        backend = PrecomputedMasks(view.masks)
    elif cfg.masks == "sam2":
        from embodmocap.perception.hf_backends import make_backend

        backend = make_backend("masks", "sam2", model=cfg.masks_model, device=cfg.device)
    else:
        from embodmocap.perception.mediapipe_backend import MediaPipePose

        backend = MediaPipePose()
    T, W, H = len(fm.raw_frames), size[0], size[1]
    with write_stack(vl.masks, (T, H, (W + 7) // 8), np.uint8) as stack:

        def write(t: int, m) -> None:
            stack[t] = pack_mask(m)

        if cfg.masks == "precomputed":
            # No pixels needed: read and pack each frame on a worker thread (OpenCV releases the
            # GIL while decoding, so both cores work).
            _parallel(lambda t: write(t, backend.mask(int(fm.raw_frames[t]), size)), range(T))
        else:
            for idx in _chunks(T, cfg.batch_size):
                ids = [int(i) for i in fm.raw_frames[idx]]
                masks = backend.segment([cap.frames.rgb(i) for i in ids], ids, boxes[idx])
                for t, m in zip(idx, masks):
                    write(t, m)
    return len(getattr(backend, "missing_frames", []))


def _parallel(fn, items) -> None:
    """Run ``fn`` on every item with two threads (this machine's cores); errors propagate. Each
    item's result is written to disk by ``fn`` itself, so memory does not grow with the items."""
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(2) as pool:
        for _ in pool.map(fn, items):
            pass


def _depth_step(cfg: SequenceConfig, view, cap: Capture, fm: FrameMap, vl: ViewLayout) -> int:
    """Depth of the sliced frames (uint16 mm stack, ``io.frame_stack``); returns frames with no valid depth."""
    refiner = None
    if cfg.depth == "precomputed":
        if view.depth is None:
            raise InputError(cap.path, "depth = precomputed but the view names no depth folder",
                             "add `depth = \"...\"` for the view in session.toml, or use --depth lidar")
        from embodmocap.perception.precomputed import PrecomputedDepth

        src = PrecomputedDepth(view.depth)
    elif cfg.depth == "promptda":
        from embodmocap.perception.depth_refine import make_depth_refiner

        refiner = make_depth_refiner("promptda", model=cfg.depth_model, device=cfg.device, output="rgb")
    def lidar(i: int) -> np.ndarray:
        d = cap.frames.depth_m(i)
        c = cap.frames.confidence(i)
        if c is not None:
            d = np.where(c >= cfg.min_depth_confidence, d, 0.0)
        return np.nan_to_num(d.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)

    T = len(fm.raw_frames)
    first = src.depth(int(fm.raw_frames[0])) if cfg.depth == "precomputed" else lidar(int(fm.raw_frames[0]))
    if refiner is not None:
        shape = (cap.rgb_intrinsics.height, cap.rgb_intrinsics.width)
    else:
        shape = first.shape
    empty = np.zeros(T, dtype=bool)
    with write_stack(vl.depth, (T,) + tuple(shape), np.uint16) as stack:

        def write(t: int, d: np.ndarray) -> None:
            if d.shape != stack.shape[1:]:
                raise InputError(cap.path, f"depth of raw frame {int(fm.raw_frames[t])} is {d.shape[1]}x{d.shape[0]}, "
                                 f"expected {stack.shape[2]}x{stack.shape[1]}", "all depth maps of a view must share one size")
            stack[t] = depth_mm(d)
            empty[t] = not np.any(stack[t])

        if refiner is None:
            read = (lambda i: src.depth(i)) if cfg.depth == "precomputed" else lidar
            _parallel(lambda t: write(t, read(int(fm.raw_frames[t]))), range(T))
        else:
            for idx in _chunks(T, cfg.batch_size):
                ids = [int(i) for i in fm.raw_frames[idx]]
                depths = refiner.refine([cap.frames.rgb(i) for i in ids], [lidar(i) for i in ids])
                for t, d in zip(idx, depths):
                    write(t, d)
    return int(empty.sum())


def _body_prior_step(view, fm: FrameMap, vl: ViewLayout) -> int:
    from embodmocap.perception.precomputed import PrecomputedBodyPrior

    src = PrecomputedBodyPrior(view.body_prior)
    prior, found = src.take(fm.raw_frames)
    # Re-index by sequence frame; rows absent from the file are zeros and counted.
    seq = BodyPriorSeq(prior.global_orient_cam, prior.body_pose, prior.betas, prior.transl_cam,
                       np.arange(len(fm.raw_frames)))
    write_body_prior(vl.body_prior, seq)
    return int((~found).sum())


def _longest_run(mask: np.ndarray) -> int:
    """Length of the longest run of True values."""
    if not mask.any():
        return 0
    padded = np.concatenate([[0], mask.astype(np.int8), [0]])
    d = np.diff(padded)
    return int((np.nonzero(d == -1)[0] - np.nonzero(d == 1)[0]).max())
