"""Ground truth for the skill clip tests and benchmark: a scripted studio motion (its clips known),
the studio scene mesh, and the scripted furniture's usable surface as a box. Not a test module."""

from __future__ import annotations

import numpy as np

from embodmocap.skills.boxes import CORNER_SIGNS
from embodmocap.synth.motion import MotionScriptConfig, script_motion
from embodmocap.synth.scene import _piece_parts, build_scene

FPS = 30.0
BETAS = np.array([0.5, -0.3, 0.2, 0.0, 0.1, 0, 0, 0, 0, 0])
ALL_SIX = ("lie", "prone", "follow", "sit", "climb", "support")


def scripted(body, seed: int, interactions=ALL_SIX, seconds: float = 70.0, betas=BETAS):
    """``(built scene, script)`` of a ``seconds`` studio motion in indoor room ``seed``."""
    built = build_scene("indoor", np.random.default_rng(seed))
    script = script_motion(built.spec, body, betas, seconds, FPS, np.random.default_rng(seed),
                           MotionScriptConfig(interactions=tuple(interactions)))
    return built, script


def bed_seeds(n: int, start: int = 0) -> list[int]:
    """The first ``n`` indoor room seeds from ``start`` whose room has a bed (lie / prone need one)."""
    out, s = [], start
    while len(out) < n:
        if "bed" in build_scene("indoor", np.random.default_rng(s)).spec.furniture:
            out.append(s)
        s += 1
    return out


def surface_corners(f, preset: str = "indoor") -> np.ndarray:
    """(8, 3) corners of the usable top of a piece of furniture, from the floor to its top: the
    part whose top is the piece's ``top_z`` less what taller parts (a chair's backrest, a bed's
    headboard) cover of it, in the piece's own frame (x front, y along the wall)."""
    parts = _piece_parts(f.name, np.asarray(f.size), f.top_z, preset)
    tops = [(np.array(c), np.array(s)) for c, s, _ in parts if abs(c[2] + s[2] / 2 - f.top_z) < 1e-6]
    c, s = max(tops, key=lambda cs: cs[1][0] * cs[1][1])
    lo, hi = c[:2] - s[:2] / 2, c[:2] + s[:2] / 2
    for pc, ps, _ in parts:
        pc, ps = np.array(pc), np.array(ps)
        if pc[2] + ps[2] / 2 <= f.top_z + 1e-6:
            continue
        plo, phi = pc[:2] - ps[:2] / 2, pc[:2] + ps[:2] / 2
        if plo[1] <= lo[1] + 1e-6 and phi[1] >= hi[1] - 1e-6:  # spans the width: cuts along x
            lo[0], hi[0] = (max(lo[0], phi[0]), hi[0]) if pc[0] < c[0] else (lo[0], min(hi[0], plo[0]))
        elif plo[0] <= lo[0] + 1e-6 and phi[0] >= hi[0] - 1e-6:  # spans the depth: cuts along y
            lo[1], hi[1] = (max(lo[1], phi[1]), hi[1]) if pc[1] < c[1] else (lo[1], min(hi[1], plo[1]))
    centre_l = (lo + hi) / 2
    size = np.array([hi[0] - lo[0], hi[1] - lo[1], f.top_z])
    cy, sy = np.cos(f.yaw), np.sin(f.yaw)
    R = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1.0]])
    centre = np.array([*(np.asarray(f.centre_xy) + R[:2, :2] @ centre_l), f.top_z / 2])
    return centre + (CORNER_SIGNS * size / 2) @ R.T


def corner_error(found: np.ndarray, truth: np.ndarray) -> float:
    """Largest distance from a true corner to the nearest found corner, metres (the corner order
    of two boxes differs when their axes are swapped or flipped)."""
    d = np.linalg.norm(np.asarray(truth)[:, None] - np.asarray(found)[None], axis=-1)
    return float(d.min(axis=1).max())


def match(truth, found, tol: int, follow_min_frames: int):
    """Pair truth clips with found clips of the same skill whose start and end are within ``tol``
    frames (each found clip used once). Truth follow clips shorter than ``follow_min_frames`` (the
    finder's shortest) are optional: matched if found, not missed if not.

    Returns ``(pairs [(truth, found)], missed truth, extra found)``."""
    used, pairs, missed = set(), [], []
    for t in truth:
        cand = [(max(abs(f.start - t.start), abs(f.end - t.end)), i) for i, f in enumerate(found)
                if i not in used and f.skill == t.skill]
        cand = [ci for ci in cand if ci[0] <= tol]
        if cand:
            i = min(cand)[1]
            used.add(i)
            pairs.append((t, found[i]))
        elif not (t.skill == "follow" and t.end - t.start < follow_min_frames):
            missed.append(t)
    extra = [f for i, f in enumerate(found) if i not in used]
    return pairs, missed, extra
