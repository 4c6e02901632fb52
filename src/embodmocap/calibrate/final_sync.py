"""Stage III's last step as a pure function: the geometric sync on the refined cameras, the final
choice among the sync sources (with the same-dot check of the laser events), and the per-frame
cameras in the scene's world. Part of :mod:`embodmocap.calibrate.solve` (its step 4), kept apart
for size; like it, no function here takes a path or opens a file.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable, Mapping

import numpy as np
from numpy.typing import NDArray

from embodmocap.calibrate.config import CalibrateConfig
from embodmocap.calibrate.inputs import ViewInputs
from embodmocap.io.layout import VIEWS
from embodmocap.io.stage_files import CameraFile

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GeosyncResult:
    """The geometric sync step's results.

    Attributes:
        record: the final ``sync.json`` (laser, manual and geometric sources, the choice).
        cameras_world: view -> its ``cameras_world.npz`` (scene world, sub-frame offset).
        figures: the stage manifest's figures.
        geometric: the geometric sync (None when disabled).
    """

    record: dict
    cameras_world: dict[str, CameraFile]
    figures: dict
    geometric: object = None


def geometric_sync(cfg: CalibrateConfig, record: dict, views: Mapping[str, ViewInputs], T_world_vio: Mapping[str, NDArray],
                   fps: float, contact_sheets: Mapping[str, str] | None = None, label: str = "",
                   laser_dots: Mapping[str, object] | Callable[[], Mapping[str, object] | None] | None = None, subframe_sync: bool = True,
                   sync_force: bool = False, measure_on: tuple[Mapping[str, ViewInputs], Mapping[str, NDArray]] | None = None
                   ) -> GeosyncResult:
    """With both views in the scene's world (whatever their time offset), the offset at which the
    two views' keypoint rays meet (:mod:`embodmocap.sequence.geosync`); the final choice among
    laser, manual and geometric (:mod:`embodmocap.sequence.sync_record`); the per-frame world
    cameras with the sub-frame offset Stage IV applies.

    Args:
        record: Stage II's ``sync.json`` (version 2); T_world_vio: view -> (4, 4) refined offset;
        fps: the sequence frame rate; contact_sheets: view -> the laser contact sheet's path (text
        for the messages); label: the sequence (log lines); laser_dots: view -> the view's last
        sighting of its laser dot (:func:`embodmocap.sequence.laser_check.observe_laser_dots`,
        or a function returning it, called once the offset is searched; None: no same-dot check); subframe_sync, sync_force: the sequence's session.toml keys
        (:func:`embodmocap.sequence.sync_record.decide`); measure_on: (views, T_world_vio) on
        whose cameras the offset is measured when not those of ``views`` and ``T_world_vio``
        (``CalibrateConfig.sync_cameras = "registration"``: the registration-only cameras); the
        world cameras written are always ``views`` and ``T_world_vio``'s.
    """
    from embodmocap.sequence.geosync import geometric_sync as find_offset
    from embodmocap.sequence.laser_check import check_laser_dots
    from embodmocap.sequence.subframe import frame_times
    from embodmocap.sequence.sync_record import decide, search_half_width_s

    names = [v for v in VIEWS if v in views]
    cams = {v: views[v].cameras for v in names}
    world = {v: T_world_vio[v] @ cams[v]["T_world_cam"] for v in names}
    geo = None
    if len(names) == 1:  # one phone: Stage II's record is final (no other clock to find)
        return _one_view_result(record, cams, world)
    if cfg.geosync.enabled:
        mv, mT = measure_on if measure_on is not None else (views, T_world_vio)
        data = [(cams[v]["K"], mT[v] @ mv[v].cameras["T_world_cam"], views[v].keypoints, frame_times(cams[v], fps))
                for v in names]
        search = search_half_width_s(record, cfg.geosync)
        geo = find_offset(*data[0], *data[1], fps=fps, search_s=search, cfg=cfg.geosync)
        log.info("%s: geometric sync %+.3f frames from the slicing (confidence %.2f, +-%.3f frames)%s", label,
                 geo.offset_frames, geo.confidence, geo.std_frames, f": {geo.message}" if geo.message else "")
    # The laser events as places in the world: one dot is one place in both views.
    if callable(laser_dots):
        laser_dots = laser_dots()
    dot_check = check_laser_dots(laser_dots, T_world_vio, cfg.geosync.laser_dot_agree_m)
    rec = decide(record, geo, cfg.geosync, fps, dict(contact_sheets or {}), label, dot_check, subframe_sync, sync_force)
    cameras_world = {}
    for v in names:
        # time_offset_s: the sub-frame sync Stage IV applies to this view (sync.json's residual).
        cameras_world[v] = CameraFile(
            version=np.int64(1), K=cams[v]["K"], width=cams[v]["width"], height=cams[v]["height"], T_world_cam=world[v],
            raw_frames=cams[v]["raw_frames"], time_offset_s=np.float64(rec["chosen"]["residual_s"] if v == VIEWS[1] else 0.0))
    ch = rec["chosen"]
    figures = {
        "sync_source": ch["source"], "sync_offset_s": round(ch["offset_s"], 6), "sync_residual_frames": ch["residual_frames"],
        "sync_confidence": ch.get("confidence"), "sync_overrides_laser": ch.get("overrides_laser", False),
        "geometric_offset_frames": None if geo is None or not geo.found else round(geo.offset_frames, 4),
        "geometric_confidence": None if geo is None else round(geo.confidence, 3),
        "laser_minus_geometric_frames": (rec["agreement"] or {}).get("laser_minus_geometric_frames"),
        "laser_dot_gap_m": None if dot_check is None or dot_check.gap_m is None else round(dot_check.gap_m, 4),
    }
    return GeosyncResult(rec, cameras_world, figures, geo)


def _one_view_result(record: dict, cams: Mapping, world: Mapping) -> GeosyncResult:
    """A one-phone sequence's step 4: Stage II's final ``sync.json`` kept, the world cameras with
    no time offset."""
    cameras_world = {v: CameraFile(version=np.int64(1), K=cams[v]["K"], width=cams[v]["width"], height=cams[v]["height"],
                                   T_world_cam=world[v], raw_frames=cams[v]["raw_frames"], time_offset_s=np.float64(0.0))
                     for v in cams}
    figures = {"sync_source": record["chosen"]["source"], "sync_offset_s": 0.0, "sync_residual_frames": 0.0,
               "geometric_offset_frames": None, "geometric_confidence": None, "laser_minus_geometric_frames": None,
               "laser_dot_gap_m": None}
    return GeosyncResult(record, cameras_world, figures, None)
