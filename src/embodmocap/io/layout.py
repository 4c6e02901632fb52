"""The one place that knows where every file of a session lives.

No other module builds a session path by hand: stages ask these objects. A session folder looks
like this (raw captures may also live elsewhere; the manifest names them)::

    SESSION/
      session.toml                    the manifest (scenes, sequences, body model)
      body_model.npz                  optional body model file (synthetic sessions write one)
      captures/                       raw captures as the phone apps wrote them
        <scene>/                      scene capture
        <seq>/v1/  <seq>/v2/          the two view captures of a sequence (v1 alone: one phone)
      perception/<seq>/<view>/        precomputed perception of a view (synth or user tools)
        keypoints/NNNNNN_keypoints.json   OpenPose-style per-frame JSON (COCO-17 layout)
        masks/NNNNNN.png              person masks, 255 = person
        body_prior.npz                camera-space body prior per frame
      ground_truth/                   only for synthetic sessions
      scenes/<scene>/                 stage I outputs
      sequences/<seq>/                stage II-IV outputs (export/, render/, sim/ from export, render, sim)
      evaluation.json                 metrics (embodmocap evaluate)
      report.html, report.md, report_assets/   the report (embodmocap report)
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

VIEWS: tuple[str, str] = ("v1", "v2")


@dataclass(frozen=True)
class SceneLayout:
    """Stage I outputs of one scene."""

    root: Path

    @property
    def manifest(self) -> Path:
        return self.root / "manifest.json"

    @property
    def keyframes(self) -> Path:
        return self.root / "keyframes.json"

    @property
    def mesh_raw(self) -> Path:
        return self.root / "mesh_raw.ply"

    @property
    def mesh_simplified(self) -> Path:
        return self.root / "mesh_simplified.ply"

    @property
    def sfm_dir(self) -> Path:
        return self.root / "sfm"

    @property
    def sfm_model(self) -> Path:
        """The sparse model (COLMAP binary files) inside ``sfm_dir``."""
        return self.sfm_dir / "sparse"

    @property
    def register_index(self) -> Path:
        """Stage III's scene index (cached once per scene, reused by every sequence)."""
        return self.root / "register_index.npz"


@dataclass(frozen=True)
class ViewLayout:
    """Per-view outputs of a sequence (stages II-IV)."""

    root: Path

    @property
    def frame_map(self) -> Path:
        return self.root / "frame_map.json"

    @property
    def cameras(self) -> Path:
        return self.root / "cameras.npz"

    @property
    def keypoints(self) -> Path:
        return self.root / "keypoints2d.npz"

    @property
    def masks(self) -> Path:
        """(T, H, ceil(W/8)) uint8 bit-packed person masks (``io.frame_stack``)."""
        return self.root / "masks.npy"

    @property
    def depth(self) -> Path:
        """(T, h, w) uint16 depth in millimetres (``io.frame_stack``)."""
        return self.root / "depth.npy"

    @property
    def body_prior(self) -> Path:
        return self.root / "body_prior.npz"

    @property
    def registration(self) -> Path:
        """Stage III: the sampled frames registered into the scene model."""
        return self.root / "registration.npz"

    @property
    def cameras_world(self) -> Path:
        """Stage III: per-frame cameras in the scene's world."""
        return self.root / "cameras_world.npz"

    @property
    def cameras_final(self) -> Path:
        """Stage IV: per-frame cameras in the scene's world after the optional contact alignment
        (equal to ``cameras_world`` without it); what exports, the viewer and the renderer use."""
        return self.root / "cameras_final.npz"


@dataclass(frozen=True)
class SequenceLayout:
    """Stage II-IV outputs of one sequence."""

    root: Path

    def view(self, name: str) -> ViewLayout:
        return ViewLayout(self.root / name)

    def views(self) -> tuple[str, ...]:
        """The views Stage II wrote (their ``cameras.npz``), in :data:`VIEWS` order: ``("v1", "v2")``,
        or ``("v1",)`` for a one-phone sequence; ``VIEWS`` before Stage II ran (what to expect)."""
        found = tuple(v for v in VIEWS if self.view(v).cameras.is_file())
        return found or VIEWS

    @property
    def manifest(self) -> Path:
        return self.root / "manifest.json"

    @property
    def sync(self) -> Path:
        """Stage II's sync record (laser and manual sources, the slicing)."""
        return self.root / "sync.json"

    @property
    def final_sync(self) -> Path:
        """Stage III's final sync record (``sync.json`` plus the geometric source and the choice);
        sessions written before it existed hold it in ``sync.json``
        (:func:`embodmocap.io.stage_files.read_final_sync`)."""
        return self.root / "final_sync.json"

    def sync_sheet(self, view: str) -> Path:
        """Stage II: the contact sheet of a view's laser sync event."""
        return self.root / f"sync_{view}.png"

    @property
    def calibrate_manifest(self) -> Path:
        """Stage III's stage manifest."""
        return self.root / "calibrate_manifest.json"

    @property
    def calibration(self) -> Path:
        """Stage III: view offsets and the residual report."""
        return self.root / "calibration.json"

    @property
    def motion_manifest(self) -> Path:
        """Stage IV's stage manifest (final loss terms, per-view reprojection error)."""
        return self.root / "motion_manifest.json"

    @property
    def smpl_fit(self) -> Path:
        """Stage IV: the SMPLify result before the optional contact alignment (same format as
        ``smpl_world``)."""
        return self.root / "smpl_fit.npz"

    @property
    def smpl_world(self) -> Path:
        """Stage IV: world SMPL motion, AMASS-like npz."""
        return self.root / "smpl_world.npz"

    @property
    def keypoints3d(self) -> Path:
        """Stage IV: triangulated COCO-17 keypoints in the scene's world."""
        return self.root / "keypoints3d.npz"

    @property
    def joints_world(self) -> Path:
        """Stage IV: the fitted body's joints in the scene's world."""
        return self.root / "joints_world.npz"

    @property
    def exports_dir(self) -> Path:
        """``embodmocap export`` writes here (one file or folder per format)."""
        return self.root / "export"

    @property
    def robots_dir(self) -> Path:
        """``embodmocap robot retarget``: one folder per robot (:meth:`robot_dir`)."""
        return self.root / "robot"

    def robot_dir(self, robot: str) -> Path:
        """``embodmocap robot retarget`` writes one robot's motion, exports and report here."""
        return self.robots_dir / robot

    @property
    def skills_dir(self) -> Path:
        """``embodmocap skills`` writes here (``skills.json`` and its manifest)."""
        return self.root / "skills"

    @property
    def skills_json(self) -> Path:
        """``embodmocap skills``: the skill clips of the sequence."""
        return self.skills_dir / "skills.json"

    @property
    def skills_manifest(self) -> Path:
        """``embodmocap skills``' stage manifest."""
        return self.skills_dir / "manifest.json"

    @property
    def skill_clips(self) -> Path:
        """Optional hand-made clip list (``{"clips": [...]}``) that ``embodmocap catalog`` reads."""
        return self.root / "skill_clips.json"

    @property
    def renders_dir(self) -> Path:
        """``embodmocap render`` writes its MP4s here."""
        return self.root / "render"

    def mono(self, view: str) -> "MonoLayout":
        """``embodmocap mono`` outputs of one view."""
        return MonoLayout(self.root / "mono" / view)

    @property
    def sim_dir(self) -> Path:
        """``embodmocap sim`` writes here (``sim_check.json``, caches, training runs)."""
        return self.root / "sim"

    @property
    def sim_check(self) -> Path:
        """``embodmocap sim check``: physical plausibility of the fitted motion."""
        return self.root / "sim" / "sim_check.json"


@dataclass(frozen=True)
class PerceptionLayout:
    """Precomputed perception of one view, in the formats users bring (and synth writes)."""

    root: Path

    @property
    def keypoints_dir(self) -> Path:
        return self.root / "keypoints"

    def keypoints_json(self, frame: int) -> Path:
        return self.keypoints_dir / f"{frame:06d}_keypoints.json"

    @property
    def masks_dir(self) -> Path:
        return self.root / "masks"

    def mask_png(self, frame: int) -> Path:
        return self.masks_dir / f"{frame:06d}.png"

    @property
    def body_prior(self) -> Path:
        return self.root / "body_prior.npz"

    @property
    def mono_scene_dir(self) -> Path:
        """``embodmocap mono --scene-model precomputed``: one ``chunk_<first frame:06d>.npz`` per
        chunk (Pi3 layout: camera_poses, local_points, conf, frames)."""
        return self.root / "mono_scene"

    @property
    def mono_human(self) -> Path:
        """``embodmocap mono --human-model precomputed``: camera-space SMPL per sequence frame."""
        return self.root / "mono_human.npz"


@dataclass(frozen=True)
class MonoLayout:
    """``embodmocap mono`` outputs of one view: ``sequences/<seq>/mono/<view>/``."""

    root: Path

    @property
    def manifest(self) -> Path:
        return self.root / "mono_manifest.json"

    @property
    def cameras_world(self) -> Path:
        """T_world_cam per frame in the metric, Z-up monocular world."""
        return self.root / "cameras_world.npz"

    @property
    def smpl_world(self) -> Path:
        """World SMPL motion (Stage IV's format)."""
        return self.root / "smpl_world.npz"

    @property
    def points(self) -> Path:
        """Stitched, coloured scene points."""
        return self.root / "points.ply"


@dataclass(frozen=True)
class GroundTruthLayout:
    """Ground truth written by the synthetic studio (never read by the pipeline stages)."""

    root: Path

    @property
    def info(self) -> Path:
        """JSON: seed, preset, sizes, per-scene and per-sequence facts."""
        return self.root / "ground_truth.json"

    def scene_mesh(self, scene: str) -> Path:
        """PLY, Z-up metres, scene frame."""
        return self.root / f"scene_{scene}_mesh.ply"

    def scene_device(self, scene: str) -> Path:
        """npz: T_scene_vio (4,4), T_scene_cam (T,4,4) true poses of the scene capture."""
        return self.root / f"scene_{scene}_device.npz"

    def sequence(self, seq: str) -> Path:
        """npz: world SMPL params, joints, per-view true cameras, T_scene_vio, sync frames."""
        return self.root / f"seq_{seq}.npz"


@dataclass(frozen=True)
class SessionLayout:
    """Every path of one session folder."""

    root: Path

    def __post_init__(self) -> None:
        object.__setattr__(self, "root", Path(self.root))

    @property
    def manifest(self) -> Path:
        return self.root / "session.toml"

    @property
    def body_model(self) -> Path:
        return self.root / "body_model.npz"

    @property
    def captures_dir(self) -> Path:
        return self.root / "captures"

    def scene_capture(self, scene: str) -> Path:
        """Default folder of a scene's raw capture (the manifest may name another)."""
        return self.captures_dir / scene

    def view_capture(self, seq: str, view: str) -> Path:
        """Default folder of a view's raw capture (the manifest may name another)."""
        return self.captures_dir / seq / view

    def perception(self, seq: str, view: str) -> PerceptionLayout:
        return PerceptionLayout(self.root / "perception" / seq / view)

    @property
    def ground_truth(self) -> GroundTruthLayout:
        return GroundTruthLayout(self.root / "ground_truth")

    @property
    def scenes_dir(self) -> Path:
        return self.root / "scenes"

    @property
    def sequences_dir(self) -> Path:
        return self.root / "sequences"

    def scene(self, name: str) -> SceneLayout:
        return SceneLayout(self.scenes_dir / name)

    def sequence(self, name: str) -> SequenceLayout:
        return SequenceLayout(self.sequences_dir / name)

    @property
    def evaluation(self) -> Path:
        return self.root / "evaluation.json"

    @property
    def training_dir(self) -> Path:
        """``embodmocap export SESSION --to training`` writes here unless ``--out`` is given."""
        return self.root / "training"

    @property
    def report_html(self) -> Path:
        return self.root / "report.html"

    @property
    def report_md(self) -> Path:
        """Markdown twin of the report; its pictures are in ``report_assets``."""
        return self.root / "report.md"

    @property
    def report_assets(self) -> Path:
        return self.root / "report_assets"
