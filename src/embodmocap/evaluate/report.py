"""``embodmocap report``: one self-contained HTML page per session, and a Markdown twin.

The page holds, per sequence: the metrics of ``evaluation.json`` (computed first when missing),
a top-down floor plan of the scene with both camera paths and the performer's path, the error of
each joint over time (against ground truth when there is some, else the reprojection error), the
residuals and timings of every stage, the sync contact sheets, and a few frames of each view with
the fitted body drawn over them. Pictures are PNGs made with matplotlib (Agg backend, no screen),
embedded in the HTML as data URIs and written to ``report_assets/`` for the Markdown file.
"""

from __future__ import annotations

import base64
import html
import io
import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from embodmocap.errors import InputError
from embodmocap.io.atomic import write_bytes, write_text
from embodmocap.io.layout import SessionLayout
from embodmocap.io.manifest import load_manifest
from embodmocap.io.stage_files import (
    read_calibration, read_cameras, read_evaluation, read_keypoints3d, read_report_json, read_stage_record, read_world_joints,
    sequence_fps,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ReportConfig:
    """What the report shows."""

    overlay_frames: int = 3
    """Frames per view shown with the fitted body drawn over them."""
    floor_points: int = 60000
    """Points sampled on the scene mesh for the floor plan."""
    plan_cut_m: float = 1.8
    """The floor plan shows the scene up to this height above the floor (the ceiling would hide it)."""


@dataclass
class _Page:
    """The report being built: HTML and Markdown side by side, pictures kept for both."""

    assets: Path
    html_parts: list[str]
    md_parts: list[str]

    def heading(self, text: str, level: int = 2) -> None:
        self.html_parts.append(f"<h{level}>{html.escape(text)}</h{level}>")
        self.md_parts.append(f"{'#' * level} {text}\n")

    def para(self, text: str) -> None:
        self.html_parts.append(f"<p>{html.escape(text)}</p>")
        self.md_parts.append(text + "\n")

    def table(self, header: list[str], rows: list[list]) -> None:
        h = "".join(f"<th>{html.escape(str(c))}</th>" for c in header)
        body = "".join("<tr>" + "".join(f"<td>{html.escape(_fmt(c))}</td>" for c in r) + "</tr>" for r in rows)
        self.html_parts.append(f"<table><thead><tr>{h}</tr></thead><tbody>{body}</tbody></table>")
        self.md_parts.append("| " + " | ".join(header) + " |\n|" + "---|" * len(header) + "\n"
                             + "".join("| " + " | ".join(_fmt(c) for c in r) + " |\n" for r in rows))

    def image(self, name: str, png: bytes, caption: str) -> None:
        write_bytes(self.assets / name, png)
        uri = "data:image/png;base64," + base64.b64encode(png).decode("ascii")
        self.html_parts.append(f'<figure><img src="{uri}" alt="{html.escape(caption)}">'
                               f"<figcaption>{html.escape(caption)}</figcaption></figure>")
        self.md_parts.append(f"![{caption}]({self.assets.name}/{name})\n")


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, (list, dict)):
        return json.dumps(v)
    return str(v)


_STYLE = """body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;margin:.5em 0 1.5em}td,th{border:1px solid #ccc;padding:3px 8px;text-align:left;
font-size:14px}th{background:#f3f3f3}img{max-width:100%}figure{margin:1em 0}figcaption{color:#555;font-size:13px}"""


def write_report(session: str | Path, cfg: ReportConfig = ReportConfig()) -> tuple[Path, Path]:
    """Write ``report.html`` and ``report.md`` for ``session``; returns their paths."""
    from embodmocap.evaluate.session import evaluate_session

    lay = SessionLayout(Path(session))
    manifest = load_manifest(lay.manifest)
    evaluation = read_evaluation(lay.evaluation) if lay.evaluation.is_file() else evaluate_session(lay.root)
    page = _Page(lay.report_assets, [], [])
    page.heading(f"EmbodMocap report: {lay.root.name}", 1)
    page.para(f"Session {lay.root}; ground truth: {'yes' if evaluation.get('ground_truth') else 'no'}.")
    for name, m in evaluation.get("scene", {}).items():
        page.heading(f"Scene {name}")
        page.table(["metric", "value"], [[k, v] for k, v in m.items()])
    for name in manifest.scenes:
        _stage_table(page, f"Stage I ({name})", lay.scene(name).manifest)
    for name, entry in manifest.sequences.items():
        page.heading(f"Sequence {name}")
        m = evaluation.get("sequences", {}).get(name, {})
        page.table(["metric", "value"], [[k, v] for k, v in m.items()])
        sl = lay.sequence(name)
        if not sl.smpl_world.is_file() or "missing" in m:  # unfitted, or a stage failed / is out of date
            continue
        page.image(f"{name}_floorplan.png", _floor_plan(lay, entry.scene, name, cfg), "Top-down view: scene, camera paths, performer path")
        page.image(f"{name}_errors.png", _error_plot(lay, entry.scene, name, manifest.body_model, evaluation.get("ground_truth")),
                   "Error per joint over time")
        _stage_table(page, "Stage II", sl.manifest)
        _stage_table(page, "Stage III", sl.calibrate_manifest)
        if sl.calibration.is_file():
            _calibration_table(page, read_calibration(sl.calibration).record)
        _stage_table(page, "Stage IV", sl.motion_manifest)
        _sim_check_section(page, sl.sim_check)
        for v in sl.views():
            sheet = sl.sync_sheet(v)
            if sheet.is_file():
                page.image(f"{name}_sync_{v}.png", sheet.read_bytes(), f"Sync contact sheet, {v}")
        for v in sl.views():
            page.image(f"{name}_overlay_{v}.png", _overlays(lay, entry, name, v, manifest.body_model, cfg),
                       f"{v}: fitted body over the RGB frames")
        _robot_tables(page, sl.robots_dir)
        _skills_section(page, sl.skills_json, name)
    doc = (f"<!doctype html><html><head><meta charset='utf-8'><title>EmbodMocap report: {html.escape(lay.root.name)}"
           f"</title><style>{_STYLE}</style></head><body>{''.join(page.html_parts)}</body></html>")
    write_text(lay.report_html, doc)
    write_text(lay.report_md, "\n".join(page.md_parts))
    return lay.report_html, lay.report_md


def _stage_table(page: _Page, title: str, manifest_path: Path) -> None:
    """Steps with their seconds, then the stage's figures."""
    if not manifest_path.is_file():
        return
    man = read_stage_record(manifest_path)
    page.heading(title, 3)
    steps = man.steps
    page.table(["step", "seconds", "finished"], [[k, s.get("seconds"), s.get("finished", "")] for k, s in steps.items()])
    figs = {k: v for k, v in man.figures.items() if k != "T_align"}
    if figs:
        page.table(["figure", "value"], [[k, v] for k, v in figs.items()])


def _calibration_table(page: _Page, calib: dict) -> None:
    ref = calib.get("refine", {})
    rows = [[k, ref.get("terms_before", {}).get(k), ref.get("terms_after", {}).get(k)] for k in ref.get("terms_before", {})]
    if rows:
        page.para(f"Stage III refinement: solver {ref.get('solver')}, loss {_fmt(ref.get('loss_before'))} -> "
                  f"{_fmt(ref.get('loss_after'))}.")
        page.table(["term", "before", "after"], rows)
    for w in calib.get("warnings", []):
        page.para(f"Warning: {w}")


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return buf.getvalue()


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _floor_plan(lay: SessionLayout, scene: str, seq: str, cfg: ReportConfig) -> bytes:
    from embodmocap.io.mesh_file import read_mesh_ply

    plt = _plt()
    sl = lay.sequence(seq)
    fig, ax = plt.subplots(figsize=(7, 7))
    mesh = lay.scene(scene).mesh_simplified if lay.scene(scene).mesh_simplified.is_file() else lay.scene(scene).mesh_raw
    if mesh.is_file():
        from embodmocap.evaluate.mesh_metrics import sample_surface

        v, f, _ = read_mesh_ply(mesh)
        # Points spread over the surface (not the vertices: large flat triangles have few), drawn
        # lowest first so walls and furniture stay on top of the floor.
        p = sample_surface(v, f, cfg.floor_points) if len(f) else v
        # Cut like an architect's plan, below the ceiling.
        p = p[p[:, 2] < np.percentile(p[:, 2], 2) + cfg.plan_cut_m]
        p = p[np.argsort(p[:, 2])]
        sc = ax.scatter(p[:, 0], p[:, 1], c=p[:, 2], s=0.3, cmap="Greys", alpha=0.6)
        fig.colorbar(sc, ax=ax, fraction=0.04, label="height (m)")
    for v, colour in zip(sl.views(), ("tab:blue", "tab:orange")):
        c = read_cameras(sl.view(v).cameras_final).T_world_cam[:, :3, 3]
        ax.plot(c[:, 0], c[:, 1], color=colour, lw=1.5, label=f"camera {v}")
        ax.plot(*c[0, :2], "o", color=colour)
    pelvis = read_world_joints(sl.joints_world).joints[:, 0]
    ax.plot(pelvis[:, 0], pelvis[:, 1], color="tab:red", lw=2, label="performer (pelvis)")
    ax.plot(*pelvis[0, :2], "o", color="tab:red")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(f"{seq}: top-down (Z up); dots mark the start")
    return _png(fig)


def _error_plot(lay: SessionLayout, scene: str, seq: str, body_model, has_gt: bool) -> bytes:
    """Per-joint world error over time against ground truth, or the reprojection error without it."""
    from embodmocap.body.joints import SMPL_JOINT_NAMES

    plt = _plt()
    sl = lay.sequence(seq)
    fig, ax = plt.subplots(figsize=(10, 4))
    wj = read_world_joints(sl.joints_world)  # frames 0..T-1 for files written without them
    joints, frames = wj.joints, wj.frames
    fps = sequence_fps(sl)
    t = frames / float(fps)
    if has_gt:
        from embodmocap.evaluate.truth import sequence_truth

        truth = sequence_truth(lay, scene, seq)
        err = 1000 * np.linalg.norm(joints - truth.joints[frames], axis=-1)  # (T, 24) mm, no alignment
        err[~truth.valid[frames]] = np.nan
        for j in (0, 7, 8, 15, 20, 21):  # pelvis, ankles, head, wrists
            ax.plot(t, err[:, j], lw=1, label=SMPL_JOINT_NAMES[j])
        ax.plot(t, np.nanmean(err, axis=1), color="k", lw=2, label="mean (MPJPE)")
        ax.set_ylabel("world error, no alignment (mm)")
    else:
        for i, v in enumerate(sl.views()):
            k3 = read_keypoints3d(sl.keypoints3d)
            e = k3["reproj_err_px"][..., i]
            ax.plot(t[: len(e)], np.nanmean(e, axis=1), lw=1, label=f"{v}: triangulation reprojection")
        ax.set_ylabel("pixels")
    ax.set_xlabel("time (s)")
    ax.legend(fontsize=8, ncol=4)
    ax.grid(alpha=0.3)
    return _png(fig)


def _overlays(lay: SessionLayout, entry, seq: str, view: str, body_model, cfg: ReportConfig) -> bytes:
    """A strip of ``cfg.overlay_frames`` frames with the fitted body's silhouette blended in."""
    import torch

    from embodmocap.body.model import load_body_model
    from embodmocap.io.captures import open_capture
    from embodmocap.io.smpl_file import read_smpl_npz
    from embodmocap.types import Intrinsics
    from embodmocap.viz.render import body_pixels, overlay

    plt = _plt()
    sl = lay.sequence(seq)
    model = load_body_model(body_model)
    params, frames = read_smpl_npz(sl.smpl_world)
    cams = read_cameras(sl.view(view).cameras_final)
    K = Intrinsics.from_K(cams["K"], int(cams["width"]), int(cams["height"]))
    capture = open_capture(entry.views[view].capture)
    pick = np.unique(np.linspace(0, len(frames) - 1, cfg.overlay_frames + 2)[1:-1].astype(int))
    with torch.no_grad():
        verts = model.forward(params.betas, params.global_orient[pick], params.body_pose[pick], params.transl[pick],
                              dtype=torch.float64).vertices.numpy()
    fig, axes = plt.subplots(1, len(pick), figsize=(4 * len(pick), 3.2))
    for ax, i, v in zip(np.atleast_1d(axes), pick, verts):
        t = int(frames[i])
        rgb = np.asarray(capture.frames.rgb(int(cams["raw_frames"][t])))
        ax.imshow(overlay(rgb, body_pixels(K, cams["T_world_cam"][t], v, model.faces)))
        ax.set_title(f"{view} frame {t}", fontsize=9)
        ax.axis("off")
    return _png(fig)


#: Figures of ``robot_report.json`` shown in the report, with their labels.
_ROBOT_FIGURES: tuple[tuple[str, str], ...] = (
    ("scale", "scale (robot / human leg length)"),
    ("keypoint_residual_mean_m", "keypoint residual mean (m)"),
    ("keypoint_residual_max_m", "keypoint residual max (m)"),
    ("joint_limit_violations", "joint-limit violations"),
    ("joint_speed_max_ratio", "peak joint speed / its limit"),
    ("joint_speed_worst_joint", "joint closest to its speed limit"),
    ("foot_skating_max_m", "foot skating during contacts, max (m)"),
    ("foot_penetration_max_m", "foot penetration into the scene, max (m)"),
    ("self_collision_frames", "self-collision frames"),
    ("frames", "frames"),
)


def _robot_tables(page: _Page, robot_root: Path) -> None:
    """One table per retargeted robot of the sequence (``robot/<robot>/robot_report.json``)."""
    for path in sorted(robot_root.glob("*/robot_report.json")) if robot_root.is_dir() else []:
        try:
            rep = read_report_json(path, "robot report", "embodmocap robot retarget")
        except InputError:
            page.para(f"Robot {path.parent.name}: unreadable {path.name}")
            continue
        page.heading(f"Robot {rep.get('robot', path.parent.name)}", 3)
        page.table(["figure", "value"], [[label, rep.get(key)] for key, label in _ROBOT_FIGURES])


def _sim_check_section(page: _Page, path: Path) -> None:
    """Physical plausibility (``embodmocap sim check``), when it was run."""
    if not path.is_file():
        return
    s = read_report_json(path, "sim check", "embodmocap sim check")["summary"]
    page.heading("Physical plausibility (sim check)", 3)
    keys = ("penetration_max_cm", "penetration_mean_cm", "floating_max_cm", "floating_mean_cm", "unsupported_frames",
            "foot_skating_mean_cm",
            "residual_force_n_per_kg_mean", "residual_torque_nm_per_kg_mean", "mass_kg")
    page.table(["figure", "value"], [[k, s[k]] for k in keys if k in s])
    if s.get("unsupported_frames"):  # said plainly: those frames' floating is not measured
        n, total = int(s["unsupported_frames"]), max(int(s.get("frames", 0)), 1)
        page.para(f"Note: {n} of {total} frames ({100.0 * n / total:.0f} %) have no scene surface under the body "
                  "(a hole in the scene mesh, e.g. floor the scan never saw): floating is not measured on them "
                  "and penetration may be missed; the figures describe the other frames.")
    page.table(["body part", "contact fraction"], [[k, v] for k, v in s.get("contact_fraction", {}).items()])


#: Colours of the six skills in the report's clip timeline.
_SKILL_COLOURS = {"follow": "tab:blue", "sit": "tab:green", "climb": "tab:orange", "lie": "tab:purple",
                  "prone": "tab:brown", "support": "tab:red"}


def _skills_section(page: _Page, path: Path, seq: str) -> None:
    """The skill clips (``embodmocap skills``), when found: a timeline and one row per clip."""
    if not path.is_file():
        return
    from embodmocap.io.stage_files import read_skills

    try:
        sf = read_skills(path)
    except InputError as e:
        page.para(f"Skill clips: {e}")
        return
    page.heading("Skill clips", 3)
    counts = {k: len(sf.of_skill(k)) for k in _SKILL_COLOURS}
    page.para(f"{len(sf.clips)} clips in {sf.n_frames} frames at {sf.fps:g} fps: "
              + ", ".join(f"{k} {n}" for k, n in counts.items()) + ".")
    if not sf.clips:
        return
    plt = _plt()
    fig, ax = plt.subplots(figsize=(9, 2.2))
    rows = list(_SKILL_COLOURS)
    for c in sf.clips:
        y = rows.index(c.skill)
        ax.barh(y, (c.end - c.start) / sf.fps, left=c.start / sf.fps, color=_SKILL_COLOURS[c.skill], alpha=0.5)
        if c.contact_start is not None:
            ax.barh(y, (c.contact_end - c.contact_start) / sf.fps, left=c.contact_start / sf.fps,
                    color=_SKILL_COLOURS[c.skill])
    ax.set_yticks(range(len(rows)), rows)
    ax.set_xlim(0, sf.n_frames / sf.fps)
    ax.set_xlabel("time (s)")
    ax.set_title(f"{seq}: skill clips (dark: the contact hold)")
    page.image(f"{seq}_skills.png", _png(fig), "Skill clips over time")
    table = []
    for c in sf.clips:
        size = "" if c.object is None else " x ".join(f"{x:.2f}" for x in c.object.size)
        tgt = c.target.position if c.target.position is not None else (f"path of {len(c.target.path)} waypoints"
                                                                      if c.target.path else "")
        if isinstance(tgt, list):
            tgt = "(" + ", ".join(f"{x:.2f}" for x in tgt) + ")"
        hold = "" if c.contact_start is None else f"{c.contact_start}-{c.contact_end}"
        table.append([c.id, c.skill, f"{c.start}-{c.end}", f"{(c.end - c.start) / sf.fps:.1f}", hold,
                      ", ".join(c.parts), size, tgt, c.score])
    page.table(["clip", "skill", "frames", "seconds", "hold", "parts in contact", "object box (m)", "target", "score"], table)
