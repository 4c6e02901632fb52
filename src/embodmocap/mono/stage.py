"""``embodmocap mono``: one view's video -> cameras, scene points and SMPL in a metric, Z-up world.

Reads Stage II's outputs of the view (``cameras.npz`` for the intrinsics and the VIO poses that
give gravity, ``masks.npy``, ``depth.npy`` for the ``vio`` model, ``body_prior.npz`` for the
``prior`` human model) and the scene/human models' files; writes ``sequences/<seq>/mono/<view>/``.
Two resumable steps (``io.stage_manifest``): ``stitch`` (chunks -> stitched cameras -> metric
scale from the body -> gravity; writes ``cameras_world.npz`` and ``points.ply``) and ``body``
(``smpl_world.npz``). Equations: :mod:`~embodmocap.mono.stitch`, :mod:`~embodmocap.mono.scale`,
:mod:`~embodmocap.mono.gravity`, :mod:`~embodmocap.mono.body`; docs/formats.md.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from embodmocap.errors import InputError
from embodmocap.geometry.similarity import similarity_matrix, transform_poses
from embodmocap.io.layout import MonoLayout, SessionLayout
from embodmocap.io.manifest import load_manifest
from embodmocap.io.stage_manifest import StageManifest, Upstream, tracked_stage
from embodmocap.mono.config import MonoConfig
from embodmocap.mono.files import plan_chunks, write_mono_cameras, write_points_ply
from embodmocap.mono.steps import STEPS
from embodmocap.mono.roles import HumanModel, PrecomputedHuman, PrecomputedScene, PriorHuman, SceneModel, VioScene

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MonoOutputs:
    """What a run gave: the sequence, view, output folder, the manifest's figures, skipped steps."""

    name: str
    view: str
    layout: MonoLayout
    figures: dict
    skipped: tuple[str, ...]


def _models(cfg: MonoConfig, lay: SessionLayout, seq: str, view: str, cams) -> tuple[SceneModel, HumanModel, list[Path], Path]:
    vl, pl = lay.sequence(seq).view(view), lay.perception(seq, view)
    if cfg.scene_model == "colmap":
        scene = _colmap_scene(cfg, lay, seq, view, cams)
        scene_inputs = []  # the video and the masks: the capture and Stage II's outputs, fingerprinted already
    elif cfg.scene_model == "precomputed":
        if not pl.mono_scene_dir.is_dir():
            raise InputError(pl.mono_scene_dir, "--scene-model precomputed needs the scene model's chunk files here",
                             "run Pi3 / VGGT / MASt3R per chunk and write chunk_<first frame>.npz files (docs/formats.md, "
                             "'Monocular pipeline'), or use --scene-model vio")
        scene: SceneModel = PrecomputedScene(pl.mono_scene_dir)
        scene_inputs = [pl.mono_scene_dir]
    else:
        if not vl.depth.is_file():
            raise InputError(vl.depth, "--scene-model vio needs Stage II's depth", f"run `embodmocap sequence {lay.root} --seq {seq}`")
        scene = VioScene(cams.T_world_cam, cams.K_depth, vl.depth)
        scene_inputs = [vl.depth]
    if cfg.human_model == "prior":
        if not vl.body_prior.is_file():
            raise InputError(vl.body_prior, "--human-model prior needs Stage II's body prior",
                             "give the view a body_prior in session.toml and rerun `embodmocap sequence`, or use "
                             "--human-model precomputed")
        human: HumanModel = PriorHuman(vl.body_prior)
        human_input = vl.body_prior
    else:
        human = PrecomputedHuman(pl.mono_human)
        human_input = pl.mono_human
    return scene, human, scene_inputs, human_input


def _colmap_scene(cfg: MonoConfig, lay: SessionLayout, seq: str, view: str, cams):
    from embodmocap.io.captures import open_capture
    from embodmocap.mono.colmap_scene import ColmapScene

    vl = lay.sequence(seq).view(view)
    if not vl.masks.is_file():
        raise InputError(vl.masks, "--scene-model colmap needs Stage II's person masks (the person is masked out of SfM)",
                         f"run `embodmocap sequence {lay.root} --seq {seq}`")
    capture = open_capture(load_manifest(lay.manifest).sequences[seq].views[view].capture)
    raw = np.asarray(cams.raw_frames, dtype=np.int64)
    W = int(cams.width)
    packed = np.load(vl.masks, mmap_mode="r")
    return ColmapScene(lambda f: capture.frames.rgb(int(raw[f])),
                       lambda f: np.unpackbits(np.asarray(packed[f]), axis=-1)[:, :W].astype(bool),
                       np.asarray(cams.K, dtype=np.float64), (W, int(cams.height)), cfg.colmap)


@tracked_stage
def run(cfg: MonoConfig, session: str | Path, seq: str | None = None, view: str = "v1", *,
        force: bool = False) -> MonoOutputs:
    """Run the monocular pipeline on one view of one sequence (resumable)."""
    from embodmocap.io.stage_files import read_cameras, sequence_fps

    if view not in ("v1", "v2"):
        raise InputError(None, f"--view {view!r} is not a view", "use --view v1 or --view v2")
    lay = SessionLayout(Path(session))
    manifest = load_manifest(lay.manifest)
    entry = manifest.sequence(seq)
    sl = lay.sequence(entry.name)
    vl = sl.view(view)
    ml = sl.mono(view)
    cams = read_cameras(vl.cameras)
    scene, human, scene_inputs, human_input = _models(cfg, lay, entry.name, view, cams)
    kp_path = vl.keypoints if cfg.human_depth == "keypoints" and vl.keypoints.is_file() else None
    inputs = [vl.cameras, vl.masks, *([kp_path] if kp_path else []), *scene_inputs, human_input]
    sm = StageManifest(ml.manifest, "mono", {"view": view, **_plain(cfg)}, inputs=inputs, root=lay.root,
                       upstream=[Upstream(sl.manifest, "sequence", f"embodmocap sequence {lay.root} --seq {entry.name}")])
    label = f"mono {entry.name} {view}"
    ml.root.mkdir(parents=True, exist_ok=True)
    body_path = manifest.body_model
    fp_stitch = STEPS.fingerprint("stitch", cfg, context={"view": view}, reads={
        "<view>/cameras.npz": vl.cameras, "<view>/masks.npy": vl.masks, "<view>/keypoints2d.npz": kp_path,
        "scene model files": scene_inputs, "human model file": human_input, "body model": body_path})
    with sm.step("stitch", fp_stitch, force=force, label=label) as step:
        if step.run:
            figs = _stitch_step(cfg, lay, entry, view, cams, scene, human, ml, kp_path)
            step.record([ml.cameras_world, ml.points], figs)
    with sm.step("body", STEPS.fingerprint("body", cfg, after={"stitch": fp_stitch}), force=force, label=label) as step:
        if step.run:
            figs = _body_step(cfg, cams, human, ml, body_path, sequence_fps(sl.root), kp_path)
            step.record([ml.smpl_world], figs)
    return MonoOutputs(entry.name, view, ml, sm.figures(), tuple(sm.skipped))


def _plain(cfg: MonoConfig) -> dict:
    from dataclasses import asdict

    return asdict(cfg)


def _camera_body(cfg: MonoConfig, human: HumanModel, model, cams, kp_path: Path | None, T: int):
    """The human model's camera-space body, its depth refined against the 2D keypoints
    (``--human-depth keypoints``, :mod:`~embodmocap.mono.refine`) and/or its shape set to the
    user's height. Returns the :class:`~embodmocap.mono.files.HumanSeq`, the refinement's
    statistics and warnings."""
    from embodmocap.io.stage_files import read_keypoints2d
    from embodmocap.mono.refine import refine_human

    hum = human.estimate(T)
    warnings = []
    kp, layout = None, "COCO17"
    if cfg.human_depth == "keypoints":
        if kp_path is None:
            warnings.append("--human-depth keypoints: Stage II's keypoints2d.npz is missing for this view: the human "
                            "model's own depth is used (rerun `embodmocap sequence` with keypoints to refine it)")
        else:
            f = read_keypoints2d(kp_path)
            if len(f.keypoints) != T or (cams.raw_frames is not None
                                         and not np.array_equal(np.asarray(f.raw_frames), np.asarray(cams.raw_frames))):
                raise InputError(kp_path, f"its {len(f.keypoints)} rows are not the {T} sequence frames of cameras.npz",
                                 "rerun `embodmocap sequence` for this sequence so both files come from one run")
            kp, layout = np.where(np.asarray(f.seen, bool)[:, None, None], np.asarray(f.keypoints, np.float64), 0.0), \
                str(f.layout)
    fps = float(cams.fps) if cams.fps is not None and np.isfinite(cams.fps) else 30.0
    res = refine_human(hum, model, kp, np.asarray(cams.K, dtype=np.float64), fps, cfg.depth_refine,
                       cfg.scale.height_m, layout)
    return res.human, res.stats, warnings


def _stitch_step(cfg: MonoConfig, lay: SessionLayout, entry, view: str, cams, scene: SceneModel, human: HumanModel,
                 ml: MonoLayout, kp_path: Path | None = None) -> dict:
    import torch

    from embodmocap.body.model import load_body_model
    from embodmocap.io.captures import open_capture
    from embodmocap.mono import gravity
    from embodmocap.mono.feet import feet_scale, foot_vertices, stitched_floor
    from embodmocap.mono.scale import depth_ratios, summarise
    from embodmocap.mono.stitch import grid, stitch

    vl = lay.sequence(entry.name).view(view)
    T = cams.num_frames
    W_rgb, H_rgb = int(cams.width), int(cams.height)
    K = np.asarray(cams.K, dtype=np.float64)
    model = load_body_model(load_manifest(lay.manifest).body_model)
    hum, depth_stats, depth_warnings = _camera_body(cfg, human, model, cams, kp_path, T)
    if not vl.masks.is_file():
        raise InputError(vl.masks, "the metric scale needs Stage II's person masks",
                         f"give the view masks and rerun `embodmocap sequence {lay.root} --seq {entry.name}`")
    masks_packed = np.load(vl.masks, mmap_mode="r")
    capture = open_capture(entry.views[view].capture)
    raw = np.asarray(cams.raw_frames, dtype=np.int64)
    ratios: dict[int, list] = {}
    covered: dict[int, list] = {}
    ratio_frames: dict[int, list] = {}  # the sequence frame of each entry of ratios[segment]
    pts_acc: list[tuple[int, np.ndarray, np.ndarray]] = []  # (segment, stitched points, colours)
    ply_budget = max(1, cfg.ply_points // max(1, len(range(0, T, cfg.ply_frame_stride))))
    use_body = cfg.scale.cue != "feet"
    feet_idx = foot_vertices(model) if cfg.scale.cue != "body" else None
    feet_cam = np.zeros((T, 2, feet_idx.shape[1], 3)) if feet_idx is not None else None

    def visit(pred, S, own, segment):
        s_k = float(np.cbrt(np.linalg.det(S[:3, :3])))
        frames = pred.frames[own]
        ok = hum.valid[frames]
        if ok.any():
            idx = own[ok]
            f = pred.frames[idx]
            with torch.no_grad():
                out = model.forward(hum.betas[f], hum.global_orient[f], hum.body_pose[f], hum.transl[f], dtype=torch.float64)
            verts = out.vertices.numpy()
            if feet_cam is not None:
                feet_cam[f] = verts[:, feet_idx]
            # the body-depth cue needs map points on the person (dense maps); sparse SfM has none
            if use_body and (cfg.scale.cue == "body" or (pred.conf[idx] > 0).mean() > 0.2):
                masks = np.unpackbits(np.asarray(masks_packed[f]), axis=-1)[..., :W_rgb].astype(bool)
                r, cov = depth_ratios(verts, np.asarray(model.faces), pred.local_points[idx, ..., 2], pred.conf[idx],
                                      masks, K, (W_rgb, H_rgb), s_k, cfg.scale)
                ratios.setdefault(segment, []).extend(r)
                covered.setdefault(segment, []).extend(cov)
                ratio_frames.setdefault(segment, []).extend(int(x) for x in f)
        # coloured points of every ply_frame_stride-th frame (not the person: scene points only)
        H, W = pred.conf.shape[1:]
        rows, cols = grid(H, W, ply_budget)
        for i in own[frames % cfg.ply_frame_stride == 0]:
            f = int(pred.frames[i])
            c = pred.conf[i][rows][:, cols] >= cfg.stitch.min_conf
            person = np.unpackbits(np.asarray(masks_packed[f]), axis=-1)[:, :W_rgb].astype(bool)
            ur = np.clip(np.rint((cols + 0.5) * W_rgb / W - 0.5), 0, W_rgb - 1).astype(np.int64)
            vr = np.clip(np.rint((rows + 0.5) * H_rgb / H - 0.5), 0, H_rgb - 1).astype(np.int64)
            c &= ~person[vr][:, ur]
            if not c.any():
                continue
            P = pred.world_points(np.array([i]), rows, cols)[0][c]
            P = P @ S[:3, :3].T + S[:3, 3]
            rgb = capture.frames.rgb(int(raw[f]))
            pts_acc.append((segment, P, rgb[vr][:, ur][c]))

    res = stitch(scene, plan_chunks(T, cfg.chunk, cfg.overlap), cfg.stitch, visit)
    warnings = list(res.warnings) + depth_warnings
    n_seg = int(res.segment.max()) + 1
    T_world_cam = np.array(res.T_stitch_cam)
    metric_scale = np.ones(T)
    scales: dict[str, dict] = {}
    up_sources: dict[str, str] = {}
    tracked = ~np.asarray(cams.untracked, dtype=bool) if cams.untracked is not None else np.ones(T, bool)
    use_vio = cfg.gravity == "vio" or (cfg.gravity == "auto" and tracked.any())
    M_seg = {}
    fps = float(cams.fps) if cams.fps is not None and np.isfinite(cams.fps) else 30.0
    for g in range(n_seg):
        fr = np.flatnonzero(res.segment == g)
        summ = {"cue": "body", **summarise(ratios.get(g, []), np.asarray(covered.get(g, []), dtype=np.int64),
                                           cfg.scale.min_frame_samples, np.asarray(ratio_frames.get(g, []), dtype=np.int64),
                                           fps, cfg.scale.block_s)}
        body_summ = summ
        if feet_cam is not None and not res.failed[fr].all() and (
                cfg.scale.cue in ("feet", "combined") or summ["samples"] < cfg.scale.min_samples):
            seg_pts = [p for s, p, _ in pts_acc if s == g]
            plane = stitched_floor(np.concatenate(seg_pts), res.T_stitch_cam[fr], cfg.scale.feet.plane_inlier_rel) \
                if seg_pts else None
            if plane is None:
                summ = {"cue": "feet", "scale": float("nan"), "frames": 0, "samples": 0, "reason": "no floor plane"}
            else:
                fs = feet_scale(feet_cam[fr], res.T_stitch_cam[fr], hum.valid[fr], plane, fps, cfg.scale.feet,
                                cfg.scale.block_s)
                summ = {"cue": "feet", **{k: v for k, v in fs.items() if k not in ("per_frame", "contact")},
                        "samples": fs["frames"]}
        if cfg.scale.cue == "combined":
            summ = _combined(body_summ, summ if summ["cue"] == "feet" else None, cfg)
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
        Sm = similarity_matrix(np.float64(m if np.isfinite(m) else 1.0), np.eye(3), np.zeros(3))
        Tm = transform_poses(Sm, res.T_stitch_cam[fr])
        seg_pts = [p for s, p, _ in pts_acc if s == g]
        P_m = Sm[0, 0] * np.concatenate(seg_pts) if seg_pts else np.zeros((0, 3))
        T_vio = np.where(tracked[fr, None, None], cams.T_world_cam[fr], np.nan) if use_vio else None
        A, up_sources[str(g)] = gravity.world_alignment(Tm, P_m, T_vio)
        if up_sources[str(g)] == "cameras":
            warnings.append(f"segment {g}: no floor plane found; Z-up from the cameras' mean up direction")
        M_seg[g] = A @ Sm
        T_world_cam[fr] = transform_poses(M_seg[g], res.T_stitch_cam[fr])
    if not np.isfinite(metric_scale).any():
        for w in warnings:
            log.warning(w)
        raise InputError(vl.masks, f"no segment of the {n_seg} has a metric scale ("
                         + "; ".join(f"segment {g}: cue {s.get('cue')}, {s.get('samples', 0)} samples"
                                     + (f", {s['reason']}" if "reason" in s else "") for g, s in scales.items())
                         + ")", "check the person masks and the human model's file for this view; with "
                         "--scene-model colmap the floor must be visible and the feet on it")
    write_mono_cameras(ml.cameras_world, T_world_cam, K, W_rgb, H_rgb, res.segment, metric_scale,
                       float(cams.fps) if cams.fps is not None else float("nan"))
    if pts_acc:
        P = np.concatenate([p @ M_seg[s][:3, :3].T + M_seg[s][:3, 3] for s, p, _ in pts_acc])
        C = np.concatenate([c for _, _, c in pts_acc])
        if len(P) > cfg.ply_points:
            keep = np.random.default_rng(0).choice(len(P), cfg.ply_points, replace=False)
            P, C = P[np.sort(keep)], C[np.sort(keep)]
    else:
        P, C = np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    write_points_ply(ml.points, P, C)
    for w in warnings[len(res.warnings):]:
        log.warning(w)
    res_rel = [c.residual_rel for c in res.chunks if c.aligned]
    return {"frames": T, "chunks": [c.as_json() for c in res.chunks], "segments": n_seg,
            "overlap_residual_rel_median": round(float(np.median(res_rel)), 5) if res_rel else None,
            "overlap_residual_rel_max": round(float(np.max(res_rel)), 5) if res_rel else None,
            "metric_scale": scales, "scale_from": "scene model (metric)" if res.metric else "body",
            "gravity": up_sources, "points": int(len(P)), "human_depth": depth_stats, "warnings": warnings}


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


def _body_step(cfg: MonoConfig, cams, human: HumanModel, ml: MonoLayout, body_path, fps: float,
               kp_path: Path | None = None) -> dict:
    from embodmocap.body.model import load_body_model
    from embodmocap.io.smpl_file import write_smpl_npz
    from embodmocap.mono.body import world_motion
    from embodmocap.mono.files import read_mono_cameras

    mc = read_mono_cameras(ml.cameras_world)
    T = len(mc["T_world_cam"])
    model = load_body_model(body_path)
    hum, _, _ = _camera_body(cfg, human, model, cams, kp_path, T)
    hum = replace(hum, valid=hum.valid & np.isfinite(mc["metric_scale"]))  # unscaled segments: not metric
    try:
        params, valid = world_motion(hum, mc["T_world_cam"], model, fps)
    except ValueError as err:
        raise InputError(getattr(human, "path", None), f"{err}", "check the human model's file") from None
    write_smpl_npz(ml.smpl_world, params, frames=np.arange(T), valid=valid)
    return {"valid_frames": int(valid.sum()), "invalid_frames": int((~valid).sum())}
