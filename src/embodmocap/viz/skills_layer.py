"""The viewer's skill layer (``embodmocap skills``): each clip's object box drawn as its 12 edges
in the skill's colour, its target as a point, and a clip list in the GUI that moves the timeline
to the chosen clip. Reads ``sequences/<seq>/skills/skills.json`` when it exists."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap.io.layout import SessionLayout

#: The 12 edges of a box as pairs of corner indices (corner order of ``skills.json``).
BOX_EDGES = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4], [0, 4], [1, 5], [2, 6], [3, 7]])

#: Colour of each skill's boxes, 0..255 RGB.
SKILL_RGB: dict[str, tuple[int, int, int]] = {"follow": (40, 120, 220), "sit": (40, 170, 70), "climb": (240, 140, 20),
                                              "lie": (150, 80, 200), "prone": (140, 90, 50), "support": (220, 40, 40)}


def skills_path(session: Path, seq: str) -> Path:
    return SessionLayout(session).sequence(seq).skills_json


def box_segments(clips) -> tuple[NDArray[np.float32], NDArray[np.uint8]]:
    """Line segments (N, 2, 3) of every clip object's box edges and their colours (N, 2, 3)."""
    segs, cols = [], []
    for c in clips:
        if c.object is None:
            continue
        corners = np.asarray(c.object.corners, dtype=np.float32)
        segs.append(corners[BOX_EDGES])
        cols.append(np.broadcast_to(np.array(SKILL_RGB[c.skill], np.uint8), (len(BOX_EDGES), 2, 3)))
    if not segs:
        return np.zeros((0, 2, 3), np.float32), np.zeros((0, 2, 3), np.uint8)
    return np.concatenate(segs), np.concatenate(cols)


def clip_labels(clips, fps: float) -> list[str]:
    """One line per clip for the GUI's clip list: id, frames and seconds."""
    return [f"{c.id}: frames {c.start}-{c.end} ({(c.end - c.start) / fps:.1f} s)" for c in clips]


def add_skills(handle, session: Path) -> None:
    """Add the skill layer and the clip list to a running viewer, if the sequence has clips."""
    from embodmocap.io.stage_files import read_skills

    handle.skills = None
    path = skills_path(session, handle.data.name)
    if not path.is_file():
        return
    sf = read_skills(path)
    handle.skills = sf
    segs, cols = box_segments(sf.clips)
    nodes = {}
    if len(segs):
        nodes["/skills/boxes"] = handle.server.scene.add_line_segments("/skills/boxes", segs, cols, thickness=3.0,
                                                                      thickness_units="screen")
    targets = [(c.target.position, SKILL_RGB[c.skill]) for c in sf.clips if c.target.position is not None]
    if targets:
        nodes["/skills/targets"] = handle.server.scene.add_point_cloud(
            "/skills/targets", np.array([t for t, _ in targets], np.float32), np.array([c for _, c in targets], np.uint8),
            point_size=0.08, point_shape="diamond")
    handle.nodes["skills"] = nodes


def add_clip_list(handle) -> None:
    """A GUI folder listing the clips; choosing one shows its first frame."""
    sf = getattr(handle, "skills", None)
    if sf is None or not sf.clips:
        return
    gui = handle.server.gui
    labels = clip_labels(sf.clips, sf.fps)
    with gui.add_folder("Skill clips"):
        dd = gui.add_dropdown("Clip", options=tuple(labels), initial_value=labels[0])
    dd.on_update(lambda _: handle.set_frame(sf.clips[labels.index(dd.value)].start))
    handle._gui["clips"] = dd
