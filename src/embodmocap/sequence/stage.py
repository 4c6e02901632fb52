"""Stage II: synchronised, sliced per-view data with the performer's observations.

``run(config, session, seq)`` reads top to bottom as the recipe:

1. ``sync``: the laser-dot event of each view (session.toml's frames override detection), with a
   contact sheet per view for a person to confirm (``sync.json``, ``sync_<view>.png``). Without a
   laser event the views are sliced from their first frames and Stage III finds the offset from
   the registered cameras and the keypoints (:mod:`embodmocap.sequence.sync_record`);
2. ``slice``: one sequence timeline from the event on, mapped to each view's raw frames through
   timestamps (different rates and dropped frames handled); the view's intrinsics and VIO poses
   for those frames (``<view>/frame_map.json``, ``<view>/cameras.npz``);
3. ``keypoints``: every person's COCO-17 keypoints per frame from the chosen backend
   (:func:`embodmocap.perception.registry.make`), linked into tracks, and the performer's track
   chosen consistently across the views by the pure :func:`~embodmocap.sequence.solve.solve_performer`
   (``<view>/keypoints2d.npz``: keypoints (T, 17, 3) and boxes (T, 4));
4. ``masks``, ``depth``, ``body_prior``: the other observations, per sliced frame.

Frames stream through in chunks, so memory does not grow with the sequence length. Each step is
skipped when its fingerprint matches the manifest and its outputs exist (``StageManifest.step``);
files are written through :mod:`embodmocap.io.stage_files`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from embodmocap.errors import InputError
from embodmocap.geometry.depth_edges import drop_depth_edges
from embodmocap.io.frame_stack import depth_mm, pack_mask, write_stack
from embodmocap.io.body_prior import BodyPriorSeq, write_body_prior
from embodmocap.io.captures import open_capture
from embodmocap.io.layout import SequenceLayout, SessionLayout, ViewLayout
from embodmocap.io.manifest import SequenceEntry, load_manifest
from embodmocap.io.stage_files import (
    CameraFile, FrameMap, Keypoints2DFile, read_frame_map, read_keypoints2d, read_sync, write_cameras, write_frame_map,
    write_keypoints2d, write_sync,
)
from embodmocap.io.stage_manifest import StageManifest, tracked_stage
from embodmocap.perception.registry import make
from embodmocap.sequence.config import SequenceConfig
from embodmocap.sequence.solve import solve_performer
from embodmocap.sequence.slicing import slice_views
from embodmocap.sequence.sync import SyncEvent, write_contact_sheet
from embodmocap.sequence.steps import STEPS
from embodmocap.sequence.sync_record import events_from_record, first_record
from embodmocap.progress import progress
from embodmocap.types import Capture

log = logging.getLogger(__name__)



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
    views = entry.view_names  # ("v1", "v2"), or ("v1",) for a one-phone sequence
    sm = StageManifest(out.manifest, "sequence", cfg, root=lay.root, inputs=[
        p for v in views for p in (entry.views[v].capture, entry.views[v].keypoints, entry.views[v].masks,
                                   entry.views[v].depth, entry.views[v].body_prior)])
    captures = {v: open_capture(entry.views[v].capture) for v in views}
    label = f"sequence {entry.name}"

    # 1. Sync.
    manual = {v: entry.views[v].sync_frame for v in views}
    geometric = cfg.sync_without_laser == "geometric"
    fp_sync = STEPS.fingerprint("sync", cfg, reads={"view captures": {v: Path(captures[v].path) for v in views}},
                                context={"sync_frame": manual})
    with sm.step("sync", fp_sync, force=force, label=label) as step:
        if step.run:
            events, record = first_record(captures, manual, cfg.sync, geometric, seq=entry.name,
                                          min_overlap_s=cfg.min_overlap_s)
            sheets = _contact_sheets(entry.name, captures, events, record, out)
            write_sync(out.sync, record)
            step.record([out.sync, *sheets], {f"{v}_sync_frame": events[v].frame for v in views} | {
                f"{v}_sync_confidence": round(events[v].confidence, 3) for v in views} | {
                "sync_slicing": record["slicing"]["source"], "one_view": entry.one_view})
    events = events_from_record(read_sync(out.sync).record, out.sync)

    # 2. Slice.
    fp_slice = STEPS.fingerprint("slice", cfg, after={"sync": fp_sync})
    with sm.step("slice", fp_slice, force=force, label=label) as step:
        if step.run:
            maps = slice_views(captures, events, cfg.fps, cfg.min_overlap_s)
            outs = []
            for v in views:
                vl = out.view(v)
                vl.root.mkdir(parents=True, exist_ok=True)
                write_frame_map(vl.frame_map, maps[v])
                _write_cameras(vl, captures[v], maps[v])
                outs += [vl.frame_map, vl.cameras]
            step.record(outs, {"frames": len(maps[views[0]].raw_frames), "fps": maps[views[0]].fps,
                               **{f"{v}_dropped_frames": int(maps[v].dropped.sum()) for v in views}})
    maps = {v: read_frame_map(out.view(v).frame_map) for v in views}

    # 3. Keypoints and the performer's identity.
    fp_kp = STEPS.fingerprint("keypoints", cfg, after={"slice": fp_slice},
                              reads={"keypoint folders": {v: entry.views[v].keypoints for v in views}})
    with sm.step("keypoints", fp_kp, force=force, label=label) as step:
        if step.run:
            figs = _keypoints_step(cfg, entry, captures, maps, out)
            step.record([out.view(v).keypoints for v in views], figs)

    # 4. Masks, depth, body prior (per view; each its own step so a change redoes only it).
    for v in views:
        vl, view, cap, fm = out.view(v), entry.views[v], captures[v], maps[v]
        if cfg.masks != "none":
            fp = STEPS.fingerprint("masks", cfg, after={"keypoints": fp_kp}, reads={"mask folder": view.masks})
            with sm.step(f"masks_{v}", fp, force=force, label=label) as step:
                if step.run:
                    step.record([vl.masks], {f"{v}_frames_missing_mask": _masks_step(cfg, view, cap, fm, vl)})
        fp = STEPS.fingerprint("depth", cfg, after={"slice": fp_slice}, reads={"depth folder": view.depth})
        with sm.step(f"depth_{v}", fp, force=force, label=label) as step:
            if step.run:
                step.record([vl.depth], {f"{v}_frames_missing_depth": _depth_step(cfg, view, cap, fm, vl)})
        if cfg.body_prior != "none" and view.body_prior is not None:
            fp = STEPS.fingerprint("body_prior", cfg, after={"slice": fp_slice}, reads={"body prior file": view.body_prior})
            with sm.step(f"body_prior_{v}", fp, force=force, label=label) as step:
                if step.run:
                    step.record([vl.body_prior], {f"{v}_frames_missing_body_prior": _body_prior_step(view, fm, vl)})

    if sm.skipped:
        log.info("%s: up to date, skipped: %s", label, ", ".join(sm.skipped))
    return SequenceOutputs(entry.name, out, sm.figures(), tuple(sm.skipped))


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


def _contact_sheets(name: str, captures, events, record: dict, out: SequenceLayout) -> list[Path]:
    """One contact sheet per view with a laser or manual event (noted in ``record``); their paths."""
    sheets = []
    for v in captures:
        # The sheet shows the laser event when there is one (what a person confirms), else the
        # manual frame; a view sliced from its first frame has nothing to confirm.
        lz = record["sources"]["laser"]["views"][v]
        ev = (SyncEvent(lz["frame"], lz["confidence"], tuple(lz["dot_xy_before"]) if lz["dot_xy_before"] else None,
                        lz["frames_seen"]) if lz["found"] else events[v] if events[v].method == "manual" else None)
        if ev is None:
            if len(captures) > 1:
                log.warning("%s %s: no laser event; the geometric sync in Stage III decides the offset", name, v)
            continue
        sheets.append(write_contact_sheet(captures[v], ev, out.sync_sheet(v)))
        lz["contact_sheet"] = sheets[-1].name
        log.info("%s %s: sync frame %d (%s, confidence %.2f); check %s", name, v, ev.frame,
                 ev.method, ev.confidence, sheets[-1])
    return sheets


def _keypoints_step(cfg: SequenceConfig, entry: SequenceEntry, captures, maps, out: SequenceLayout) -> dict:
    """Every person per frame (the backends) -> the performer (:func:`solve_performer`) -> checks, files."""
    people, layouts, figs = {}, {}, {}
    views = entry.view_names
    for v in views:
        people[v], missing, layouts[v] = _all_people(cfg, entry.views[v], captures[v], maps[v])
        figs[f"{v}_frames_missing_keypoint_file"] = missing
        if missing:
            log.warning("%s %s: %d of %d frames have no keypoint file (kept as zero confidence)",
                        entry.name, v, missing, len(maps[v].raw_frames))
    sizes = {v: (captures[v].rgb_intrinsics.width, captures[v].rgb_intrinsics.height) for v in views}
    found = solve_performer(people, sizes, {v: maps[v].fps for v in views}, cfg.tracking)
    for v in views:
        p, T = found[v], len(maps[v].raw_frames)
        if p.seen_fraction < cfg.min_person_fraction:
            raise InputError(captures[v].path, f"the performer is seen in only {100 * p.seen_fraction:.0f}% of the "
                             f"{T} sliced frames of view {v}",
                             "check the view's keypoint folder / detector, or the sync frames")
        if p.longest_gap_s > cfg.long_gap_s:
            log.warning("%s %s: no performer for %.1f s in a row (longest gap)", entry.name, v, p.longest_gap_s)
        write_keypoints2d(out.view(v).keypoints, Keypoints2DFile(
            version=np.int64(1), keypoints=p.keypoints, boxes=p.boxes, raw_frames=maps[v].raw_frames, seen=p.seen,
            track_id=np.int64(p.track_id), layout=np.array(layouts[v])))
        figs.update(p.figures(v))
    return figs


def _all_people(cfg: SequenceConfig, view, cap: Capture, fm: FrameMap) -> tuple[list[np.ndarray], int, str]:
    """Per sliced frame, (N, 17, 3) keypoints of everyone the backend sees; missing files; the
    layout of the detector that produced them (its hip definition matters to Stage IV)."""
    if cfg.keypoints == "precomputed":
        src = make("keypoints", "precomputed", view, cfg)
        people = src.read(fm.raw_frames)
        return people, len(src.missing_frames), src.layout or "COCO17"
    shared: dict = {}  # one MediaPipe model serves both roles
    detector = make("detector", cfg.detector, view, cfg, shared)
    estimator = make("keypoints", cfg.keypoints, view, cfg, shared)
    people = []
    for idx in progress(list(_chunks(len(fm.raw_frames), cfg.batch_size)), f"{cap.path.name}: people",
                        unit="batch"):
        ids = [int(i) for i in fm.raw_frames[idx]]
        frames = [cap.frames.rgb(i) for i in ids]
        boxes = detector.detect(frames, ids)
        kps = estimator.estimate(frames, ids, [b[:, :4] for b in boxes])
        people += [np.asarray(k, dtype=np.float64).reshape(-1, 17, 3) for k in kps]
    return people, 0, "COCO17"


def _masks_step(cfg: SequenceConfig, view, cap: Capture, fm: FrameMap, vl: ViewLayout) -> int:
    """Person masks of the sliced frames (bit-packed stack, ``io.frame_stack``); returns frames missing."""
    size = (cap.rgb_intrinsics.width, cap.rgb_intrinsics.height)
    boxes = read_keypoints2d(vl.keypoints).boxes
    backend = make("masks", cfg.masks, view, cfg)
    T, W, H = len(fm.raw_frames), size[0], size[1]
    with write_stack(vl.masks, (T, H, (W + 7) // 8), np.uint8) as stack:

        def write(t: int, m) -> None:
            stack[t] = pack_mask(m)

        if cfg.masks == "precomputed":
            # No pixels needed: read and pack each frame on a worker thread (OpenCV releases the
            # GIL while decoding, so both cores work).
            _parallel(lambda t: write(t, backend.mask(int(fm.raw_frames[t]), size)), range(T), f"{cap.path.name}: masks")
        else:
            for idx in progress(list(_chunks(T, cfg.batch_size)), f"{cap.path.name}: masks", unit="batch"):
                ids = [int(i) for i in fm.raw_frames[idx]]
                masks = backend.segment([cap.frames.rgb(i) for i in ids], ids, boxes[idx])
                for t, m in zip(idx, masks):
                    write(t, m)
    return len(getattr(backend, "missing_frames", []))


def _parallel(fn, items, desc: str) -> None:
    """Run ``fn`` on every item with two threads (this machine's cores); errors propagate. Each
    item's result is written to disk by ``fn`` itself, so memory does not grow with the items."""
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(2) as pool:
        for _ in progress(pool.map(fn, items), desc, total=len(items), unit="frame"):
            pass


def _depth_step(cfg: SequenceConfig, view, cap: Capture, fm: FrameMap, vl: ViewLayout) -> int:
    """Depth of the sliced frames (uint16 mm stack, ``io.frame_stack``); returns frames with no valid depth."""
    # lidar: the capture's own depth (confidence-filtered); else a registered depth backend.
    src = make("depth", cfg.depth, view, cfg) if cfg.depth != "lidar" else None
    refiner = src if cfg.depth == "promptda" else None

    def lidar(i: int) -> np.ndarray:
        d = cap.frames.depth_m(i)
        c = cap.frames.confidence(i)
        if c is not None:
            d = np.where(c >= cfg.min_depth_confidence, d, 0.0)
        elif cfg.min_depth_confidence > 0:  # no confidence map: drop what it would have marked low
            return drop_depth_edges(d, cfg.no_confidence_edge_spread)
        return np.nan_to_num(d.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)

    stored_mm = getattr(cap.frames, "depth_mm", None)

    def lidar_mm(i: int) -> np.ndarray:
        """``depth_mm(lidar(i))`` read as integers where the capture stores millimetres (a 16-bit
        PNG): metres x 1000 rounds back to the stored value exactly, so the stack is the same."""
        d = stored_mm(i) if stored_mm is not None else None
        c = cap.frames.confidence(i) if d is not None else None
        if d is None or (c is None and cfg.min_depth_confidence > 0):
            return depth_mm(lidar(i))
        return d if c is None else np.where(c >= cfg.min_depth_confidence, d, np.uint16(0))

    T = len(fm.raw_frames)
    if src is None and cfg.min_depth_confidence > 0 and cap.frames.confidence(int(fm.raw_frames[0])) is None:
        log.info("%s has no LiDAR confidence map: depth edges dropped instead (relative 3x3 spread > %g, "
                 "sequence setting no_confidence_edge_spread)", cap.path.name, cfg.no_confidence_edge_spread)
    first = src.depth_maps(None, [int(fm.raw_frames[0])], None)[0] if cfg.depth == "precomputed" else lidar_mm(int(fm.raw_frames[0]))
    if refiner is not None:
        shape = (cap.rgb_intrinsics.height, cap.rgb_intrinsics.width)
    else:
        shape = first.shape
    empty = np.zeros(T, dtype=bool)
    with write_stack(vl.depth, (T,) + tuple(shape), np.uint16) as stack:

        def write_mm(t: int, mm: np.ndarray) -> None:
            if mm.shape != stack.shape[1:]:
                raise InputError(cap.path, f"depth of raw frame {int(fm.raw_frames[t])} is {mm.shape[1]}x{mm.shape[0]}, "
                                 f"expected {stack.shape[2]}x{stack.shape[1]}", "all depth maps of a view must share one size")
            stack[t] = mm
            empty[t] = not mm.any()

        def write(t: int, d: np.ndarray) -> None:
            write_mm(t, depth_mm(d))

        if cfg.depth == "lidar":
            _parallel(lambda t: write_mm(t, lidar_mm(int(fm.raw_frames[t]))), range(T), f"{cap.path.name}: depth")
        elif refiner is None:
            _parallel(lambda t: write(t, src.depth_maps(None, [int(fm.raw_frames[t])], None)[0]), range(T),
                      f"{cap.path.name}: depth")
        else:
            for idx in progress(list(_chunks(T, cfg.batch_size)), f"{cap.path.name}: depth", unit="batch"):
                ids = [int(i) for i in fm.raw_frames[idx]]
                depths = refiner.depth_maps([cap.frames.rgb(i) for i in ids], ids, [lidar(i) for i in ids])
                for t, d in zip(idx, depths):
                    write(t, d)
    return int(empty.sum())


def _body_prior_step(view, fm: FrameMap, vl: ViewLayout) -> int:
    src = make("body_prior", "precomputed", view)
    prior, found = src.take(fm.raw_frames)
    # Re-index by sequence frame; rows absent from the file are zeros and counted.
    seq = BodyPriorSeq(prior.global_orient_cam, prior.body_pose, prior.betas, prior.transl_cam,
                       np.arange(len(fm.raw_frames)))
    write_body_prior(vl.body_prior, seq)
    return int((~found).sum())
