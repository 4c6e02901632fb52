"""The floor under the fit: feet that the scene says stand on the floor must not sink through it.

Where both views lose a leg (a knee and ankle hidden behind a chair while the performer stands up,
a detector missing both), SMPLify has only the smoothness terms and the priors to place it, and
they happily put the foot 10 cm under the floor (issue 29: ``sim check`` found fits with 5.7 and
12.4 cm of penetration, true fit errors). Stage I knows where the floor is: the dominant low
horizontal plane of its mesh (:func:`embodmocap.geometry.planes.find_floor`, the plane Stage I's
gravity check measures). The fit gets a one-sided term: no cost while the feet are above the
floor, a quadratic one for every centimetre a foot joint goes below its lowest height over it.

The joints are SMPL's ankles and feet (the ball of the foot); their lowest heights above the
floor (:data:`FOOT_CLEARANCE_M`) are what a foot flat on the floor, a heel raised or a foot
turned on its side still keeps, less a margin for Stage I's floor (about a centimetre): the term
never pushes a foot that truly stands on the floor. A foot on a box, a step or a bed is above the
floor and costs nothing; the floor is one plane, so a sloping ground (outdoors) lower than the
plane somewhere would be pushed up there: a floor tilted more than ``max_tilt_deg`` is not used.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch

log = logging.getLogger(__name__)

#: SMPL joints of the feet: left and right ankle, left and right foot (ball of the foot).
FOOT_JOINTS: tuple[int, ...] = (7, 8, 10, 11)
#: The lowest height of each of :data:`FOOT_JOINTS` above the floor it stands on, metres: an
#: ankle is 6-9 cm above the sole standing (SMPL's neutral body), the ball of the foot 2-4 cm;
#: less a margin for the floor plane's error (a centimetre) and a tilted foot.
FOOT_CLEARANCE_M: tuple[float, ...] = (0.04, 0.04, 0.01, 0.01)


def floor_term(joints: torch.Tensor, floor_z: torch.Tensor) -> torch.Tensor:
    """Mean over frames of the summed squared depth of the foot joints below their floor height.

    Args:
        joints: (T, 24, 3) SMPL joints, world metres (Z up).
        floor_z: () the floor's height, world metres.

    Returns:
        () metres^2: 0 while every foot joint is at least its clearance above the floor.
    """
    low = floor_z + torch.as_tensor(FOOT_CLEARANCE_M, dtype=joints.dtype, device=joints.device)
    below = torch.relu(low - joints[:, list(FOOT_JOINTS), 2])
    return (below ** 2).sum(-1).mean()


def scene_floor_z(mesh: Path | None, max_tilt_deg: float, label: str = "") -> float | None:
    """The floor height (world metres) of Stage I's mesh at ``mesh``, or None (with one log line)
    when the mesh has no floor plane or its floor is tilted more than ``max_tilt_deg`` (None when
    ``mesh`` is None: no mesh, or the floor term off).

    The floor of a Z-up mesh is horizontal; its height is taken at the plane's points (the mean of
    its inliers' heights), so a small tilt costs at most tilt x half the room's size."""
    from embodmocap.geometry.planes import find_floor
    from embodmocap.io.mesh_file import read_mesh_ply

    if mesh is None:
        return None
    vertices, faces = read_mesh_ply(mesh)[:2]
    floor = find_floor(np.asarray(vertices, dtype=np.float64), np.asarray(faces))
    if floor is None:
        log.warning("%s: no floor plane in %s; the fit keeps no foot above the floor", label, mesh)
        return None
    if floor.tilt_deg > max_tilt_deg:
        log.warning("%s: the floor of %s is %.1f deg off horizontal (more than %.1f): not used by the fit",
                    label, mesh, floor.tilt_deg, max_tilt_deg)
        return None
    return float(floor.height_m)
