"""``sync.json``: every sync source of a sequence, their agreement, and the offset chosen (and why).

Offsets are between the two views' own clocks: ``offset_s = t_v2 - t_v1`` for the same instant,
where ``t_v`` is the timestamp of the view's raw frames. The record is written in two steps:

1. Stage II (:func:`first_record`): each view's laser event (or why none was found), the manual
   frames of session.toml, and the frames the sequence was sliced at (``views``: manual frames,
   else laser events, else each view's first frame when a view has no laser event and the
   geometric sync is on). ``chosen`` then holds that provisional choice with ``final: false``.
2. Stage III (:func:`decide`): the geometric offset from the registered cameras and the keypoints,
   its agreement with the laser, and the final choice. ``chosen.residual_s`` is what Stage IV
   applies on top of the slicing: view 2's observations are resampled at view 1's instants
   shifted by it (sub-frame sync, :mod:`embodmocap.sequence.subframe`).

Rules of the choice: manual frames (``sync_frame`` in session.toml, both views) always win; with
laser and geometric both available, ``prefer = auto`` takes the geometric offset when the two agree
within ``agree_frames`` (same event, sub-frame precision) and otherwise the more confident one,
with a warning naming both numbers and the contact sheets; without a laser event the geometric
offset is used when confident enough, else Stage III stops with an error asking for sync frames.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Mapping

import numpy as np

from embodmocap.errors import InputError
from embodmocap.sequence.geosync import GeoSyncConfig, GeoSyncResult
from embodmocap.sequence.laser_check import DotCheck
from embodmocap.sequence.sync import SyncConfig, SyncEvent, detect_laser_event
from embodmocap.types import Capture

log = logging.getLogger(__name__)

SYNC_RECORD_VERSION = 2


def _clock(cap: Capture) -> np.ndarray:
    ts = np.asarray(cap.timestamps_s, dtype=np.float64)
    if len(ts) >= cap.num_frames and cap.num_frames > 0:
        return ts[: cap.num_frames]
    return np.arange(cap.num_frames) / (cap.fps if cap.fps > 0 else 30.0)


def first_record(captures: Mapping[str, Capture], manual: Mapping[str, int | None], cfg: SyncConfig,
                 geometric: bool, seq: str = "<seq>") -> tuple[dict[str, SyncEvent], dict]:
    """Stage II's sync: laser per view, manual frames, and the events the views are sliced at.

    Args:
        captures: view name -> capture.
        manual: view name -> ``sync_frame`` from session.toml (None: not given).
        cfg: laser detector settings.
        geometric: the geometric sync will run in Stage III (then a missing laser event is not an
            error: both views are sliced from their first frame and Stage III finds the offset).
        seq: sequence name for messages.

    Returns:
        ``(events, record)``: the slicing event per view and the JSON record (module docstring).

    Raises:
        InputError: a manual frame outside its capture; or no laser event in a view, no manual
            frame, and ``geometric`` off.
    """
    views = list(captures)
    if len(views) == 1:
        return one_view_record(captures, manual, cfg, seq)
    laser: dict[str, dict] = {}
    laser_ev: dict[str, SyncEvent] = {}
    for v, cap in captures.items():
        frame = manual.get(v)
        if frame is not None and not 0 <= int(frame) < cap.num_frames:
            raise InputError(cap.path, f"sync_frame = {frame} of view {v} is outside the capture's {cap.num_frames} frames",
                             f"give a frame in 0..{cap.num_frames - 1} under [sequences.{seq}.views.{v}] in session.toml")
        ev = detect_laser_event(cap, cfg)
        if ev is None:
            laser[v] = {"found": False, "reason": f"no laser-dot event in the first {cfg.search_s:g} s"}
        else:
            laser_ev[v] = ev
            laser[v] = {"found": True, "frame": ev.frame, "time_s": float(_clock(cap)[ev.frame]),
                        "confidence": round(float(ev.confidence), 4),
                        "dot_xy_before": None if ev.dot_xy_before is None else list(ev.dot_xy_before),
                        "frames_seen": ev.frames_seen}
    laser_offset = (laser[views[1]]["time_s"] - laser[views[0]]["time_s"]) if len(laser_ev) == len(views) else None
    sources: dict = {"laser": {"views": laser, "offset_s": laser_offset}}
    warnings: list[str] = []
    if all(manual.get(v) is not None for v in views):
        man = {v: int(manual[v]) for v in views}
        events = {v: SyncEvent(man[v], 1.0, None, 0, "manual") for v in views}
        sources["manual"] = {"frames": man, "offset_s": float(_clock(captures[views[1]])[man[views[1]]]
                                                               - _clock(captures[views[0]])[man[views[0]]])}
        how, reason = "manual", "sync_frame given in session.toml for every view"
    elif any(manual.get(v) is not None for v in views):
        missing = [v for v in views if manual.get(v) is None]
        raise InputError(captures[missing[0]].path, f"sync_frame is given for some views but not for {', '.join(missing)}",
                         f"give sync_frame for every view of sequence {seq} in session.toml, or for none")
    elif laser_offset is not None:
        events = dict(laser_ev)
        how, reason = "laser", "laser-dot event found in every view"
    elif geometric:
        events = {v: SyncEvent(0, 0.0, None, 0, "auto") for v in views}
        lost = ", ".join(v for v in views if not laser[v]["found"])
        how, reason = "start", f"no laser event in {lost}: sliced from each view's first frame; Stage III finds the offset geometrically"
        warnings.append(f"{seq}: {reason}")
    else:
        v = next(v for v in views if not laser[v]["found"])
        raise InputError(captures[v].path, f"no laser-dot sync event found in the first {cfg.search_s:g} s of view {v}",
                         f"find the first frame without the laser dot in the video and set sync_frame = N under "
                         f"[sequences.{seq}.views.{v}] in session.toml (or turn the geometric sync on)")
    slice_offset = float(_clock(captures[views[1]])[events[views[1]].frame] - _clock(captures[views[0]])[events[views[0]].frame])
    record = {
        "version": SYNC_RECORD_VERSION,
        # The frames the sequence was sliced at (what older readers call the sync frames).
        "views": {v: {"frame": events[v].frame, "confidence": events[v].confidence,
                      "dot_xy_before": None if events[v].dot_xy_before is None else list(events[v].dot_xy_before),
                      "frames_seen": events[v].frames_seen, "method": how, "time_s": float(_clock(captures[v])[events[v].frame])}
                  for v in views},
        "slicing": {"source": how, "offset_s": slice_offset},
        "sources": sources,
        "agreement": None,
        "chosen": {"source": how, "offset_s": slice_offset, "residual_s": 0.0, "residual_frames": 0.0,
                   "reason": reason, "final": False},
        "warnings": warnings,
    }
    return events, record


def events_from_record(record: dict, path: str | Path | None = None) -> dict[str, SyncEvent]:
    """The slicing events of a version-1 or version-2 ``sync.json``."""
    fix = "delete the file to redo the sync (embodmocap sequence)"
    if not isinstance(record, dict) or record.get("version") not in (1, SYNC_RECORD_VERSION) \
            or not isinstance(record.get("views"), dict):
        raise InputError(path, f"not a version-1 or -{SYNC_RECORD_VERSION} sync file", fix)
    out = {}
    try:
        for v, d in record["views"].items():
            xy = d.get("dot_xy_before")
            method = d.get("method", "auto")
            out[v] = SyncEvent(int(d["frame"]), float(d["confidence"]), None if xy is None else (float(xy[0]), float(xy[1])),
                               int(d.get("frames_seen", 0)), "manual" if method == "manual" else "auto")
    except (KeyError, TypeError, ValueError, IndexError) as err:
        raise InputError(path, f"malformed sync entry: {err}", fix) from err
    return out


def residual_s(record: dict) -> float:
    """The offset Stage IV applies on top of the slicing, seconds (0 for version-1 files)."""
    if record.get("version") != SYNC_RECORD_VERSION:
        return 0.0
    r = record.get("chosen", {}).get("residual_s", 0.0)
    return float(r) if r is not None and math.isfinite(float(r)) else 0.0


def decide(record: dict, geo: GeoSyncResult | None, cfg: GeoSyncConfig, fps: float,
           sheets: Mapping[str, str] | None = None, seq: str = "<seq>", dot_check: DotCheck | None = None) -> dict:
    """Stage III's final choice: add the geometric source, the agreement and ``chosen``.

    Args:
        record: Stage II's record (:func:`first_record`), not modified.
        geo: the geometric result relative to the slicing (None: not run).
        cfg: choice settings (``prefer``, ``agree_frames``, ``min_confidence``).
        fps: sequence frame rate (frames in messages).
        sheets: view -> contact sheet path, named in the disagreement warning.
        dot_check: whether the views' laser sightings are one place in the world
            (:func:`embodmocap.sequence.laser_check.check_same_dot`); when they are not, the laser
            offset is recorded but not chosen.

    Returns:
        A new record with ``sources.geometric``, ``agreement``, ``chosen`` (``final: true``) and
        the warnings.

    Raises:
        InputError: nothing usable: no laser event, no manual frames and no confident geometric
            offset.
    """
    rec = {k: (dict(v) if isinstance(v, dict) else v) for k, v in record.items()}
    rec["sources"] = dict(record["sources"])
    warnings = [w for w in record.get("warnings", [])]
    slicing = float(record["slicing"]["offset_s"])
    laser_offset = record["sources"]["laser"].get("offset_s")
    names = ", ".join(str(p) for p in (sheets or {}).values())
    laser_rejected = False
    if dot_check is not None and laser_offset is not None:
        # Beside the sources, not inside Stage II's laser source (which Stage III's fingerprint reads).
        rec["laser_dot_check"] = dot_check.to_json()
        if dot_check.same_dot is False:
            # Two different spots went out of sight: the frames are not one instant, so the laser
            # offset is kept in the record but takes no part in the choice.
            warnings.append(f"{seq}: the two views' laser events are {dot_check.gap_m:.2f} m apart on the wall "
                            f"(measured by {dot_check.method}; one dot is within {dot_check.limit_m:g} m): at least one "
                            f"view took something else for the dot, so the laser offset is not used; check the "
                            f"contact sheets {names} and set sync_frame in session.toml if a view's laser frame is right")
            laser_offset, laser_rejected = None, True
    geo_ok = geo is not None and geo.found
    geo_offset = slicing + geo.offset_s if geo_ok else None
    if geo is not None:
        rec["sources"]["geometric"] = {**geo.to_json(), "offset_s": geo_offset,
                                       "residual_s": geo.offset_s if geo_ok else None,
                                       "trusted": bool(geo_ok and geo.confidence >= cfg.min_confidence)}
    trusted = geo_ok and geo.confidence >= cfg.min_confidence
    agreement = None
    if geo_ok and laser_offset is not None:
        diff = (geo_offset - laser_offset) * fps
        agreement = {"laser_minus_geometric_frames": round(-diff, 4), "agree": abs(diff) <= cfg.agree_frames,
                     "limit_frames": cfg.agree_frames}
        if abs(diff) > cfg.agree_frames:
            warnings.append(f"{seq}: laser and geometric sync disagree by {abs(diff):.2f} frames: laser offset "
                            f"{laser_offset * fps:+.2f} frames ({laser_offset:+.4f} s), geometric {geo_offset * fps:+.2f} "
                            f"frames ({geo_offset:+.4f} s, confidence {geo.confidence:.2f}); check the contact sheets "
                            f"{names} and set sync_frame in session.toml if the laser frames are wrong")
    rec["agreement"] = agreement
    how = record["slicing"]["source"]
    if how == "manual":
        offset, source = slicing, "manual"
        reason = "sync_frame in session.toml overrides the automatic sources"
        if geo_ok and abs(geo_offset - slicing) * fps > cfg.agree_frames:
            warnings.append(f"{seq}: the manual sync frames differ from the geometric sync by "
                            f"{abs(geo_offset - slicing) * fps:.2f} frames (manual kept)")
    elif laser_offset is not None and (cfg.prefer == "laser" or not trusted):
        offset, source = laser_offset, "laser"
        reason = ("prefer = laser" if cfg.prefer == "laser" else
                  "geometric sync not confident enough" if geo_ok else
                  "geometric sync not run" if geo is None else f"geometric sync failed: {geo.message}")
    elif laser_offset is not None:
        assert agreement is not None
        if cfg.prefer == "geometric":
            offset, source, reason = geo_offset, "geometric", "prefer = geometric"
        elif agreement["agree"]:
            offset, source = geo_offset, "geometric"
            reason = (f"laser and geometric agree within {cfg.agree_frames:g} frame; geometric kept for its "
                      "sub-frame precision")
        else:
            laser_conf = min(record["sources"]["laser"]["views"][v]["confidence"] for v in record["views"])
            if geo.confidence > laser_conf:
                offset, source = geo_offset, "geometric"
                reason = f"disagreement; geometric more confident ({geo.confidence:.2f} vs laser {laser_conf:.2f})"
            else:
                offset, source = laser_offset, "laser"
                reason = f"disagreement; laser more confident ({laser_conf:.2f} vs geometric {geo.confidence:.2f})"
    elif trusted:
        offset, source = geo_offset, "geometric"
        reason = ("the views' laser events are different spots; geometric sync" if laser_rejected else
                  "no laser event; geometric sync")
    else:
        why = "not run" if geo is None else (geo.message or f"confidence {geo.confidence:.2f} < {cfg.min_confidence}")
        what = (f"the two views' laser events are {dot_check.gap_m:.2f} m apart (not one dot)" if laser_rejected
                else "no laser event")
        raise InputError(None, f"sequence {seq}: {what} and the geometric sync found no reliable offset ({why})",
                         "set sync_frame for both views in session.toml (the first frame without the laser dot)")
    residual = offset - slicing
    rec["chosen"] = {"source": source, "offset_s": float(offset), "residual_s": float(residual),
                     "residual_frames": round(float(residual * fps), 4), "reason": reason, "final": True}
    rec["warnings"] = warnings
    return rec


def one_view_record(captures: Mapping[str, Capture], manual: Mapping[str, int | None], cfg: SyncConfig,
                    seq: str = "<seq>") -> tuple[dict[str, SyncEvent], dict]:
    """:func:`first_record` of a one-phone sequence: nothing to synchronise, so the record is final.

    The sequence starts at the view's ``sync_frame`` when session.toml gives one, else at its
    laser-dot event when it has one (where a take is marked: the same start as a two-phone
    recording of it), else at its first frame. ``chosen.source`` is ``one_view`` with a zero offset,
    ``chosen.final`` is true (Stage III has no offset to decide) and ``one_view`` is true.
    """
    (v, cap), = captures.items()
    frame = manual.get(v)
    if frame is not None and not 0 <= int(frame) < cap.num_frames:
        raise InputError(cap.path, f"sync_frame = {frame} of view {v} is outside the capture's {cap.num_frames} frames",
                         f"give a frame in 0..{cap.num_frames - 1} under [sequences.{seq}.views.{v}] in session.toml")
    ev = detect_laser_event(cap, cfg)
    laser = ({"found": False, "reason": f"no laser-dot event in the first {cfg.search_s:g} s"} if ev is None else
             {"found": True, "frame": ev.frame, "time_s": float(_clock(cap)[ev.frame]),
              "confidence": round(float(ev.confidence), 4),
              "dot_xy_before": None if ev.dot_xy_before is None else list(ev.dot_xy_before), "frames_seen": ev.frames_seen})
    if frame is not None:
        event, how, reason = SyncEvent(int(frame), 1.0, None, 0, "manual"), "manual", "sync_frame given in session.toml"
    elif ev is not None:
        event, how, reason = ev, "laser", "one view: the sequence starts at its laser-dot event"
    else:
        event, how, reason = SyncEvent(0, 0.0, None, 0, "auto"), "start", "one view: the sequence starts at its first frame"
    record = {
        "version": SYNC_RECORD_VERSION,
        "one_view": True,
        "views": {v: {"frame": event.frame, "confidence": event.confidence,
                      "dot_xy_before": None if event.dot_xy_before is None else list(event.dot_xy_before),
                      "frames_seen": event.frames_seen, "method": how, "time_s": float(_clock(cap)[event.frame])}},
        "slicing": {"source": how, "offset_s": 0.0},
        "sources": {"laser": {"views": {v: laser}, "offset_s": None},
                    **({"manual": {"frames": {v: int(frame)}, "offset_s": 0.0}} if frame is not None else {})},
        "agreement": None,
        "chosen": {"source": "one_view", "offset_s": 0.0, "residual_s": 0.0, "residual_frames": 0.0,
                   "reason": f"{reason}; no other view to synchronise with", "final": True},
        "warnings": [],
    }
    return {v: event}, record
