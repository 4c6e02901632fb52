"""``embodmocap mono``: one view's video -> cameras, scene points and SMPL in a metric, Z-up world.

Reads Stage II's outputs of the view (``cameras.npz`` for the intrinsics and the VIO poses that
give gravity, ``masks.npy``, ``depth.npy`` for the ``vio`` model, ``body_prior.npz`` for the
``prior`` human model) and the scene/human models' files; writes ``sequences/<seq>/mono/<view>/``.
Two resumable steps (``io.stage_manifest``): ``stitch`` (chunks -> stitched cameras -> metric
scale from the body -> gravity; writes ``cameras_world.npz`` and ``points.ply``) and ``body``
(``smpl_world.npz``). Equations: :mod:`~embodmocap.mono.stitch`, :mod:`~embodmocap.mono.scale`,
:mod:`~embodmocap.mono.gravity`, :mod:`~embodmocap.mono.body`; docs/formats.md.

The decisions are pure functions in :mod:`embodmocap.mono.solve` (the view's cameras, per-frame
masks and colour frames, the scene and human models in; a result out); this module opens the
files, fingerprints each step (declared in :mod:`embodmocap.mono.steps`), calls them and writes.
``run(config, session, seq, view, force=)`` has the stages' shape.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from embodmocap.errors import InputError
from embodmocap.io.layout import MonoLayout, SessionLayout
from embodmocap.io.manifest import load_manifest
from embodmocap.io.stage_manifest import StageManifest, Upstream, tracked_stage
from embodmocap.mono.config import MonoConfig
from embodmocap.mono import solve
from embodmocap.mono.files import write_mono_cameras, write_points_ply
from embodmocap.mono.solve import MonoView
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


def _view(lay: SessionLayout, entry, view: str, cams) -> MonoView:
    """The view as :class:`~embodmocap.mono.solve.MonoView`: its cameras, its person masks read
    frame by frame from the memory-mapped stack and its colour frames from the capture (opened
    on first use)."""
    import functools

    from embodmocap.io.captures import open_capture

    vl = lay.sequence(entry.name).view(view)
    if not vl.masks.is_file():
        raise InputError(vl.masks, "the metric scale needs Stage II's person masks",
                         f"give the view masks and rerun `embodmocap sequence {lay.root} --seq {entry.name}`")
    packed = np.load(vl.masks, mmap_mode="r")
    W, H = int(cams.width), int(cams.height)
    raw = np.asarray(cams.raw_frames, dtype=np.int64)
    capture = functools.lru_cache(maxsize=1)(lambda: open_capture(entry.views[view].capture))
    T = cams.num_frames
    return MonoView(K=np.asarray(cams.K, dtype=np.float64), size=(W, H), T_vio=cams.T_world_cam,
                    tracked=~np.asarray(cams.untracked, dtype=bool) if cams.untracked is not None else np.ones(T, bool),
                    fps=float(cams.fps) if cams.fps is not None else float("nan"),
                    mask=lambda f: np.unpackbits(np.asarray(packed[f]), axis=-1)[..., :W].astype(bool),
                    rgb=lambda f: capture().frames.rgb(int(raw[f])))


def _camera_body(cfg: MonoConfig, human: HumanModel, model, cams, kp_path: Path | None, T: int):
    """:func:`~embodmocap.mono.solve.camera_body` of the view: the human model's estimate and
    Stage II's 2D keypoints (``--human-depth keypoints``) read here. Returns the
    :class:`~embodmocap.mono.files.HumanSeq`, the refinement's statistics and warnings."""
    from embodmocap.io.stage_files import read_keypoints2d

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
    hum, stats = solve.camera_body(cfg, hum, model, kp, layout, np.asarray(cams.K, dtype=np.float64), fps)
    return hum, stats, warnings


def _stitch_step(cfg: MonoConfig, lay: SessionLayout, entry, view: str, cams, scene: SceneModel, human: HumanModel,
                 ml: MonoLayout, kp_path: Path | None = None) -> dict:
    from embodmocap.body.model import load_body_model

    model = load_body_model(load_manifest(lay.manifest).body_model)
    hum, depth_stats, depth_warnings = _camera_body(cfg, human, model, cams, kp_path, cams.num_frames)
    mv = _view(lay, entry, view, cams)
    out = solve.stitch_view(cfg, scene, hum, model, mv, depth_warnings, source=lay.sequence(entry.name).view(view).masks)
    write_mono_cameras(ml.cameras_world, out.T_world_cam, mv.K, *mv.size, out.segment, out.metric_scale, mv.fps)
    write_points_ply(ml.points, out.points, out.colours)
    return {**out.figures, "human_depth": depth_stats, "warnings": out.warnings}


def _body_step(cfg: MonoConfig, cams, human: HumanModel, ml: MonoLayout, body_path, fps: float,
               kp_path: Path | None = None) -> dict:
    from embodmocap.body.model import load_body_model
    from embodmocap.io.smpl_file import write_smpl_npz
    from embodmocap.mono.files import read_mono_cameras

    mc = read_mono_cameras(ml.cameras_world)
    T = len(mc["T_world_cam"])
    model = load_body_model(body_path)
    hum, _, _ = _camera_body(cfg, human, model, cams, kp_path, T)
    params, valid = solve.body_world(hum, mc["T_world_cam"], mc["metric_scale"], model, fps,
                                     source=getattr(human, "path", None))
    write_smpl_npz(ml.smpl_world, params, frames=np.arange(T), valid=valid)
    return {"valid_frames": int(valid.sum()), "invalid_frames": int((~valid).sum())}
