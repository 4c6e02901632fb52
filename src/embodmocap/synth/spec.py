"""What the synthetic studio's parts agree on: the scene's furniture and the configs.

The scene builder (:mod:`embodmocap.synth.scene`) produces a :class:`SceneSpec`; the performer's
scripted motion (:mod:`embodmocap.synth.motion`) reads the furniture from it so that the body sits
on the chair, steps on the box and leans on the table where they really are. All coordinates are
in the **scene frame**: Z up, metres, floor at z = 0.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class Furniture:
    """An axis-aligned (in its own yaw-rotated frame) box-like piece of furniture.

    Attributes:
        name: ``"chair"``, ``"table"``, ``"sofa"``, ``"bed"``, ``"box"`` ...
        centre_xy: (2,) centre of the footprint on the floor, metres.
        yaw: rotation about +Z in radians; the piece's local +x axis is its "front" (the side a
            person sits facing / stands in front of).
        size: (3,) extent along local x, y and z (full height), metres.
        top_z: height of the surface a person uses (seat for a chair/sofa, top for table/box).
    """

    name: str
    centre_xy: NDArray[np.float64]
    yaw: float
    size: NDArray[np.float64]
    top_z: float

    def front_point(self, distance: float) -> NDArray[np.float64]:
        """(3,) floor point ``distance`` metres in front of the piece's front face."""
        d = np.array([np.cos(self.yaw), np.sin(self.yaw)])
        xy = np.asarray(self.centre_xy) + d * (self.size[0] / 2 + distance)
        return np.array([xy[0], xy[1], 0.0])

    def facing_yaw(self) -> float:
        """Yaw (about +Z) of a person standing at the front and facing *away* from the piece,
        i.e. looking along the piece's local +x (how one turns before sitting down)."""
        return float(self.yaw)


@dataclass(frozen=True)
class SceneSpec:
    """The built scene: its extent and the furniture the performer interacts with.

    Attributes:
        preset: ``"indoor"`` (a closed room) or ``"outdoor"`` (a yard with a fence, open sky).
        floor_min_xy / floor_max_xy: (2,) walkable floor rectangle (inside the walls), metres.
        wall_height: height of walls (indoor) or fence (outdoor), metres.
        furniture: by name; always holds ``"chair"``, ``"table"``, ``"box"`` and one of
            ``"sofa"`` / ``"bed"``.
        laser_dot: (3,) point on a wall where the laser dot of the sync event shines, metres.
        laser_normal: (3,) unit normal of that wall, pointing into the room.
        walk_area_min_xy / walk_area_max_xy: (2,) free floor rectangle the performer's walking
            path stays in (away from furniture and walls, leaving room for the camera operators).
    """

    preset: Literal["indoor", "outdoor"]
    floor_min_xy: NDArray[np.float64]
    floor_max_xy: NDArray[np.float64]
    wall_height: float
    furniture: dict[str, Furniture]
    laser_dot: NDArray[np.float64]
    laser_normal: NDArray[np.float64]
    walk_area_min_xy: NDArray[np.float64]
    walk_area_max_xy: NDArray[np.float64]
    extras: dict[str, float] = field(default_factory=dict)
