"""``embodmocap benchmark``: the paper's two evaluation tables, reproduced on synthetic studios.

For each seed a session is synthesised into OUT (indoor and outdoor alternate: even seeds indoor,
odd seeds outdoor, unless one preset is asked for) and run through every stage (resumed when OUT
already holds it). Then, from the same Stage II observations and Stage III registrations:

Capture methods (the paper's optical-studio table), W-MPJPE / WA-MPJPE at chunks 100, 500, 1000
and RTE against the truth:

- ``monocular``: view v1's camera-space body prior alone, moved into the world with v1's cameras
  (what a monocular regressor with a calibrated camera gives);
- ``single_v1`` / ``single_v2``: that view as a one-phone session runs it: calibrated alone
  (registration + single-view refinement: Chamfer and reprojection, no track term) and Stage IV's
  one-view path (its keypoints lifted with its LiDAR depth on the person mask in place of the
  triangulation, :func:`embodmocap.motion.solve.lift_view`, then the same fit);
- ``dual``: the full pipeline;
- ``mono_colmap`` / ``mono_vio``: ``embodmocap mono`` on view v1 alone (issue 15): the camera
  path and scene from SfM on the video (metric scale from the feet on the SfM floor) or from the
  phone's VIO and depth (ablation), the body from the camera-space prior; frames it could not place
  metrically (failed SfM chunks) are left out and counted in ``invalid_frames``.

Two more dimensions of that table (issue 11): ``perception`` (``clean``: the studio's default
detector; ``hard``: every adversity of real detectors, ``embodmocap synth --perception hard``; or
``both``: each seed synthesised both ways, the hard sessions named ``<preset>_<seed>_hard``) and
the body prior: every row above uses the camera-space prior (``realistic``); ``dual`` is also
fitted without it (``prior = none``: the start from the keypoints alone, no pose prior), on the
same observations and cameras, and so are the single-view rows (the one-phone path starts from
the depth-lifted keypoints). The monocular rows need the prior, so they exist for ``prior =
realistic`` only.

Loss ablation (the paper's optimisation table), quality metrics (mask IoU, reprojection error,
depth error, jitter) and W-MPJPE: Stage III without the track / Chamfer / reprojection term, Stage IV
without smoothness / 3D keypoints, and all terms.

Writes ``OUT/benchmark.json`` (every row) and ``OUT/benchmark.md`` (both tables, means over seeds).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np

from embodmocap.io.atomic import write_json, write_text
from embodmocap.io.layout import VIEWS, SessionLayout
from embodmocap.io.stage_files import read_cameras, read_keypoints2d, read_registration, sequence_fps

log = logging.getLogger(__name__)

CAPTURE_METHODS = ("monocular", "single_v1", "single_v2", "dual")
#: The monocular pipeline's rows (``embodmocap mono`` with these scene models), beside the above.
MONO_METHODS = ("mono_colmap", "mono_vio")
ABLATIONS = ("no_track", "no_chamfer", "no_reproj", "no_smooth", "no_kp3d", "all")
_ERR_KEYS = ("w_mpjpe_mm", "wa_mpjpe_mm", "w_mpjpe_mm_c500", "wa_mpjpe_mm_c500", "w_mpjpe_mm_c1000",
             "wa_mpjpe_mm_c1000", "rte_pct")
# The frames the dual fit flagged unplaceable (left out of the figures above, as `evaluate` does) and
# W-MPJPE with them kept (what the fit put there; equal to w_mpjpe_mm when none was flagged); and
# the error in the session's world with no alignment (:func:`scored`; not for the mono rows).
_FLAG_KEYS = ("invalid_frames", "w_mpjpe_mm_incl_invalid", "world_mpjpe_mm")
# The sequence edges (issue 29): W-MPJPE at chunk 100 with a chunk starting at every frame (median
# and worst start), the first five frames' unaligned error beside the median frame's, and the frames
# with a joint > 15 cm off that the fit flagged neither invalid nor suspect (motion_errors).
_EDGE_KEYS = ("w_mpjpe_mm_all_starts_median", "w_mpjpe_mm_all_starts_worst", "first5_frame_mm", "last5_frame_mm",
              "median_frame_mm", "suspect_frames", "wrong_frames", "wrong_unflagged_pct")
_QUALITY_KEYS = ("mask_iou_pct", "reproj_err_px", "depth_err_m2", "jitter", "w_mpjpe_mm")


@dataclass(frozen=True)
class BenchmarkConfig:
    """What ``embodmocap benchmark`` synthesises and compares."""

    seeds: int = 5
    """Number of synthetic sessions (seeds 0..N-1)."""
    preset: str = "both"
    """``indoor``, ``outdoor`` or ``both`` (even seeds indoor, odd seeds outdoor)."""
    seconds: float = 6.0
    """Performance length of each sequence, seconds."""
    scene_seconds: float = 15.0
    """Length of each scene capture, seconds."""
    ablation: bool = True
    """Also run the loss ablation (about 2 minutes per seed)."""
    frames_per_view: int = 15
    """Frames per view rendered for the quality metrics of the ablation."""
    perception: Literal["clean", "hard", "both"] = "clean"
    """The studio's detector: ``clean``, ``hard`` (every adversity of real detectors) or ``both``."""
    fit_without_prior: bool = True
    """Also fit the dual view without the camera-space body prior (the ``prior = none`` rows)."""


def _preset(cfg: BenchmarkConfig, seed: int) -> str:
    return cfg.preset if cfg.preset != "both" else ("indoor" if seed % 2 == 0 else "outdoor")


def run_benchmark(out: str | Path, cfg: BenchmarkConfig = BenchmarkConfig()) -> dict:
    """Run the benchmark into ``out`` (see the module docstring); returns what it wrote."""
    from embodmocap.pipeline import PipelineConfig, run_session
    from embodmocap.synth.config import SynthConfig
    from embodmocap.synth.studio import synthesize

    out = Path(out)
    rows: list[dict] = []
    kinds = ("clean", "hard") if cfg.perception == "both" else (cfg.perception,)
    for seed in range(cfg.seeds):
        preset = _preset(cfg, seed)
        for perception in kinds:
            session = out / (f"{preset}_{seed}" if perception == "clean" else f"{preset}_{seed}_hard")
            t0 = time.perf_counter()
            try:
                if not SessionLayout(session).ground_truth.info.is_file():
                    synthesize(SynthConfig(seed=seed, preset=preset, seconds=cfg.seconds, scene_seconds=cfg.scene_seconds,
                                           perception=perception), session)
                res = run_session(PipelineConfig(), session)
                if not res.ok:
                    raise RuntimeError("; ".join(f"{r.target} {r.stage}: {r.error}" for r in res.failed()))
                row = {"seed": seed, "preset": preset, "perception": perception, **_one_session(session, cfg)}
            except Exception as err:  # noqa: BLE001 - a failed seed is reported in the tables, not hidden
                log.warning("seed %d (%s) failed: %s", seed, perception, err)
                row = {"seed": seed, "preset": preset, "perception": perception, "error": f"{type(err).__name__}: {err}"}
            row["seconds"] = round(time.perf_counter() - t0, 1)
            rows.append(row)
            # The tables so far after every session: a long run stopped early still leaves its rows.
            _write_tables(out, cfg, rows)
            log.info("benchmark seed %d (%s, %s) done in %.0f s", seed, preset, perception, row["seconds"])
    return _write_tables(out, cfg, rows)


def _write_tables(out: Path, cfg: BenchmarkConfig, rows: list[dict]) -> dict:
    result = {"version": 1, "config": cfg.__dict__, "rows": rows}
    write_json(out / "benchmark.json", result)
    write_text(out / "benchmark.md", tables_markdown(rows))
    return result


def _one_session(session: Path, cfg: BenchmarkConfig) -> dict:
    """Every capture method and ablation variant of one processed session."""
    from embodmocap.body.model import load_body_model
    from embodmocap.evaluate.session import EvaluateConfig, motion_errors, quality_metrics
    from embodmocap.evaluate.truth import sequence_truth
    from embodmocap.io.manifest import load_manifest

    lay = SessionLayout(session)
    manifest = load_manifest(lay.manifest)
    seq = next(iter(manifest.sequences))
    scene = manifest.sequences[seq].scene
    model = load_body_model(manifest.body_model)
    truth = sequence_truth(lay, scene, seq)
    ecfg = EvaluateConfig(frames_per_view=cfg.frames_per_view)
    ctx = _Context(lay, seq, scene, model)

    methods: dict[str, dict] = {}
    # Dual: the pipeline's own result. Frames Stage IV flagged unplaceable (``valid`` False in
    # smpl_world.npz: e.g. one view sees nobody) are scored as ``evaluate`` scores them: left out,
    # counted in ``invalid_frames``, with ``w_mpjpe_mm_incl_invalid`` beside. Every capture method
    # is scored on the same frames, so the rows compare like with like.
    dual_params, frames = ctx.final_params()
    dual_valid = ctx.final_valid()
    methods["dual"] = scored(ctx.joints(dual_params), frames, truth, dual_valid, ctx.final_suspect())
    # Monocular: v1's prior through v1's calibrated cameras.
    mono = ctx.prior_in_world("v1", ctx.cameras("v1"))
    methods["monocular"] = scored(ctx.joints(mono), np.arange(len(mono)), truth,
                                  same_frames(frames, dual_valid, len(mono)))
    single_cams = {v: ctx.single_view_cameras(v) for v in VIEWS}
    for v in VIEWS:
        params = ctx.fit(single_view=v, cameras={v: single_cams[v]})
        methods[f"single_{v}"] = scored(ctx.joints(params), np.arange(len(params)), truth,
                                        same_frames(frames, dual_valid, len(params)))
    for name in MONO_METHODS:
        methods[name] = mono_errors(session, seq, name.split("_", 1)[1], truth, frames, dual_valid, ctx)
    result = {"methods": methods}
    if cfg.fit_without_prior:
        params, valid, suspect = ctx.fit(cameras={v: ctx.cameras(v) for v in VIEWS}, prior=False, flagged=True)
        result["methods_no_prior"] = {"dual": scored(ctx.joints(params), np.arange(len(params)), truth, valid, suspect)}
        for v in VIEWS:  # the one-phone path without a prior (each view alone: the figure)
            params, valid, suspect = ctx.fit(single_view=v, cameras={v: single_cams[v]}, prior=False, flagged=True)
            result["methods_no_prior"][f"single_{v}"] = scored(ctx.joints(params), np.arange(len(params)), truth,
                                                               valid, suspect)
    if cfg.ablation:
        ablation: dict[str, dict] = {}
        for name in ABLATIONS:
            cams = ctx.calibrated_cameras(name)
            params = ctx.fit(cameras=cams, variant=name)
            q = quality_metrics(lay, seq, model, params, cams, ecfg)
            q["w_mpjpe_mm"] = motion_errors(ctx.joints(params), np.arange(len(params)), truth)["w_mpjpe_mm"]
            ablation[name] = {k: q.get(k) for k in _QUALITY_KEYS}
        result["ablation"] = ablation
    return result


def scored(joints: np.ndarray, frames: np.ndarray, truth, valid: np.ndarray | None = None,
           suspect: np.ndarray | None = None) -> dict:
    """:func:`~embodmocap.evaluate.session.motion_errors` plus ``world_mpjpe_mm``: the mean joint
    error in the session's own world (Stage I's, where the truth is expressed) with no alignment at
    all, on the same frames. W-MPJPE re-anchors each chunk on its first two frames, so a few mm of
    pose error in those two frames turns the whole chunk (W-MPJPE at chunk 1000 of a 6 s session
    is set by two frames); the unaligned error says how far the output really is from the truth.
    joints: (T, 24, 3) at sequence ``frames`` (T,); ``valid``, ``suspect`` (T,) bool as motion_errors."""
    from embodmocap.evaluate.session import motion_errors

    out = motion_errors(joints, frames, truth, valid, suspect)
    ok = truth.valid[frames] & (np.ones(len(frames), dtype=bool) if valid is None else np.asarray(valid, dtype=bool))
    err = np.linalg.norm(np.asarray(joints)[ok] - truth.joints[frames][ok], axis=-1)
    out["world_mpjpe_mm"] = round(1000 * float(err.mean()), 2) if err.size else float("nan")
    return out


def mono_errors(session: Path, seq: str, scene_model: str, truth, frames: np.ndarray, dual_valid: np.ndarray,
                ctx) -> dict:
    """``embodmocap mono`` on view v1 with ``scene_model`` and the body prior (resumed when done),
    scored like the other rows on the frames the dual fit placed; its own invalid frames (no
    metric scale) are left out and counted. A failure is the row's ``error``, not the seed's."""
    from embodmocap.evaluate.session import motion_errors
    from embodmocap.io.smpl_file import read_smpl_npz, read_smpl_valid
    from embodmocap.mono import stage as mono_stage
    from embodmocap.mono.config import MonoConfig

    try:
        out = mono_stage.run(MonoConfig(scene_model=scene_model, human_model="prior"), session, seq, "v1")
        params, _ = read_smpl_npz(out.layout.smpl_world)
        valid = read_smpl_valid(out.layout.smpl_world)
    except Exception as err:  # noqa: BLE001 - reported in the row
        log.warning("mono %s on %s failed: %s", scene_model, session, err)
        return {"error": f"{type(err).__name__}: {err}"}
    n = len(params)
    return {**motion_errors(ctx.joints(params), np.arange(n), truth, valid & same_frames(frames, dual_valid, n)),
            "mono_segments": int(out.figures.get("segments", 1))}


def same_frames(frames: np.ndarray, valid: np.ndarray, n: int) -> np.ndarray:
    """(n,) bool over sequence frames 0..n-1: False where the dual fit flagged its frame
    ``frames[i]`` invalid (``valid`` (F,) bool), so another method is scored on the same frames."""
    out = np.ones(n, dtype=bool)
    bad = np.asarray(frames)[~np.asarray(valid, dtype=bool)]
    out[bad[(bad >= 0) & (bad < n)]] = False
    return out


class _Context:
    """Reads one processed session once and re-runs Stages III and IV's solve functions
    (:mod:`embodmocap.calibrate.solve`, :mod:`embodmocap.motion.solve`) with other settings."""

    def __init__(self, lay: SessionLayout, seq: str, scene: str, model) -> None:
        self.lay, self.seq, self.scene, self.model = lay, seq, scene, model
        self.sl = lay.sequence(seq)
        self._scene_points = None
        self._views = None

    def final_params(self):
        from embodmocap.io.smpl_file import read_smpl_npz

        return read_smpl_npz(self.sl.smpl_world)

    def final_valid(self) -> np.ndarray:
        from embodmocap.io.smpl_file import read_smpl_valid

        return read_smpl_valid(self.sl.smpl_world)

    def final_suspect(self) -> np.ndarray:
        from embodmocap.io.smpl_file import read_smpl_suspect

        return read_smpl_suspect(self.sl.smpl_world)

    def joints(self, params) -> np.ndarray:
        import torch

        with torch.no_grad():
            return self.model.from_params(params, dtype=torch.float64).joints.numpy()

    def cameras(self, v: str) -> np.ndarray:
        return read_cameras(self.sl.view(v).cameras_world).T_world_cam

    def _T(self) -> int:
        return min(len(read_keypoints2d(self.sl.view(v).keypoints).keypoints) for v in self.sl.views())

    def _priors(self, min_fraction: float, T: int | None = None) -> dict:
        from embodmocap.io.body_prior import body_priors_by_frame

        return body_priors_by_frame({u: self.sl.view(u).body_prior for u in self.sl.views()}, self._T() if T is None else T,
                                    min_fraction, self.seq)

    def prior_in_world(self, v: str, T_world_cam: np.ndarray):
        from embodmocap.motion.init import init_from_prior

        T = self._T()
        priors = self._priors(0.0)
        if v not in priors:
            raise RuntimeError(f"view {v} has no body prior")
        return init_from_prior(self.model, priors[v][0], T_world_cam[:T], sequence_fps(self.sl))

    # -- Stage III variants

    def _calibrate(self, views: tuple[str, ...], refine_cfg) -> dict[str, np.ndarray]:
        """view -> (T, 4, 4) cameras after refining ``views`` (alone or jointly) with ``refine_cfg``."""
        from embodmocap.calibrate import solve as s3
        from embodmocap.calibrate.config import CalibrateConfig
        from embodmocap.calibrate.stage import view_inputs
        from embodmocap.io.mesh_file import read_mesh_ply

        cfg = CalibrateConfig()
        if self._scene_points is None:
            mv, mf, _ = read_mesh_ply(self.lay.scene(self.scene).mesh_raw)
            self._scene_points = s3.scene_points(cfg, mv, mf)
        if self._views is None:
            self._views = {v: view_inputs(self.sl, v) for v in VIEWS}
        regs = {v: read_registration(self.sl.view(v).registration) for v in VIEWS}
        # As Stage III does: the offset from the VIO-consistent chain only (rejected runs left out).
        init, _ = s3.initial_offsets(cfg, self._views, regs)
        tracks = s3.track_pairs(self._views) if len(views) == 2 and refine_cfg.w_track > 0 else None
        return s3.refine_cameras(self._views, {v: init[v] for v in views}, regs, refine_cfg, cfg,
                                 self._scene_points, tracks)

    def single_view_cameras(self, v: str) -> np.ndarray:
        from embodmocap.calibrate.config import RefineConfig

        return self._calibrate((v,), RefineConfig())[v]

    def calibrated_cameras(self, variant: str) -> dict[str, np.ndarray]:
        from embodmocap.calibrate.config import RefineConfig

        if variant not in ("no_track", "no_chamfer", "no_reproj"):
            return {v: self.cameras(v) for v in VIEWS}
        weights = {"no_track": {"w_track": 0.0}, "no_chamfer": {"w_chamfer": 0.0}, "no_reproj": {"w_reproj": 0.0}}[variant]
        return self._calibrate(VIEWS, replace(RefineConfig(), **weights))

    # -- Stage IV variants

    def fit(self, cameras: dict[str, np.ndarray], single_view: str | None = None, variant: str = "all",
            prior: bool = True, flagged: bool = False):
        """The motion fitted with ``cameras`` through Stage IV's own steps: dual view
        (:func:`embodmocap.motion.solve.triangulate_views`, :func:`~embodmocap.motion.solve.fit_motion`)
        or ``single_view`` (a one-phone sequence's path: :func:`~embodmocap.motion.solve.lift_view`
        with the view's LiDAR depth, then the same fit), with ``variant``'s terms switched off and,
        with ``prior=False``, no body prior. ``flagged``: return ``(params, valid, suspect)``, the
        (T,) placeable and suspect frames too."""
        from embodmocap.motion import solve as s4
        from embodmocap.motion.config import MotionConfig
        from embodmocap.motion.stage import keypoint_layout

        mcfg = MotionConfig()
        scfg = mcfg.smplify
        if variant == "no_smooth":
            scfg = replace(scfg, w_joint_vel=0.0, w_joint_acc=0.0, w_transl_vel=0.0, w_transl_acc=0.0)
        elif variant == "no_kp3d":
            scfg = replace(scfg, w_kp3d=0.0)
        mcfg = replace(mcfg, smplify=scfg, use_body_prior=prior)
        T = self._T()
        layout = keypoint_layout(self.sl, self.seq)
        fps = sequence_fps(self.sl)
        views = [single_view] if single_view else list(VIEWS)
        kps = {v: read_keypoints2d(self.sl.view(v).keypoints).keypoints[:T] for v in views}
        cams = {v: {"K": read_cameras(self.sl.view(v).cameras).K, "T_world_cam": cameras[v]} for v in views}
        if single_view:
            from embodmocap.motion.stage import view_depth

            # A one-phone sequence's Stage IV on this view alone: its keypoints lifted with its
            # LiDAR depth on the person mask, then the same fit (motion.solve.lift_view).
            tri = s4.lift_view(mcfg, cams, kps, T, *view_depth(self.sl, single_view, mcfg), self.seq)
            priors = {single_view: p for v, p in self._priors(mcfg.min_prior_fraction, T).items()
                      if v == single_view} if prior else {}
        else:
            from embodmocap.sequence.subframe import synced_views

            # As Stage IV: view 2's keypoints and cameras resampled at view 1's instants (the
            # sub-frame sync of sync.json), so a variant differs from the pipeline only in its term.
            kps = {v: read_keypoints2d(self.sl.view(v).keypoints).keypoints for v in views}
            cams, kps = synced_views(self.sl, cams, kps)
            T = min(len(kps[v]) for v in VIEWS)
            tri = s4.triangulate_views(mcfg, cams, kps, T, self.seq)
            priors = self._priors(mcfg.min_prior_fraction, T) if prior else {}
        from embodmocap.motion.floor import scene_floor_z
        from embodmocap.motion.stage import scene_mesh

        floor_z = scene_floor_z(scene_mesh(mcfg, self.lay, self.scene), mcfg.smplify.floor_max_tilt_deg, self.seq)
        fitted = s4.fit_motion(mcfg, self.model, tri.file, cams, kps, T, fps, priors, layout, label=self.seq,
                               floor_z=floor_z)
        return (fitted.params, fitted.valid, fitted.quality.suspect) if flagged else fitted.params


def tables_markdown(rows: list[dict]) -> str:
    """Both tables as Markdown: means over the seeds that succeeded (failed seeds listed)."""
    ok = [r for r in rows if "error" not in r]
    lines = [f"Seeds: {len(ok)} of {len(rows)} succeeded"
             + "".join(f"; seed {r['seed']} ({r['preset']}) failed: {r['error']}" for r in rows if "error" in r), ""]
    lines += ["### Capture methods (W-/WA-MPJPE in mm at chunk 100 / 500 / 1000, RTE in %)", "",
              "| method | prior | perception | sessions | " + " | ".join(_ERR_KEYS + _FLAG_KEYS) + " |",
              "|---|---|---|---|" + "---|" * len(_ERR_KEYS + _FLAG_KEYS)]
    for perception in ("clean", "hard"):
        sel = [r for r in ok if r.get("perception", "clean") == perception]
        if not sel:
            continue
        for m in CAPTURE_METHODS:
            vals = [np.mean([_err(r["methods"][m], k) for r in sel]) for k in _ERR_KEYS + _FLAG_KEYS]
            lines.append(f"| {m} | realistic | {perception} | {len(sel)} | " + " | ".join(f"{x:.2f}" for x in vals) + " |")
        for m in MONO_METHODS:  # rows written before the monocular pipeline existed have none
            has = [r for r in sel if "error" not in r["methods"].get(m, {"error": ""})]
            if has:
                vals = [np.mean([_err(r["methods"][m], k) for r in has]) for k in _ERR_KEYS + _FLAG_KEYS]
                lines.append(f"| {m} | realistic | {perception} | {len(has)} | " + " | ".join(f"{x:.2f}" for x in vals)
                             + " |")
        for m in ("single_v1", "single_v2", "dual"):  # single rows: only in results written since session 7
            nop = [r for r in sel if m in r.get("methods_no_prior", {})]
            if nop:
                vals = [np.mean([_err(r["methods_no_prior"][m], k) for r in nop]) for k in _ERR_KEYS + _FLAG_KEYS]
                lines.append(f"| {m} | none | {perception} | {len(nop)} | " + " | ".join(f"{x:.2f}" for x in vals) + " |")
    lines += edge_table(ok)
    abl = [r for r in ok if "ablation" in r]
    if abl:
        lines += ["", "### Loss ablation (quality metrics; W-MPJPE in mm at chunk 100)", "",
                  "| variant | " + " | ".join(_QUALITY_KEYS) + " |", "|---|" + "---|" * len(_QUALITY_KEYS)]
        for a in ABLATIONS:
            vals = [np.mean([r["ablation"][a][k] for r in abl if r["ablation"][a].get(k) is not None] or [np.nan])
                    for k in _QUALITY_KEYS]
            lines.append(f"| {a} | " + " | ".join(f"{x:.4g}" for x in vals) + " |")
    return "\n".join(lines) + "\n"


def edge_table(ok: list[dict]) -> list[str]:
    """The dual rows' sequence-edge figures (issue 29), per session plus median and worst, as
    Markdown lines (none when no row has them: rows written before they were scored)."""
    rows = [(f"{r['preset']} {r['seed']} {r.get('perception', 'clean')}", prior, r[key]["dual"])
            for r in ok for key, prior in (("methods", "realistic"), ("methods_no_prior", "none"))
            if key in r and "w_mpjpe_mm_all_starts_median" in r[key]["dual"]]
    if not rows:
        return []
    lines = ["", "### Sequence edges, dual (mm; W-MPJPE at chunk 100 with a chunk at every start; unaligned "
             "error of the first / last five frames and the median frame; frames with a joint > 15 cm off)", "",
             "| session | prior | " + " | ".join(_EDGE_KEYS) + " | first5 / median |", "|---|---|" + "---|" * (len(_EDGE_KEYS) + 1)]
    for name, prior, x in rows:
        vals = [_err(x, k) for k in _EDGE_KEYS] + [_err(x, "first5_frame_mm") / max(_err(x, "median_frame_mm"), 1e-9)]
        lines.append(f"| {name} | {prior} | " + " | ".join(f"{v:.2f}" for v in vals) + " |")
    for prior in ("realistic", "none"):
        sel = [x for _, p, x in rows if p == prior]
        if sel:
            med = [np.median([_err(x, k) for x in sel]) for k in _EDGE_KEYS]
            worst = [np.max([_err(x, k) for x in sel]) for k in _EDGE_KEYS]
            ratio = [_err(x, "first5_frame_mm") / max(_err(x, "median_frame_mm"), 1e-9) for x in sel]
            lines.append(f"| median of {len(sel)} | {prior} | " + " | ".join(f"{v:.2f}" for v in med)
                         + f" | {np.median(ratio):.2f} |")
            lines.append(f"| worst of {len(sel)} | {prior} | " + " | ".join(f"{v:.2f}" for v in worst)
                         + f" | {np.max(ratio):.2f} |")
    return lines


def _err(x: dict, k: str) -> float:
    """One figure of a method's errors; rows written before the valid flags were scored count 0
    invalid frames, and W-MPJPE with the flagged frames kept is W-MPJPE when none was flagged."""
    if k == "w_mpjpe_mm_incl_invalid":
        return x.get(k, x["w_mpjpe_mm"])
    if k == "world_mpjpe_mm" or k in _EDGE_KEYS:  # rows written before it was scored (and the mono rows) have none
        return x.get(k, float("nan"))
    return x.get(k, 0) if k == "invalid_frames" else x[k]


def summary(result: dict) -> str:
    """The Markdown tables plus the issue's two checks on the capture-methods table."""
    rows = [r for r in result["rows"] if "error" not in r]
    text = tables_markdown(result["rows"])
    if rows:
        mean = lambda m, k: float(np.mean([r["methods"][m][k] for r in rows]))  # noqa: E731
        best_single = min(mean("single_v1", "w_mpjpe_mm_c1000"), mean("single_v2", "w_mpjpe_mm_c1000"))
        ratio = best_single / max(mean("dual", "w_mpjpe_mm_c1000"), 1e-9)
        beats_mono = all(mean("dual", k) < mean("monocular", k) for k in ("w_mpjpe_mm", "w_mpjpe_mm_c500", "w_mpjpe_mm_c1000"))
        text += (f"\nDual view vs the better single view, W-MPJPE chunk 1000: {ratio:.2f}x more accurate; "
                 f"dual better than monocular at every chunk size: {beats_mono}\n")
        for m in MONO_METHODS:
            has = [r for r in rows if "error" not in r["methods"].get(m, {"error": ""})]
            if has:
                better = all(np.mean([r["methods"]["dual"][k] for r in has]) < np.mean([r["methods"][m][k] for r in has])
                             for k in ("w_mpjpe_mm", "w_mpjpe_mm_c500", "w_mpjpe_mm_c1000", "rte_pct"))
                text += f"Dual view better than {m} at every chunk size and in RTE ({len(has)} sessions): {better}\n"
        nop = [r for r in rows if "methods_no_prior" in r]
        if nop:
            q = [r["methods_no_prior"]["dual"]["w_mpjpe_mm"] / max(r["methods"]["dual"]["w_mpjpe_mm"], 1e-9) for r in nop]
            text += f"Dual view without / with the body prior, W-MPJPE chunk 100, median over sessions: {np.median(q):.2f}\n"
    return text
