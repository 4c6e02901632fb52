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

Rules of the choice:

- manual frames (``sync_frame`` in session.toml, both views) give the integer offset; a confident
  geometric sync that agrees with them within ``agree_frames`` adds its sub-frame part (unless
  ``subframe_sync = false``); one that disagrees is a warning naming the view and both frames, and
  beyond ``manual_error_frames`` at ``manual_error_confidence`` an error (``sync_force = true``
  keeps the manual frames);
- a view with several plausible laser events: the pair of events consistent with the other view
  (the views overlap after it) and with a confident geometric sync wins, whichever scored best;
- with laser and geometric both available, ``prefer = auto`` takes the geometric offset when the
  two agree within ``agree_frames`` (same event, sub-frame precision: the residual applied weighs
  the geometric one by its standard error against the frames', :func:`subframe_residual`); when they disagree, the
  geometric offset when it is confident (``override_confidence``) or more confident than the
  laser, else the laser, with a warning naming both numbers and the contact sheets;
- without a laser event the geometric offset is used when confident enough, else Stage III stops
  with an error asking for sync frames.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Mapping

import numpy as np

from embodmocap.errors import InputError
from embodmocap.io.stage_files import SYNC_RECORD_VERSION
from embodmocap.sequence.geosync import GeoSyncConfig, GeoSyncResult
from embodmocap.sequence.laser_check import DotCheck
from embodmocap.sequence.sync import SyncConfig, SyncEvent, detect_laser_candidates, detect_laser_event
from embodmocap.types import Capture

log = logging.getLogger(__name__)


def _clock(cap: Capture) -> np.ndarray:
    ts = np.asarray(cap.timestamps_s, dtype=np.float64)
    if len(ts) >= cap.num_frames and cap.num_frames > 0:
        return ts[: cap.num_frames]
    return np.arange(cap.num_frames) / (cap.fps if cap.fps > 0 else 30.0)


#: Slicing sources whose frames are not taken as simultaneous in both views: ``start`` (a view has
#: no laser event) and ``candidates`` (a view's laser events score alike; Stage III chooses).
UNPAIRED_SLICING = ("start", "candidates")


def _event_json(ev: SyncEvent, clock: np.ndarray) -> dict:
    return {"frame": ev.frame, "time_s": float(clock[ev.frame]), "confidence": round(float(ev.confidence), 4),
            "dot_xy_before": None if ev.dot_xy_before is None else list(ev.dot_xy_before), "frames_seen": ev.frames_seen}


def _laser_pairs(cands: Mapping[str, list[SyncEvent]], clocks: Mapping[str, np.ndarray],
                 min_overlap_s: float) -> list[dict]:
    """Every pair of the two views' laser candidates, best first: its offset, how long the views
    overlap when sliced at it (``feasible``: at least ``min_overlap_s``) and its score (the
    product of the two confidences). Feasible pairs come before infeasible ones."""
    v1, v2 = list(cands)
    pairs = []
    for a in cands[v1]:
        for b in cands[v2]:
            c1, c2 = clocks[v1], clocks[v2]
            overlap = min(c1[-1] - c1[a.frame], c2[-1] - c2[b.frame])
            pairs.append({"frames": {v1: a.frame, v2: b.frame}, "offset_s": float(c2[b.frame] - c1[a.frame]),
                          "score": round(float(a.confidence * b.confidence), 4), "overlap_s": round(float(overlap), 3),
                          "feasible": bool(overlap >= min_overlap_s)})
    pairs.sort(key=lambda p: (not p["feasible"], -p["score"]))
    return pairs


def first_record(captures: Mapping[str, Capture], manual: Mapping[str, int | None], cfg: SyncConfig,
                 geometric: bool, seq: str = "<seq>", min_overlap_s: float = 0.0) -> tuple[dict[str, SyncEvent], dict]:
    """Stage II's sync: laser per view, manual frames, and the events the views are sliced at.

    Every plausible laser event of each view is kept (``sources.laser.views.<v>.candidates``) and
    every pair of them scored (``sources.laser.pairs``): a pair the views would overlap too little
    after is left out (a disappearance late in one view cannot be the other's early one), and
    when two feasible pairs score alike (``cfg.rival_ratio``) the views are sliced at the best one
    with source ``candidates``: Stage III's geometric sync then chooses the pair (:func:`decide`).

    Args:
        captures: view name -> capture.
        manual: view name -> ``sync_frame`` from session.toml (None: not given).
        cfg: laser detector settings.
        geometric: the geometric sync will run in Stage III (then a missing laser event is not an
            error: both views are sliced from their first frame and Stage III finds the offset).
        seq: sequence name for messages.
        min_overlap_s: the shortest common span slicing accepts, seconds (pairs giving less are
            not chosen).

    Returns:
        ``(events, record)``: the slicing event per view and the JSON record (module docstring).

    Raises:
        InputError: a manual frame outside its capture; or no laser event in a view, no manual
            frame, and ``geometric`` off.
    """
    views = list(captures)
    if len(views) == 1:
        return one_view_record(captures, manual, cfg, seq)
    clocks = {v: _clock(captures[v]) for v in views}
    cands = {v: detect_laser_candidates(cap, cfg) for v, cap in captures.items()}
    for v, cap in captures.items():
        frame = manual.get(v)
        if frame is not None and not 0 <= int(frame) < cap.num_frames:
            est = (f"; the laser dot goes out at frame {cands[v][0].frame} (confidence {cands[v][0].confidence:.2f})"
                   if cands[v] else "; no laser event was found in the view to compare")
            raise InputError(cap.path, f"sync_frame = {frame} of view {v} is outside the view's {cap.num_frames} frames{est}",
                             f"give a frame in 0..{cap.num_frames - 1} under [sequences.{seq}.views.{v}] in session.toml")
    pairs = _laser_pairs(cands, clocks, min_overlap_s) if all(cands.values()) else []
    best = pairs[0] if pairs else None
    laser: dict[str, dict] = {}
    laser_ev: dict[str, SyncEvent] = {}
    for v in views:
        if not cands[v]:
            laser[v] = {"found": False, "reason": f"no laser-dot event in the first {cfg.search_s:g} s", "candidates": []}
            continue
        # The view's event in the best pair (its best event when the other view has none).
        ev = next(e for e in cands[v] if best is None or e.frame == best["frames"][v])
        laser_ev[v] = ev
        laser[v] = {"found": True, **_event_json(ev, clocks[v]),
                    "candidates": [_event_json(e, clocks[v]) for e in cands[v]]}
    laser_offset = best["offset_s"] if best is not None else None
    feasible = [p for p in pairs if p["feasible"]]
    ambiguous = len(feasible) > 1 and feasible[1]["score"] >= cfg.rival_ratio * feasible[0]["score"]
    sources: dict = {"laser": {"views": laser, "offset_s": laser_offset, "pairs": pairs[:16], "ambiguous": ambiguous}}
    warnings: list[str] = []
    if best is not None and not best["feasible"]:
        warnings.append(f"{seq}: no pair of laser events leaves the views {min_overlap_s:g} s in common; the best-scoring "
                        "pair is used")
    if all(manual.get(v) is not None for v in views):
        man = {v: int(manual[v]) for v in views}
        events = {v: SyncEvent(man[v], 1.0, None, 0, "manual") for v in views}
        sources["manual"] = {"frames": man, "offset_s": float(clocks[views[1]][man[views[1]]] - clocks[views[0]][man[views[0]]])}
        how, reason = "manual", "sync_frame given in session.toml for every view"
    elif any(manual.get(v) is not None for v in views):
        missing = [v for v in views if manual.get(v) is None]
        raise InputError(captures[missing[0]].path, f"sync_frame is given for some views but not for {', '.join(missing)}",
                         f"give sync_frame for every view of sequence {seq} in session.toml, or for none")
    elif laser_offset is not None and ambiguous and geometric:
        events = dict(laser_ev)
        alike = ", ".join(f"{p['frames'][views[0]]}/{p['frames'][views[1]]} (score {p['score']:.2f})" for p in feasible[:3])
        how = "candidates"
        reason = (f"laser events that score alike (frames {views[0]}/{views[1]}: {alike}): sliced at the best pair; "
                  "Stage III's geometric sync chooses the pair")
        warnings.append(f"{seq}: {reason}")
    elif laser_offset is not None:
        events = dict(laser_ev)
        how, reason = "laser", "laser-dot event found in every view"
        if ambiguous:
            warnings.append(f"{seq}: laser events that score alike and no geometric sync to choose: the best pair is used")
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
    slice_offset = float(clocks[views[1]][events[views[1]].frame] - clocks[views[0]][events[views[0]].frame])
    record = {
        "version": SYNC_RECORD_VERSION,
        # The frames the sequence was sliced at (what older readers call the sync frames).
        "views": {v: {"frame": events[v].frame, "confidence": events[v].confidence,
                      "dot_xy_before": None if events[v].dot_xy_before is None else list(events[v].dot_xy_before),
                      "frames_seen": events[v].frames_seen, "method": how, "time_s": float(clocks[v][events[v].frame])}
                  for v in views},
        "slicing": {"source": how, "offset_s": slice_offset},
        "sources": sources,
        "agreement": None,
        "chosen": {"source": how, "offset_s": slice_offset, "residual_s": 0.0, "residual_frames": 0.0,
                   "reason": reason, "final": False},
        "warnings": warnings,
    }
    return events, record


def search_half_width_s(record: dict, cfg: GeoSyncConfig) -> float:
    """Half-width of the geometric sync's search around the slicing, seconds: ``search_s_without_laser``
    without a laser event; ``search_s`` around manual frames; otherwise ``search_s`` around every
    feasible pair of laser events (so the geometry can tell which pair is right), at most
    ``search_s_without_laser``."""
    if record["slicing"]["source"] == "start":
        return cfg.search_s_without_laser
    if record["slicing"]["source"] == "manual":
        return cfg.search_s
    slicing = float(record["slicing"]["offset_s"])
    far = max((abs(p["offset_s"] - slicing) for p in record["sources"]["laser"].get("pairs", []) if p["feasible"]),
              default=0.0)
    return min(far + cfg.search_s, max(cfg.search_s, cfg.search_s_without_laser))


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


def decide(record: dict, geo: GeoSyncResult | None, cfg: GeoSyncConfig, fps: float,
           sheets: Mapping[str, str] | None = None, seq: str = "<seq>", dot_check: DotCheck | None = None,
           subframe_sync: bool = True, sync_force: bool = False) -> dict:
    """Stage III's final choice: add the geometric source, the agreement and ``chosen``.

    Args:
        record: Stage II's record (:func:`first_record`), not modified.
        geo: the geometric result relative to the slicing (None: not run).
        cfg: choice settings (``prefer``, ``agree_frames``, ``min_confidence``, ...).
        fps: sequence frame rate (frames in messages).
        sheets: view -> contact sheet path, named in the disagreement warning.
        dot_check: whether the views' laser sightings are one place in the world
            (:func:`embodmocap.sequence.laser_check.check_same_dot`); when they are not, the laser
            offset is recorded but not chosen.
        subframe_sync: with manual frames, apply the geometric sync's sub-frame part when it
            agrees with them within ``agree_frames`` (session.toml's ``subframe_sync``).
        sync_force: keep manual frames the geometry contradicts (session.toml's ``sync_force``).

    Returns:
        A new record with ``sources.geometric``, ``agreement``, ``chosen`` (``final: true``, with
        the chosen source's ``confidence``) and the warnings.

    Raises:
        InputError: nothing usable (no laser event, no manual frames and no confident geometric
            offset); or manual frames that a confident geometric sync puts more than
            ``cfg.manual_error_frames`` off, unless ``sync_force``.
    """
    rec = {k: (dict(v) if isinstance(v, dict) else v) for k, v in record.items()}
    rec["sources"] = dict(record["sources"])
    rec["sources"]["laser"] = dict(record["sources"]["laser"])
    warnings = [w for w in record.get("warnings", [])]
    views = list(record["views"])
    slicing = float(record["slicing"]["offset_s"])
    how = record["slicing"]["source"]
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
    laser_conf = (min(record["sources"]["laser"]["views"][v]["confidence"] for v in views)
                  if record["sources"]["laser"].get("offset_s") is not None else None)
    # Several laser events in a view: the pair the geometry agrees with wins (it is consistent with
    # the other view's event and with the cameras), whichever scored best on its own.
    pairs = [p for p in record["sources"]["laser"].get("pairs", []) if p.get("feasible", True)]
    best_pair = pairs[0] if pairs else None
    if trusted and how != "manual" and pairs:
        near = min(pairs, key=lambda p: abs(p["offset_s"] - geo_offset))
        if abs(near["offset_s"] - geo_offset) * fps <= cfg.agree_frames and near is not best_pair:
            f_new, f_old = near["frames"], best_pair["frames"]
            moved = [v for v in views if f_new[v] != f_old[v]]
            rec["sources"]["laser"]["consistent_pair"] = near
            warnings.append(f"{seq}: the laser events at frames " + ", ".join(f"{v} {f_new[v]}" for v in views)
                            + " agree with the geometric sync and were taken over the best-scoring "
                            + ", ".join(f"{v} {f_old[v]}" for v in moved) + f" (check the contact sheets {names})")
            laser_offset, laser_rejected = near["offset_s"], False
            laser_conf = min(laser_conf or 1.0, math.sqrt(near["score"]))
    elif geo_ok and how != "manual" and len(pairs) > 1:
        # Not confident about the offset, the geometry still tells pairs seconds apart: the pair at
        # whose shift the keypoint rays meet clearly better wins.
        costs = [_pair_cost(geo, (p["offset_s"] - slicing) * fps) for p in pairs]
        rec["sources"]["laser"]["pair_costs_px2"] = [None if not math.isfinite(c) else round(c, 3) for c in costs]
        known = [i for i, c in enumerate(costs) if math.isfinite(c)]
        if len(known) > 1:
            i = min(known, key=lambda k: costs[k])
            clear = all(costs[i] <= cfg.pair_cost_ratio * costs[k] for k in known if k != i)
            if laser_rejected and any(pairs[i]["frames"][v] == best_pair["frames"][v] for v in views):
                # The same-dot check put the best pair's two sightings apart: a frame of it is
                # something else taken for the dot, and a pair that shares that frame is no better
                # (an untrusted geometry must not bring it back).
                clear = False
            if clear and pairs[i] is best_pair:
                # The geometry confirms the best-scoring pair: the choice was not blind (no warning).
                rec["sources"]["laser"]["geometry_confirms"] = best_pair["frames"]
            if clear and pairs[i] is not best_pair:
                near = pairs[i]
                f_new, f_old = near["frames"], best_pair["frames"]
                rec["sources"]["laser"]["consistent_pair"] = near
                warnings.append(f"{seq}: the laser events at frames " + ", ".join(f"{v} {f_new[v]}" for v in views)
                                + f" fit the geometry better (reprojection cost {costs[i]:.1f} px^2 against "
                                + ", ".join(f"{costs[k]:.1f}" for k in known if k != i) + ") and were taken over the "
                                + "best-scoring " + ", ".join(f"{v} {f_old[v]}" for v in views if f_new[v] != f_old[v])
                                + f" (check the contact sheets {names})")
                laser_offset, laser_rejected = near["offset_s"], False
                laser_conf = min(laser_conf or 1.0, math.sqrt(near["score"]))
    agreement = None
    if geo_ok and laser_offset is not None:
        diff = (geo_offset - laser_offset) * fps
        agreement = {"laser_minus_geometric_frames": round(-diff, 4), "agree": abs(diff) <= cfg.agree_frames,
                     "limit_frames": cfg.agree_frames}
    rec["agreement"] = agreement
    if how == "manual":
        offset, source, reason, conf = _manual_choice(rec, record, geo, geo_offset, trusted, cfg, fps, seq,
                                                      subframe_sync, sync_force, warnings)
    elif laser_offset is not None and (cfg.prefer == "laser" or not trusted):
        offset, source, conf = laser_offset, "laser", laser_conf
        reason = ("prefer = laser" if cfg.prefer == "laser" else
                  "geometric sync not confident enough" if geo_ok else
                  "geometric sync not run" if geo is None else f"geometric sync failed: {geo.message}")
        if how == "candidates" and not ({"consistent_pair", "geometry_confirms"} & set(rec["sources"]["laser"])):
            warnings.append(f"{seq}: laser events that score alike and no confident geometric sync to choose between "
                            f"them ({reason}): the best-scoring pair is used; check the contact sheets {names}")
    elif laser_offset is not None:
        assert agreement is not None
        if cfg.prefer == "geometric":
            offset, source, conf, reason = geo_offset, "geometric", geo.confidence, "prefer = geometric"
        elif agreement["agree"] and abs(laser_offset - slicing) * fps > 1e-6:
            # A laser pair other than the slicing's: its sub-frame prior is not about this slicing.
            offset, source, conf = geo_offset, "geometric", geo.confidence
            reason = (f"laser and geometric agree within {cfg.agree_frames:g} frame; geometric kept for its "
                      "sub-frame precision")
        elif agreement["agree"]:
            offset, source, conf = _subframe_offset(slicing, geo, fps, cfg), "geometric", geo.confidence
            reason = (f"laser and geometric agree within {cfg.agree_frames:g} frame; geometric kept for its "
                      "sub-frame precision" + (f" (its residual {geo.offset_s * fps:+.3f} +- {geo.std_frames:.3f} frame "
                                               "weighed with the laser frames')" if cfg.subframe_shrink else ""))
        elif geo.confidence >= cfg.override_confidence or geo.confidence > laser_conf:
            offset, source, conf = geo_offset, "geometric", geo.confidence
            reason = (f"laser and geometric disagree; geometric confident ({geo.confidence:.2f}, laser {laser_conf:.2f}) "
                      "and no pair of laser events agrees with it")
        else:
            offset, source, conf = laser_offset, "laser", laser_conf
            reason = f"disagreement; laser more confident ({laser_conf:.2f} vs geometric {geo.confidence:.2f})"
        if not agreement["agree"]:
            diff = abs(agreement["laser_minus_geometric_frames"])
            warnings.append(f"{seq}: laser and geometric sync disagree by {diff:.2f} frames: laser offset "
                            f"{laser_offset * fps:+.2f} frames ({laser_offset:+.4f} s), geometric {geo_offset * fps:+.2f} "
                            f"frames ({geo_offset:+.4f} s, confidence {geo.confidence:.2f}); the {source} offset is used; "
                            f"check the contact sheets {names} and set sync_frame in session.toml if it is wrong")
    elif trusted:
        offset, source, conf = geo_offset, "geometric", geo.confidence
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
                     "residual_frames": round(float(residual * fps), 4), "reason": reason,
                     "confidence": None if conf is None else round(float(conf), 3),
                     "overrides_laser": bool(source == "geometric" and agreement is not None and not agreement["agree"]),
                     "final": True}
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


def subframe_residual(measured_frames: float, std_frames: float) -> float:
    """The sub-frame residual to apply on top of a slicing at laser or manual frames, frames: the
    mean of its distribution given the geometric measurement ``measured_frames`` +- ``std_frames``
    (Gaussian) and what the frames alone say, a triangular spread on (-1, 1) (the event falls
    anywhere within a frame of each view's clock: the difference of two uniform quantisations).
    A precise measurement is kept (0.3 +- 0.05 -> 0.29); an imprecise one is drawn towards the
    frames' 0 (0.3 +- 0.25 -> 0.22), as it should be: the geometric residual's error on the studio's
    in-phase sessions reached twice its standard error before the estimator was fixed."""
    if not (math.isfinite(measured_frames) and math.isfinite(std_frames)):
        return 0.0
    if std_frames <= 1e-6:
        return float(np.clip(measured_frames, -1.0, 1.0))
    r = np.linspace(-1.0, 1.0, 2001)
    w = (1.0 - np.abs(r)) * np.exp(-0.5 * ((r - measured_frames) / std_frames) ** 2)
    total = float(w.sum())
    return float((w * r).sum() / total) if total > 0 else 0.0


def _subframe_offset(slicing: float, geo: GeoSyncResult, fps: float, cfg: GeoSyncConfig) -> float:
    """The offset (s) applied when the geometric sync agrees with laser / manual frames sliced at
    ``slicing`` (:func:`subframe_residual` unless ``cfg.subframe_shrink`` is off)."""
    if not cfg.subframe_shrink:
        return slicing + geo.offset_s
    return slicing + subframe_residual(geo.offset_s * fps, geo.std_frames) / fps


def _pair_cost(geo: GeoSyncResult, shift_frames: float) -> float:
    """The geometric cost curve's lowest value within a frame of ``shift_frames`` (inf if none)."""
    near = np.abs(np.asarray(geo.shifts, dtype=np.float64) - shift_frames) <= 1.0
    c = np.asarray(geo.costs, dtype=np.float64)[near]
    c = c[np.isfinite(c)]
    return float(c.min()) if len(c) else math.inf


def _manual_choice(rec: dict, record: dict, geo: GeoSyncResult | None, geo_offset: float | None, trusted: bool,
                   cfg: GeoSyncConfig, fps: float, seq: str, subframe_sync: bool, sync_force: bool,
                   warnings: list[str]) -> tuple[float, str, str, float]:
    """Manual frames give the integer offset; the geometric sync gives the sub-frame part when it
    agrees with them (``rec["sources"]["manual"]`` records both); a confident contradiction of more
    than ``cfg.manual_error_frames`` is an error unless forced. Returns (offset, source, reason, confidence)."""
    slicing = float(record["slicing"]["offset_s"])
    views = list(record["views"])
    manual = dict(record["sources"].get("manual") or {})
    frames = manual.get("frames") or {v: record["views"][v]["frame"] for v in views}
    diff = (geo_offset - slicing) * fps if geo_offset is not None else None
    manual["geometric_minus_manual_frames"] = None if diff is None else round(float(diff), 4)
    manual["subframe_sync"] = subframe_sync
    offset, reason = slicing, "sync_frame in session.toml overrides the automatic sources"
    applied = False
    if diff is not None and trusted and abs(diff) > cfg.agree_frames:
        v1, v2 = views
        est = frames[v2] + diff
        if trusted and geo.confidence >= cfg.manual_error_confidence and abs(diff) > cfg.manual_error_frames and not sync_force:
            raise InputError(None, f"sequence {seq}: view {v2}'s sync_frame = {frames[v2]} (with view {v1}'s = {frames[v1]}) is "
                             f"{abs(diff):.1f} frames from the geometric sync's estimate, frame {est:.1f} of view {v2} "
                             f"(confidence {geo.confidence:.2f})",
                             f"check the frames on the contact sheets and fix sync_frame under [sequences.{seq}.views.{v2}] "
                             f"in session.toml, or set sync_force = true under [sequences.{seq}] to keep them")
        warnings.append(f"{seq}: view {v2}'s sync_frame = {frames[v2]} (with view {v1}'s = {frames[v1]}) disagrees with the "
                        f"geometric sync's estimate, frame {est:.2f} of view {v2} (confidence {geo.confidence:.2f}), by "
                        f"{abs(diff):.2f} frames; the manual frames are kept without a sub-frame part")
        reason += "; the geometric sync disagrees, no sub-frame part applied"
    elif diff is not None and trusted:  # agree within agree_frames
        if subframe_sync:
            offset, applied = _subframe_offset(slicing, geo, fps, cfg), True
            reason = "sync_frame in session.toml gives the integer frame; the geometric sync its sub-frame part"
        else:
            reason = "sync_frame in session.toml, applied as given (subframe_sync = false)"
    elif diff is not None:
        reason += f"; geometric sync not confident enough ({geo.confidence:.2f}) for the sub-frame part"
    manual["subframe_applied"] = applied
    manual["subframe_frames"] = round(float((offset - slicing) * fps), 4)
    rec["sources"]["manual"] = manual
    return offset, "manual", reason, 1.0
