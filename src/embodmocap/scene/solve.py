"""Stage I's decisions as pure functions: a capture and the config in, arrays out.

No function here takes a path, writes a file or touches a manifest: :mod:`embodmocap.scene.stage`
opens the capture, fingerprints each step, calls these and writes what they return. The capture
(:class:`embodmocap.io.captures.Capture`) is the one input object: its frames are read one by one
while fusing, so a long scan never sits in memory whole. :func:`solve` runs the key frames and
the mesh in memory, for tests and scripts. The sparse model stays with the
stage: COLMAP builds it in a database and model folder (:func:`embodmocap.scene.sfm.build_sparse_model`),
and :func:`sfm_images` is its pure part (which key frames, with which poses).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Mapping

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.scene.adjust import carry_drift
from embodmocap.scene.config import SceneConfig
from embodmocap.scene.depth import DepthStats, fusion_frames, prefetch
from embodmocap.scene.keyframes import choose_keyframes, fusion_rows
from embodmocap.scene.mesh import clean_mesh, mesh_stats, simplify_mesh
from embodmocap.scene.tsdf import fuse_open3d

log = logging.getLogger(__name__)

KEYFRAMES_VERSION = 1


@dataclass(frozen=True)
class Keyframes:
    """The key frames of a scene capture (``keyframes.json`` without the capture's path).

    Attributes:
        record: ``version``, ``indoor``, ``frame_ids`` (K,), ``T_world_cam`` (K, 4, 4),
            ``sharpness`` (K,) (-1 where unknown), ``dropped_blurry``, ``excluded_jumps``.
        figures: the stage manifest's figures.
        frames: frame index -> (H, W, 3) uint8 RGB of the key frames decoded while choosing them
            (for :func:`sfm_images`; empty when the blur test did not run).
    """

    record: dict
    figures: dict
    frames: dict = field(default_factory=dict)


def select_keyframes(capture, cfg: SceneConfig, indoor: bool) -> Keyframes:
    """Key frames by camera motion, the blurriest of each small group dropped, frames around
    tracking jumps excluded."""
    frames: dict = {}
    sel = choose_keyframes(capture, cfg, indoor, keep=frames)
    T = capture.trajectory.T_world_cam[sel.rows]
    record = {"version": KEYFRAMES_VERSION, "indoor": indoor, "frame_ids": sel.frame_ids, "T_world_cam": T,
              "sharpness": np.nan_to_num(sel.sharpness, nan=-1.0), "dropped_blurry": sel.dropped_blurry,
              "excluded_jumps": sel.excluded_jumps}
    figures = {"keyframes": len(sel), "keyframes_dropped_blurry": len(sel.dropped_blurry),
               "frames_excluded_jumps": len(sel.excluded_jumps)}
    return Keyframes(record, figures, frames)


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh: (N, 3) vertices (world metres, Z up), (F, 3) faces, (N, 3) colours, and
    the stage manifest's figures of the step that made it."""

    vertices: NDArray
    faces: NDArray
    colors: NDArray
    figures: dict


def fuse_mesh(capture, cfg: SceneConfig, indoor: bool, *, label: str = "", source: object = None,
              drift: dict | None = None) -> Mesh:
    """Every frame with a trusted pose and enough valid depth (a fine motion step, many more than
    the key frames) fused in a TSDF; the colour mesh extracted and cleaned.

    Args:
        capture: the scene capture; indoor: the scene's preset (voxel size, truncation, range);
        label: the scene (progress lines); source: what an error names (the capture);
        drift: the sparse model's drift correction of the key frames (``summary.json``
        ``drift_correction``), carried over to every fused frame (None: the capture's poses).

    Raises:
        InputError: the mesh is empty after clean-up.
    """
    import time

    t0 = time.perf_counter()
    # Every trusted frame (fine motion step), not only the SfM key frames: coverage of ceilings,
    # far walls and furniture sides comes from the frames between key frames.
    rows = fusion_rows(capture, cfg)[:: max(1, cfg.integrate_every)]
    ids = capture.trajectory.frame_ids[rows]
    poses = carry_drift(drift, capture.trajectory.timestamps_s[rows], capture.trajectory.T_world_cam[rows])
    stats = DepthStats()
    frames = prefetch(fusion_frames(capture, ids, poses, cfg, indoor, refine=depth_refiner(cfg), stats=stats))
    v, f, c = fuse_open3d(_progress(frames, len(ids), f"scene {label}: fusing"), cfg.voxel_m(indoor),
                          cfg.sdf_trunc_m(indoor), cfg.depth_trunc_m(indoor), threads=cfg.fusion_threads)
    t_fuse = time.perf_counter() - t0
    v, f, c = clean_mesh(v, f, c, cfg)
    if len(f) == 0:
        raise InputError(source, "the fused mesh is empty after clean-up",
                         "check that the depth maps and poses belong together")
    st = mesh_stats(v, f)
    return Mesh(v, f, c, {
        "mesh_vertices": st["vertices"], "mesh_faces": st["faces"], "mesh_area_m2": round(st["area_m2"], 3),
        "fused_frames": stats.fused_frames, "fusion_candidates": len(ids),
        "depth_pixels_used_fraction": round(stats.used_fraction, 4),
        "fusion_fps": round(stats.fused_frames / max(t_fuse, 1e-9), 2),
    })


def simplified(vertices: NDArray, faces: NDArray, colors: NDArray, cfg: SceneConfig) -> Mesh:
    """The light mesh for viewers and physics (vertex clustering at ``cfg.simplify_voxel_m``)."""
    vs, fs, cs = simplify_mesh(vertices, faces, colors, cfg.simplify_voxel_m)
    st = mesh_stats(vs, fs)
    return Mesh(vs, fs, cs, {"simplified_vertices": st["vertices"], "simplified_faces": st["faces"]})


def sfm_images(capture, frame_ids: NDArray, T_world_cam: NDArray, cfg: SceneConfig,
               decoded: Mapping[int, NDArray] | None = None) -> tuple[list, NDArray, NDArray]:
    """The sparse model's images: up to ``cfg.sfm.max_images`` key frames spread evenly, as
    ``[(name, (H, W, 3) uint8 RGB)]``, their (N, 4, 4) capture poses (held fixed by the model
    unless its drift correction is on) and their (N,) capture times in seconds (the correction's
    VIO prior and how it is carried over to the frames between key frames). Frames found in
    ``decoded`` (frame index -> RGB, e.g. :attr:`Keyframes.frames`) are not read again."""
    pick = evenly(len(frame_ids), cfg.sfm.max_images)
    names = [f"kf_{int(i):06d}" for i in frame_ids[pick]]
    decoded = decoded or {}
    images = [(n, decoded[int(i)] if int(i) in decoded else capture.frames.rgb(int(i)))
              for n, i in zip(names, frame_ids[pick])]
    times = np.interp(frame_ids[pick], capture.trajectory.frame_ids, capture.trajectory.timestamps_s)
    return images, T_world_cam[pick], times


@dataclass(frozen=True)
class SceneResult:
    """Stage I's key frames and fused mesh (see the module docstring for the simplified mesh and
    the sparse model)."""

    keyframes: Keyframes
    mesh: Mesh


def solve(capture, cfg: SceneConfig, indoor: bool, label: str = "", drift: dict | None = None) -> SceneResult:
    """Stage I's key frames and mesh in memory, as :func:`embodmocap.scene.stage.run` makes them
    given the sparse model's drift correction ``drift`` (the stage builds the model with COLMAP
    between the two: see the module docstring). The simplified mesh is :func:`simplified` of the
    mesh as ``mesh_raw.ply`` stores it (colours as 8-bit), which is what the stage simplifies."""
    return SceneResult(select_keyframes(capture, cfg, indoor), fuse_mesh(capture, cfg, indoor, label=label, drift=drift))


def evenly(n: int, k: int) -> np.ndarray:
    """Up to ``k`` indices spread evenly over ``range(n)``."""
    if n <= k:
        return np.arange(n)
    return np.unique(np.round(np.linspace(0, n - 1, k)).astype(np.int64))


def depth_refiner(cfg: SceneConfig):
    """The refinement hook for :func:`fusion_frames`, or None for plain LiDAR depth."""
    if cfg.depth_refine == "none":
        return None
    from embodmocap.perception.depth_refine import make_depth_refiner

    # Output at the sensor's resolution: the TSDF runs at depth resolution.
    refiner = make_depth_refiner(cfg.depth_refine, model=cfg.depth_refine_model, output="depth")
    return lambda rgb, depth, conf: refiner.refine([rgb], [depth])[0]


def _progress(it, total: int, desc: str):
    """A progress bar on a terminal, one log line otherwise (:mod:`embodmocap.progress`)."""
    from embodmocap.progress import progress

    yield from progress(it, desc, total=total, unit="frame")
