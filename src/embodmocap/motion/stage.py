"""Stage IV: world-space SMPL motion with the cameras and the scene fixed.

``run(config, session, seq)`` reads top to bottom as the recipe:

1. ``triangulate``: both views' COCO-17 keypoints (Stage II), left/right swaps undone, triangulated
   with the cameras in the scene's world (Stage III): confidence-weighted DLT over all frames at
   once, short gaps filled, long gaps flagged -> ``keypoints3d.npz``; a one-phone sequence runs
   ``lift`` instead: its view's keypoints lifted with its LiDAR depth on the person mask
   (:mod:`embodmocap.motion.lift`), the same file with ``one_view`` true, then the same fit (its
   outputs carry ``one_view`` too);
2. ``fit``: the world SMPLify (shape, translation and orientation first; then everything) on the
   3D keypoints, each view's 2D keypoints (both with the SMPL points of the detector's layout),
   smoothness, anatomical joint ranges and the pose prior, started from the camera-space body
   prior moved into the world, or without a prior from the 3D keypoints alone (shape from bone
   lengths, torso fit, limb IK: :mod:`embodmocap.motion.ik`); the prior loses to the triangulation
   where it is grossly off; limbs whose start their keypoints reject take the pose carried over
   from the frames where they fit (:mod:`embodmocap.motion.propagate`). Too few triangulated joints is one clear error; frames where the body
   cannot be placed are flagged ``valid = False`` -> ``smpl_fit.npz``;
3. ``align``: with contact markers in the manifest, the yaw + translation that puts the feet on
   the markers, applied to the body (pelvis-consistent) and the cameras; refused, with the
   residual, when the markers disagree -> ``smpl_world.npz``, ``joints_world.npz`` and
   ``<view>/cameras_final.npz`` (the final outputs, also written without markers).

The decisions are pure functions in :mod:`embodmocap.motion.solve` (arrays and configs in,
results out); this module loads the files, fingerprints each step, calls them and writes.

Each step is fingerprinted in ``motion_manifest.json`` and skipped when its inputs and settings
did not change.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from embodmocap.errors import InputError
from embodmocap.io.layout import VIEWS, SessionLayout, SequenceLayout
from embodmocap.io.manifest import load_manifest
from embodmocap.io.smpl_file import read_smpl_quality
from embodmocap.io.stage_files import (read_cameras, read_keypoints2d, read_keypoints3d, read_smpl_npz, read_smpl_valid,
                                       sequence_fps, write_cameras, write_keypoints3d, write_smpl_npz, write_world_joints)
from embodmocap.io.stage_manifest import StageManifest, Upstream, tracked_stage
from embodmocap.motion import solve
from embodmocap.motion.config import MotionConfig  # noqa: F401 (re-exported: defined in config.py)
from embodmocap.motion.solve import KEYPOINTS3D_VERSION, placeable_frames, prefer_keypoints  # noqa: F401 (re-exported)
from embodmocap.motion.steps import STEPS
from embodmocap.motion.floor import scene_floor_z
from embodmocap.sequence.subframe import synced_views

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MotionOutputs:
    """What Stage IV produced for one sequence."""

    name: str
    layout: SequenceLayout
    figures: dict
    skipped: tuple[str, ...]


def scene_mesh(cfg: MotionConfig, lay: SessionLayout, scene: str) -> Path | None:
    """Stage I's mesh whose floor the fit keeps the feet above (the simplified one when Stage I
    wrote it, as ``sim check`` reads), or None with the floor term off or no mesh."""
    if cfg.smplify.w_floor <= 0:
        return None
    sc = lay.scene(scene)
    return next((p for p in (sc.mesh_simplified, sc.mesh_raw) if p.is_file()), None)


@tracked_stage
def run(cfg: MotionConfig, session: str | Path, seq: str | None = None, *, force: bool = False) -> MotionOutputs:
    """Run Stage IV for sequence ``seq`` (the only one when None)."""
    from embodmocap.body.model import load_body_model
    from embodmocap.io.body_prior import body_priors_by_frame

    lay = SessionLayout(Path(session))
    manifest = load_manifest(lay.manifest)
    entry = manifest.sequence(seq)
    out = lay.sequence(entry.name)
    names = entry.view_names  # ("v1", "v2"), or ("v1",) for a one-phone sequence
    for v in names:
        vl = out.view(v)
        if not vl.keypoints.is_file():
            raise InputError(vl.keypoints, "Stage II outputs are missing", f"run `embodmocap sequence {lay.root} --seq {entry.name}` first")
        if not vl.cameras_world.is_file():
            raise InputError(vl.cameras_world, "Stage III outputs are missing", f"run `embodmocap calibrate {lay.root} --seq {entry.name}` first")
    sm = StageManifest(out.motion_manifest, "motion", cfg, root=lay.root, upstream=[
        Upstream(lay.scene(entry.scene).manifest, "scene", f"embodmocap scene {lay.root} --scene {entry.scene}"),
        Upstream(out.manifest, "sequence", f"embodmocap sequence {lay.root} --seq {entry.name}"),
        Upstream(out.calibrate_manifest, "calibrate", f"embodmocap calibrate {lay.root} --seq {entry.name}")],
        inputs=[manifest.body_model, *[getattr(out.view(v), k) for v in names
                                       for k in ("keypoints", "cameras_world", "body_prior")
                                       + (("depth", "masks") if entry.one_view else ())]])
    label = f"sequence {entry.name}"
    cams = {v: read_cameras(out.view(v).cameras_world) for v in names}
    kps = {v: read_keypoints2d(out.view(v).keypoints).keypoints for v in names}
    # Sub-frame sync: view 2's keypoints and cameras at view 1's instants (cams_raw: each view's own frames).
    cams_raw, (cams, kps) = cams, synced_views(out, cams, kps)
    T = min(len(kps[v]) for v in names)
    fps = sequence_fps(out)

    # 1. Triangulation (one view: its keypoints lifted with its LiDAR depth, motion.lift).
    fp_tri = STEPS.fingerprint("triangulate", cfg, context={"one_view": entry.one_view}, reads={
        "<view>/keypoints2d.npz": {v: out.view(v).keypoints for v in names},
        "<view>/cameras_world.npz": {v: out.view(v).cameras_world for v in names},
        # the lift (one view) reads its view's depth on the person mask too
        "<view>/depth.npy": {v: out.view(v).depth for v in names} if entry.one_view else None,
        "<view>/masks.npy": {v: out.view(v).masks for v in names} if entry.one_view else None})
    with sm.step("lift" if entry.one_view else "triangulate", fp_tri, force=force, label=label) as step:
        if step.run:
            if entry.one_view:
                tri = solve.lift_view(cfg, cams, kps, T, *view_depth(out, names[0], cfg), entry.name)
            else:
                tri = solve.triangulate_views(cfg, cams, kps, T, entry.name)
            write_keypoints3d(out.keypoints3d, tri.file)
            step.record([out.keypoints3d], tri.figures)

    # 2. SMPLify.
    model = load_body_model(manifest.body_model)
    priors = body_priors_by_frame({v: out.view(v).body_prior for v in names}, T, cfg.min_prior_fraction,
                                  entry.name) if cfg.use_body_prior else {}
    layout = keypoint_layout(out, entry.name)
    mesh = scene_mesh(cfg, lay, entry.scene)  # the floor under the feet (motion.floor)
    fp_fit = STEPS.fingerprint("fit", cfg, after={"triangulate": fp_tri}, context={"layout": layout, "gender": manifest.gender},
                               reads={"<view>/body_prior.npz": {v: out.view(v).body_prior for v in priors}, "scene mesh": mesh,
                                      # the model's content, not its absolute path: a moved session redoes nothing
                                      "body model": Path(manifest.body_model) if manifest.body_model else model.source,
                                      # the quality's free-space test reads each view's depth
                                      "<view>/depth.npy": {v: out.view(v).depth for v in names if out.view(v).depth.is_file()}
                                      if _depth_tests(cfg) else None,
                                      # and the seen-surface test its person masks
                                      "<view>/masks.npy": {v: out.view(v).masks for v in names if out.view(v).masks.is_file()}
                                      if cfg.quality.surface_m > 0 or cfg.quality.front_m > 0
                                      or cfg.depth_points.min_conf > 0 else None})
    with sm.step("fit", fp_fit, force=force, label=label) as step:
        if step.run:
            fit = solve.fit_motion(cfg, model, read_keypoints3d(out.keypoints3d), cams, kps, T, fps, priors, layout,
                                   manifest.gender, label=entry.name, source=out.keypoints3d,
                                   depth=quality_depth(out, names) if _depth_tests(cfg) else None,
                                   floor_z=scene_floor_z(mesh, cfg.smplify.floor_max_tilt_deg, entry.name))
            write_smpl_npz(out.smpl_fit, fit.params, valid=fit.valid, quality=fit.quality.arrays(),
                           one_view=entry.one_view)
            step.record([out.smpl_fit], fit.figures)

    # 3. Contact alignment (always writes the final outputs).
    contacts = [(c.frame, np.asarray(c.xyz)) for c in entry.contacts] if cfg.align_contacts else []
    fp_align = STEPS.fingerprint("align", cfg, after={"fit": fp_fit}, context={"contacts": [(f, x.tolist()) for f, x in contacts]},
                                 reads={"<view>/cameras_world.npz": {v: out.view(v).cameras_world for v in names}})
    with sm.step("align", fp_align, force=force, label=label) as step:
        if step.run:
            params, frames = read_smpl_npz(out.smpl_fit)
            al = solve.align_motion(cfg, model, params, frames, read_smpl_valid(out.smpl_fit), contacts, cams_raw,
                                    label=entry.name, source=lay.manifest)
            # The per-frame quality is the fit's: the alignment moves body and cameras together.
            write_smpl_npz(out.smpl_world, al.params, al.frames, valid=al.valid,
                           quality=read_smpl_quality(out.smpl_fit), one_view=entry.one_view)
            write_world_joints(out.joints_world, al.joints)
            for v in names:
                write_cameras(out.view(v).cameras_final, al.cameras_final[v])
            step.record([out.smpl_world, out.joints_world, *[out.view(v).cameras_final for v in names]],
                        al.figures | {"one_view": entry.one_view})
    return MotionOutputs(entry.name, out, sm.figures(), tuple(sm.skipped))


def keypoint_layout(out: SequenceLayout, seq: str) -> str:
    """The layout of the detector behind the sequence's 2D keypoints (``keypoints2d.npz``'s
    ``layout``; COCO17 for files written before it was recorded). Views that disagree fall back
    to COCO17 with a warning (one hip definition serves the 3D points of both)."""
    found = []
    # the views Stage II wrote (v1 alone for a one-phone sequence; v1 read, and its error raised, when none)
    for v in [v for v in VIEWS if out.view(v).keypoints.is_file()] or list(VIEWS[:1]):
        found.append(str(read_keypoints2d(out.view(v).keypoints).layout))  # COCO17 for files without it
    if len(set(found)) > 1:
        log.warning("%s: the views' keypoints come from different layouts %s; fitting with COCO-17 hips", seq, found)
        return "COCO17"
    return found[0]


def _depth_tests(cfg: MotionConfig) -> bool:
    """Whether the fit reads the views' depth (the quality's free-space or seen-surface tests, the
    one-view joints placed with depth: :mod:`embodmocap.motion.depth_points`)."""
    return (cfg.quality.free_space_m > 0 or cfg.quality.surface_m > 0 or cfg.quality.front_m > 0
            or cfg.depth_points.min_conf > 0)


def quality_depth(out: SequenceLayout, names) -> dict:
    """view -> ``(depth_mm, (width, height), masks)`` for the quality's free-space and
    seen-surface tests (:mod:`embodmocap.motion.free_space`, :mod:`embodmocap.motion.seen_surface`):
    Stage II's depth stack and packed person masks, memory-mapped (masks None when the view has
    none); views without ``depth.npy`` are left out. View 2's frame ``t`` stands for view 1's
    instant ``t``: the sub-frame offset (under one frame) moves a limb far less than the tests'
    tolerances."""
    found = {}
    for v in names:
        vl = out.view(v)
        if vl.depth.is_file():
            cams = read_cameras(vl.cameras)
            found[v] = (np.load(vl.depth, mmap_mode="r"), (int(cams["width"]), int(cams["height"])),
                        np.load(vl.masks, mmap_mode="r") if vl.masks.is_file() else None)
    return found


def view_depth(out: SequenceLayout, v: str, cfg: MotionConfig):
    """``(depth_at, rgb_size)`` of view ``v`` for :func:`embodmocap.motion.solve.lift_view`: its
    Stage II depth read frame by frame from the memory-mapped stack, kept on the person mask
    (:func:`embodmocap.motion.lift.person_depth`; all pixels when the view has no masks)."""
    from embodmocap.io.frame_stack import read_depth_m, read_mask
    from embodmocap.motion.lift import person_depth

    vl = out.view(v)
    if not vl.depth.is_file():
        raise InputError(vl.depth, "a one-phone sequence needs its view's depth (Stage II's depth.npy)",
                         f"run `embodmocap sequence --seq {out.root.name}` (depth is not optional with one view)")
    cams = read_cameras(vl.cameras)
    width, height = int(cams["width"]), int(cams["height"])
    mask_at = (lambda t: read_mask(vl.masks, t, width)) if vl.masks.is_file() else None
    if mask_at is None:
        log.warning("%s: one view without person masks: keypoint depth may read the background at the body's edges",
                    out.root.name)
    return person_depth(lambda t: read_depth_m(vl.depth, t), mask_at, cfg.lift.mask_erode_px), (width, height)
