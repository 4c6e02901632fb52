"""The monocular pipeline's decisions as pure functions: arrays, the scene model and configs in,
a result out; no paths, no file I/O (:mod:`embodmocap.mono.stage` reads and writes).

1. :func:`camera_body`: the human model's camera-space body, its depth refined against the 2D
   keypoints (``--human-depth keypoints``, :mod:`~embodmocap.mono.refine`) and/or its shape set to
   the user's height;
2. :func:`stitch_view`: the scene model's chunks stitched (:mod:`~embodmocap.mono.stitch`), the
   metric scale of each segment from the body (:mod:`~embodmocap.mono.scale`, the feet:
   :mod:`~embodmocap.mono.feet`), Z-up (:mod:`~embodmocap.mono.gravity`) and the coloured scene
   points, in one :class:`StitchOutcome`;
3. :func:`body_world`: the body moved into that metric world (:mod:`~embodmocap.mono.body`).

The view's frames reach them as per-frame functions (:class:`MonoView`: person masks and colour
frames read by the stage on demand), the scene model as its role object.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.geometry.similarity import similarity_matrix, transform_poses
from embodmocap.mono.config import MonoConfig
from embodmocap.mono.files import HumanSeq, plan_chunks
from embodmocap.mono.roles import SceneModel

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MonoView:
    """What the pipeline knows of the view (Stage II's ``cameras.npz``, masks and video).

    Attributes:
        K: (3, 3) colour intrinsics, pixels.
        size: (width, height) of the colour frames.
        T_vio: (T, 4, 4) the phone's VIO poses ``T_world_cam`` (gravity-aligned, Z up).
        tracked: (T,) bool: the frame has a VIO pose of its own.
        fps: the sequence's frame rate (NaN when unknown).
        mask: sequence frame(s) -> (..., H, W) bool person mask.
        rgb: sequence frame -> (H, W, 3) uint8 colour frame.
    """

    K: NDArray[np.float64]
    size: tuple[int, int]
    T_vio: NDArray[np.float64]
    tracked: NDArray[np.bool_]
    fps: float
    mask: Callable[[int | NDArray[np.int64]], NDArray[np.bool_]]
    rgb: Callable[[int], NDArray[np.uint8]]

    @property
    def num_frames(self) -> int:
        return len(self.T_vio)

    @property
    def rate(self) -> float:
        """The frame rate, 30 when unknown."""
        return self.fps if np.isfinite(self.fps) else 30.0


@dataclass(frozen=True)
class StitchOutcome:
    """The stitch step's result.

    Attributes:
        T_world_cam: (T, 4, 4) cameras in the metric, Z-up world (each segment its own).
        segment: (T,) the segment of each frame.
        metric_scale: (T,) the scale applied to each frame's segment (NaN: no metric scale).
        points: (N, 3) coloured scene points in the world; colours: (N, 3) uint8.
        figures: the manifest's figures (chunks, scales, gravity sources...).
        warnings: what the user should know (segments without a metric scale...), logged.
    """

    T_world_cam: NDArray[np.float64]
    segment: NDArray[np.int64]
    metric_scale: NDArray[np.float64]
    points: NDArray[np.float64]
    colours: NDArray[np.uint8]
    figures: dict
    warnings: list[str]


def camera_body(cfg: MonoConfig, human: HumanSeq, model, keypoints: NDArray | None, layout: str,
                K: NDArray, fps: float) -> tuple[HumanSeq, dict]:
    """The camera-space body, its depth refined against the 2D keypoints ((T, 17, 3) rows of the
    sequence frames, unseen rows zero, in the ``layout`` of their detector; None = the model's own
    depth) seen through intrinsics ``K`` (3, 3) at ``fps``, and/or its shape set to
    ``cfg.scale.height_m``. Returns the body and the refinement's statistics."""
    from embodmocap.mono.refine import refine_human

    res = refine_human(human, model, keypoints, K, fps, cfg.depth_refine, cfg.scale.height_m, layout)
    return res.human, res.stats


def stitch_view(cfg: MonoConfig, scene: SceneModel, hum: HumanSeq, model, view: MonoView,
                warnings: list[str] = (), source=None) -> StitchOutcome:
    """Chunks -> stitched cameras -> metric scale per segment -> Z-up world, and the scene points.

    Args:
        cfg: settings.
        scene: the scene model (chunk predictions).
        hum: the camera-space body (:func:`camera_body`).
        model: the body model.
        view: the view's cameras and per-frame masks and colour frames.
        warnings: warnings of the earlier parts (the body's depth), carried into the figures.
        source: the file named by the error when no segment has a metric scale (the masks).

    Raises:
        InputError: no segment of the video has a metric scale.
    """
    from embodmocap.mono.stitch import stitch

    T = view.num_frames
    acc = _Votes(cfg, hum, model, view)
    res = stitch(scene, plan_chunks(T, cfg.chunk, cfg.overlap), cfg.stitch, acc.visit)
    warnings = list(res.warnings) + list(warnings)
    n_seg = int(res.segment.max()) + 1
    T_world_cam = np.array(res.T_stitch_cam)
    metric_scale = np.ones(T)
    scales: dict[str, dict] = {}
    up_sources: dict[str, str] = {}
    use_vio = cfg.gravity == "vio" or (cfg.gravity == "auto" and view.tracked.any())
    M_seg = {}
    for g in range(n_seg):
        fr = np.flatnonzero(res.segment == g)
        summ = _segment_scale(cfg, acc, res, g, fr, view.rate)
        if res.metric:
            m = 1.0  # the model's units are metres already; the body's figure is a check
        else:
            m = summ["scale"]
            enough = summ["samples"] >= {"body": cfg.scale.min_samples, "feet": cfg.scale.feet.min_frames,
                                         "combined": 1}[summ["cue"]]
            if res.failed[fr].all() or not enough or not np.isfinite(m):
                why = "the scene model failed on it" if res.failed[fr].all() else (
                    f"only {summ['samples']} {_UNITS[summ['cue']]}"
                    + (f" ({summ['reason']})" if "reason" in summ else ""))
                m = float("nan")
                warnings.append(f"segment {g} (frames {fr[0]}..{fr[-1]}): no metric scale ({why}): left in the scene "
                                "model's units, its frames flagged invalid")
        scales[str(g)] = {k: (round(v, 6) if isinstance(v, float) else v) for k, v in summ.items()}
        metric_scale[fr] = m
        M_seg[g], up_sources[str(g)] = _world_of_segment(m, res.T_stitch_cam[fr], acc.points_of(g),
                                                         np.where(view.tracked[fr, None, None], view.T_vio[fr], np.nan)
                                                         if use_vio else None)
        if up_sources[str(g)] == "cameras":
            warnings.append(f"segment {g}: no floor plane found; Z-up from the cameras' mean up direction")
        T_world_cam[fr] = transform_poses(M_seg[g], res.T_stitch_cam[fr])
    if not np.isfinite(metric_scale).any():
        for w in warnings:
            log.warning(w)
        raise InputError(source, f"no segment of the {n_seg} has a metric scale ("
                         + "; ".join(f"segment {g}: cue {s.get('cue')}, {s.get('samples', 0)} samples"
                                     + (f", {s['reason']}" if "reason" in s else "") for g, s in scales.items())
                         + ")", "check the person masks and the human model's file for this view; with "
                         "--scene-model colmap the floor must be visible and the feet on it")
    P, C = acc.world_points(M_seg, cfg.ply_points)
    for w in warnings[len(res.warnings):]:
        log.warning(w)
    res_rel = [c.residual_rel for c in res.chunks if c.aligned]
    figures = {"frames": T, "chunks": [c.as_json() for c in res.chunks], "segments": n_seg,
               "overlap_residual_rel_median": round(float(np.median(res_rel)), 5) if res_rel else None,
               "overlap_residual_rel_max": round(float(np.max(res_rel)), 5) if res_rel else None,
               "metric_scale": scales, "scale_from": "scene model (metric)" if res.metric else "body",
               "gravity": up_sources, "points": int(len(P))}
    return StitchOutcome(T_world_cam, res.segment, metric_scale, P, C, figures, warnings)


def body_world(hum: HumanSeq, T_world_cam: NDArray, metric_scale: NDArray, model, fps: float, source=None):
    """The camera-space body in the metric world: ``(params, valid)``; frames of a segment without
    a metric scale are not valid. Raises :class:`InputError` (naming ``source``, the human model's
    file) when the human model gave no frame."""
    from embodmocap.mono.body import world_motion

    hum = replace(hum, valid=hum.valid & np.isfinite(metric_scale))  # unscaled segments: not metric
    try:
        return world_motion(hum, T_world_cam, model, fps)
    except ValueError as err:
        raise InputError(source, f"{err}", "check the human model's file") from None


class _Votes:
    """What :func:`stitch_view` gathers from each stitched chunk (the ``visit`` of
    :func:`~embodmocap.mono.stitch.stitch`): the body-depth scale votes per segment, the feet in
    camera space, and the coloured points of every ``ply_frame_stride``-th frame."""

    def __init__(self, cfg: MonoConfig, hum: HumanSeq, model, view: MonoView) -> None:
        from embodmocap.mono.feet import foot_vertices

        T = view.num_frames
        self.cfg, self.hum, self.model, self.view = cfg, hum, model, view
        self.ratios: dict[int, list] = {}
        self.covered: dict[int, list] = {}
        self.ratio_frames: dict[int, list] = {}  # the sequence frame of each entry of ratios[segment]
        self.pts: list[tuple[int, np.ndarray, np.ndarray]] = []  # (segment, stitched points, colours)
        self.ply_budget = max(1, cfg.ply_points // max(1, len(range(0, T, cfg.ply_frame_stride))))
        self.use_body = cfg.scale.cue != "feet"
        self.feet_idx = foot_vertices(model) if cfg.scale.cue != "body" else None
        self.feet_cam = np.zeros((T, 2, self.feet_idx.shape[1], 3)) if self.feet_idx is not None else None

    def visit(self, pred, S, own, segment) -> None:
        import torch

        from embodmocap.mono.scale import depth_ratios
        from embodmocap.mono.stitch import grid

        cfg, hum, model, view = self.cfg, self.hum, self.model, self.view
        W_rgb, H_rgb = view.size
        s_k = float(np.cbrt(np.linalg.det(S[:3, :3])))
        frames = pred.frames[own]
        ok = hum.valid[frames]
        if ok.any():
            idx = own[ok]
            f = pred.frames[idx]
            with torch.no_grad():
                out = model.forward(hum.betas[f], hum.global_orient[f], hum.body_pose[f], hum.transl[f], dtype=torch.float64)
            verts = out.vertices.numpy()
            if self.feet_cam is not None:
                self.feet_cam[f] = verts[:, self.feet_idx]
            # the body-depth cue needs map points on the person (dense maps); sparse SfM has none
            if self.use_body and (cfg.scale.cue == "body" or (pred.conf[idx] > 0).mean() > 0.2):
                r, cov = depth_ratios(verts, np.asarray(model.faces), pred.local_points[idx, ..., 2], pred.conf[idx],
                                      view.mask(f), view.K, (W_rgb, H_rgb), s_k, cfg.scale)
                self.ratios.setdefault(segment, []).extend(r)
                self.covered.setdefault(segment, []).extend(cov)
                self.ratio_frames.setdefault(segment, []).extend(int(x) for x in f)
        # coloured points of every ply_frame_stride-th frame (not the person: scene points only)
        H, W = pred.conf.shape[1:]
        rows, cols = grid(H, W, self.ply_budget)
        for i in own[frames % cfg.ply_frame_stride == 0]:
            f = int(pred.frames[i])
            c = pred.conf[i][rows][:, cols] >= cfg.stitch.min_conf
            person = view.mask(f)
            ur = np.clip(np.rint((cols + 0.5) * W_rgb / W - 0.5), 0, W_rgb - 1).astype(np.int64)
            vr = np.clip(np.rint((rows + 0.5) * H_rgb / H - 0.5), 0, H_rgb - 1).astype(np.int64)
            c &= ~person[vr][:, ur]
            if not c.any():
                continue
            P = pred.world_points(np.array([i]), rows, cols)[0][c]
            P = P @ S[:3, :3].T + S[:3, 3]
            rgb = view.rgb(f)
            self.pts.append((segment, P, rgb[vr][:, ur][c]))

    def points_of(self, g: int) -> list[np.ndarray]:
        """The stitched scene points of segment ``g`` (one array per frame that gave some)."""
        return [p for s, p, _ in self.pts if s == g]

    def world_points(self, M_seg: dict, limit: int) -> tuple[np.ndarray, np.ndarray]:
        """Every segment's points moved by its metric world transform, at most ``limit`` (a seeded sample)."""
        if not self.pts:
            return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
        P = np.concatenate([p @ M_seg[s][:3, :3].T + M_seg[s][:3, 3] for s, p, _ in self.pts])
        C = np.concatenate([c for _, _, c in self.pts])
        if len(P) > limit:
            keep = np.random.default_rng(0).choice(len(P), limit, replace=False)
            P, C = P[np.sort(keep)], C[np.sort(keep)]
        return P, C


def _segment_scale(cfg: MonoConfig, acc: _Votes, res, g: int, fr: NDArray, fps: float) -> dict:
    """The metric scale of segment ``g`` (frames ``fr``) from the cue the config picks: the summary
    the manifest keeps (``cue``, ``scale``, ``samples``...)."""
    from embodmocap.mono.feet import feet_scale, stitched_floor
    from embodmocap.mono.scale import summarise

    summ = {"cue": "body", **summarise(acc.ratios.get(g, []), np.asarray(acc.covered.get(g, []), dtype=np.int64),
                                       cfg.scale.min_frame_samples, np.asarray(acc.ratio_frames.get(g, []), dtype=np.int64),
                                       fps, cfg.scale.block_s)}
    body_summ = summ
    if acc.feet_cam is not None and not res.failed[fr].all() and (
            cfg.scale.cue in ("feet", "combined") or summ["samples"] < cfg.scale.min_samples):
        seg_pts = acc.points_of(g)
        plane = stitched_floor(np.concatenate(seg_pts), res.T_stitch_cam[fr], cfg.scale.feet.plane_inlier_rel) \
            if seg_pts else None
        if plane is None:
            summ = {"cue": "feet", "scale": float("nan"), "frames": 0, "samples": 0, "reason": "no floor plane"}
        else:
            fs = feet_scale(acc.feet_cam[fr], res.T_stitch_cam[fr], acc.hum.valid[fr], plane, fps, cfg.scale.feet,
                            cfg.scale.block_s)
            summ = {"cue": "feet", **{k: v for k, v in fs.items() if k not in ("per_frame", "contact")},
                    "samples": fs["frames"]}
    if cfg.scale.cue == "combined":
        summ = _combined(body_summ, summ if summ["cue"] == "feet" else None, cfg)
    return summ


def _world_of_segment(m: float, T_stitch_cam: NDArray, seg_pts: list[np.ndarray],
                      T_vio: NDArray | None) -> tuple[NDArray[np.float64], str]:
    """The 4x4 similarity taking a segment's stitched frame to the metric, Z-up world (scale ``m``,
    1 when NaN, then gravity: :func:`~embodmocap.mono.gravity.world_alignment`) and where its up came from."""
    from embodmocap.mono import gravity

    Sm = similarity_matrix(np.float64(m if np.isfinite(m) else 1.0), np.eye(3), np.zeros(3))
    Tm = transform_poses(Sm, T_stitch_cam)
    P_m = Sm[0, 0] * np.concatenate(seg_pts) if seg_pts else np.zeros((0, 3))
    A, up = gravity.world_alignment(Tm, P_m, T_vio)
    return A @ Sm, up


_UNITS = {"body": "body samples", "feet": "feet contact frames", "combined": "cues with enough samples"}


def _combined(body: dict, feet: dict | None, cfg: MonoConfig) -> dict:
    """``--scale.cue combined``: the body-depth and the feet cues of one segment, each where it has
    enough samples, averaged by :func:`~embodmocap.mono.scale.combine_cues`. ``samples`` = the
    number of cues used; the manifest keeps both cues' own summaries under ``body`` / ``feet``."""
    from embodmocap.mono.scale import combine_cues

    def r6(d):
        return {k: (round(v, 6) if isinstance(v, float) else v) for k, v in d.items()}

    cues = {}
    if body["samples"] >= cfg.scale.min_samples and np.isfinite(body["scale"]):
        cues["body"] = body
    if feet is not None and feet.get("frames", 0) >= cfg.scale.feet.min_frames and np.isfinite(feet["scale"]):
        cues["feet"] = {k: v for k, v in feet.items() if k != "cue"}
    comb = combine_cues(cues)
    out = {"cue": "combined", "scale": comb["scale"], "se_rel": comb["se_rel"], "weights": comb["weights"],
           "samples": len(comb["weights"]), "body": r6({k: v for k, v in body.items() if k != "cue"})}
    if feet is not None:
        out["feet"] = r6({k: v for k, v in feet.items() if k != "cue"})
    return out
