"""Were the two views' laser events the same dot? A check in the scene's world (Stage III).

The laser detector (:mod:`embodmocap.sequence.sync`) works on each view alone, so a speck of wall
texture that goes out of sight in one view, while the other view sees the real dot (or another
speck), gives two "events" that are not the same instant. Once Stage III has put both views in the
scene's world, that is checkable from physics rather than from how the spots look: one laser dot
sits at one place on the wall, so both views' last sightings of it must land on the same world
point, whatever the phones' poses and clocks.

Each view's sighting is the ray through the dot's pixel at the last frame it was seen, from that
frame's camera (the capture's VIO pose taken to the world by Stage III's ``T_world_vio``). Where the
view's depth map has a valid value at the dot, the ray gives a 3D point and the check is the
distance between the two points; otherwise it falls back to the closest approach of the two rays,
which can only show a disagreement (two rays can pass close without meeting at the dot, so a small
ray distance confirms nothing and the check reports it as unconfirmed).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Literal, Mapping

import numpy as np
from numpy.typing import NDArray

from embodmocap.geometry.raycast import pixel_rays
from embodmocap.types import Capture


@dataclass(frozen=True)
class DotSighting:
    """One view's last sighting of its laser dot, in the scene's world (metres, Z up).

    Attributes:
        origin: (3,) camera centre.
        direction: (3,) unit ray through the dot's pixel (OpenCV camera, taken to the world).
        point: (3,) the dot on the wall from the view's own depth, or None (no valid depth there).
    """

    origin: NDArray[np.float64]
    direction: NDArray[np.float64]
    point: NDArray[np.float64] | None


@dataclass(frozen=True)
class DotCheck:
    """Outcome of :func:`check_same_dot`.

    Attributes:
        gap_m: distance between the two sightings: between the depth points (``method = "depth"``)
            or the closest approach of the two rays (``"rays"``); None if not measurable.
        method: how ``gap_m`` was measured (``"none"``: a view had no pose at its sighting).
        limit_m: the largest gap taken as one dot.
        same_dot: False when the gap shows two different places; True when depth points agree;
            None when nothing confirms it (rays that pass close, or no measurement).
    """

    gap_m: float | None
    method: Literal["depth", "rays", "none"]
    limit_m: float
    same_dot: bool | None

    def to_json(self) -> dict:
        return {"gap_m": None if self.gap_m is None else round(self.gap_m, 4), "method": self.method,
                "limit_m": self.limit_m, "same_dot": self.same_dot}


@dataclass(frozen=True)
class DotObservation:
    """What one view's capture says about its last sighting of the dot, before any calibration.

    Attributes:
        K: (3, 3) intrinsics at RGB resolution.
        xy: (2,) the dot's pixel at RGB resolution (pixel centres at integers).
        T_vio_cam: (4, 4) the capture's VIO pose of that frame (camera to the view's VIO world).
        depth_m: z-depth at the dot (median of the valid depth around it), or None.
    """

    K: NDArray[np.float64]
    xy: NDArray[np.float64]
    T_vio_cam: NDArray[np.float64]
    depth_m: float | None


def observe_dot(capture: Capture, frame: int, xy: tuple[float, float], depth_window: int = 2) -> DotObservation | None:
    """Read a view's sighting of its dot at pixel ``xy`` in raw ``frame`` from its capture.

    Args:
        capture: the view's raw capture (its VIO trajectory, intrinsics and depth maps).
        frame: raw video frame of the sighting (the frame before the sync event).
        xy: (x, y) pixel at RGB resolution, pixel centres at integers.
        depth_window: half-size of the depth-map window whose median valid depth is used (a laser
            dot is a few RGB pixels; one depth pixel can be an edge).

    Returns:
        The observation, or None when the capture has no pose at ``frame`` or a neighbour.
    """
    traj = capture.trajectory
    if len(traj.frame_ids) == 0:
        return None
    k = int(np.argmin(np.abs(traj.frame_ids - frame)))
    if abs(int(traj.frame_ids[k]) - frame) > 1:
        return None  # no pose near the sighting: a ray from another moment would be misleading
    rgb, dk = capture.rgb_intrinsics, capture.depth_intrinsics
    depth = np.asarray(capture.frames.depth_m(frame), np.float32)
    # The same pixel at depth resolution (pixel-centre convention, as Intrinsics.scaled).
    ui = int(round((xy[0] + 0.5) * dk.width / rgb.width - 0.5))
    vi = int(round((xy[1] + 0.5) * dk.height / rgb.height - 0.5))
    h, w = depth.shape
    win = depth[max(vi - depth_window, 0): min(vi + depth_window + 1, h), max(ui - depth_window, 0): min(ui + depth_window + 1, w)]
    valid = win[np.isfinite(win) & (win > 0)]
    return DotObservation(K=np.asarray(rgb.K, np.float64), xy=np.asarray(xy, np.float64),
                          T_vio_cam=np.asarray(traj.T_world_cam[k], np.float64),
                          depth_m=float(np.median(valid)) if valid.size else None)


def place_dot(obs: DotObservation | None, T_world_vio: NDArray) -> DotSighting | None:
    """A view's dot observation in the scene's world, given the view's (4, 4) ``T_world_vio``."""
    if obs is None:
        return None
    T_world_cam = np.asarray(T_world_vio, np.float64) @ obs.T_vio_cam
    origin, direction = pixel_rays(obs.K, T_world_cam, obs.xy)
    point = None
    if obs.depth_m is not None:
        # The depth is along the camera's optical axis: scale the unit ray to reach that plane.
        cos = float(direction @ T_world_cam[:3, 2])
        if cos > 1e-6:
            point = origin + direction * (obs.depth_m / cos)
    return DotSighting(origin=np.asarray(origin, np.float64), direction=np.asarray(direction, np.float64), point=point)


def dot_sighting(capture: Capture, frame: int, xy: tuple[float, float], T_world_vio: NDArray) -> DotSighting | None:
    """:func:`observe_dot` then :func:`place_dot`: the world ray (and point) of a view's dot."""
    return place_dot(observe_dot(capture, frame, xy), T_world_vio)


def ray_gap(o1: NDArray, d1: NDArray, o2: NDArray, d2: NDArray) -> float:
    """Closest approach of two rays (metres): origins (3,), unit directions (3,); points behind an
    origin are not on its ray (the distance then comes from the origin)."""
    w = o1 - o2
    b = float(d1 @ d2)
    den = 1.0 - b * b
    if den < 1e-9:  # parallel: distance of o2 from ray 1
        t1, t2 = 0.0, float(w @ d2)
    else:
        t1 = (b * float(w @ d2) - float(w @ d1)) / den
        t2 = (float(w @ d2) - b * float(w @ d1)) / den
    t1, t2 = max(t1, 0.0), max(t2, 0.0)
    return float(np.linalg.norm(o1 + t1 * d1 - (o2 + t2 * d2)))


def check_same_dot(a: DotSighting | None, b: DotSighting | None, limit_m: float) -> DotCheck:
    """Whether two views' sightings can be one laser dot (see the module docstring)."""
    if a is None or b is None:
        return DotCheck(None, "none", limit_m, None)
    if a.point is not None and b.point is not None:
        gap = float(np.linalg.norm(a.point - b.point))
        return DotCheck(gap, "depth", limit_m, gap <= limit_m)
    gap = ray_gap(a.origin, a.direction, b.origin, b.direction)
    return DotCheck(gap, "rays", limit_m, False if gap > limit_m else None)


def observe_laser_dots(record: dict, captures: Mapping[str, Callable[[], Capture]]) -> dict[str, DotObservation | None] | None:
    """Each view's last sighting of its laser dot from a sequence's ``sync.json`` record.

    Args:
        record: the sync record (``sources.laser.views.<v>``: ``found``, ``frame``, ``dot_xy_before``).
        captures: view name -> a function opening the view's raw capture (opened only when both
            views have a laser event).

    Returns:
        View -> observation (None where the capture has no pose there), or None when a view has no
        laser event or no dot position.
    """
    views = record["sources"]["laser"]["views"]
    names = list(record["views"])
    if not all(views.get(v, {}).get("found") and views[v].get("dot_xy_before") is not None for v in names):
        return None
    # The dot was last seen in the frame before the event (the event is the first frame without it).
    return {v: observe_dot(captures[v](), int(views[v]["frame"]) - 1, tuple(views[v]["dot_xy_before"])) for v in names}


def check_laser_dots(observations: Mapping[str, DotObservation | None] | None, T_world_vio: Mapping[str, NDArray],
                     limit_m: float) -> DotCheck | None:
    """The same-dot check of two views' observations (:func:`observe_laser_dots`) placed with
    their ``T_world_vio``; None without observations."""
    if observations is None:
        return None
    a, b = (place_dot(observations[v], T_world_vio[v]) for v in observations)
    return check_same_dot(a, b, limit_m)


def laser_dot_check(record: dict, captures: Mapping[str, Callable[[], Capture]], T_world_vio: Mapping[str, NDArray],
                    limit_m: float) -> DotCheck | None:
    """:func:`observe_laser_dots` then :func:`check_laser_dots`: the same-dot check of a sequence's
    two laser events, or None when the record has no laser event (or dot position) in a view."""
    return check_laser_dots(observe_laser_dots(record, captures), T_world_vio, limit_m)
