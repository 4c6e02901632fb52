"""Stage III camera placement frame by frame: the rigid offset (as before drift knots) against the
drift-knot refinement, from the same registrations, on studio sessions whose Stages I and II ran.

For each session: Stage III runs (its registrations are reused when up to date), then from the same
registrations the refinement is redone twice in memory, once rigid (``drift_knot_frames = 0``, the
refinement before drift knots) and once with the given settings (default: the stage's defaults).
Errors against the studio's truth, in Stage I's world:

- ``centre``: each frame's camera centre against the true one (median over a view's frames,
  its 95th percentile and max): what a user of ``cameras_world.npz`` gets;
- ``offset``: the refined ``T_world_vio`` against the true VIO offset, at the view's camera centres
  (``bench_calibrate.py``'s figure, mean distance).

Sessions are made with ``embodmocap synth`` (``--cameras hard`` for the hard camera preset) and
Stages I-II with ``embodmocap scene`` / ``embodmocap sequence``::

    PYTHONPATH=src .venv/bin/python benchmarks/bench_calibrate_drift.py --sessions /tmp/cameras/std_indoor_0 \\
        /tmp/cameras/hard_indoor_0 --out /tmp/cameras/drift.json
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np


def centre_errors(T_est, T_true) -> dict:
    """Per-frame camera centre errors (cm): median, p95, max."""
    d = 100 * np.linalg.norm(np.asarray(T_est)[:, :3, 3] - np.asarray(T_true)[:, :3, 3], axis=1)
    return {"median": round(float(np.median(d)), 3), "p95": round(float(np.percentile(d, 95)), 3),
            "max": round(float(d.max()), 3)}


def one_session(session: Path, cfg) -> dict:
    from embodmocap.calibrate import solve, stage
    from embodmocap.geometry.transforms import invert_T
    from embodmocap.io.layout import VIEWS, SessionLayout
    from embodmocap.io.mesh_file import read_mesh_ply

    lay = SessionLayout(session)
    seq = lay.sequence("seq0")
    t0 = time.perf_counter()
    stage.run(cfg, session)
    wall = time.perf_counter() - t0
    views = {v: stage.view_inputs(seq, v) for v in VIEWS}
    regs = {v: stage._load_registration(seq.view(v).registration) for v in VIEWS}
    mv, mf, _ = read_mesh_ply(lay.scene("scene0").mesh_raw)
    points = solve.scene_points(cfg, mv, mf)
    use_tracks = json.loads(seq.sync.read_text())["slicing"]["source"] != "start"
    gt = lay.ground_truth
    scene_vio = np.load(gt.scene_device("scene0"))["T_scene_vio"]
    truth = np.load(gt.sequence("seq0"))
    info = json.loads(gt.info.read_text())
    row = {"session": session.name, "cameras": info["config"].get("cameras", "standard"), "stage_wall_s": round(wall, 1)}
    init, init_report = solve.initial_offsets(cfg, views, regs)
    variants = {"rigid": replace(cfg, refine=replace(cfg.refine, drift_knot_frames=0)), "drift": cfg}
    for name, c in variants.items():
        t1 = time.perf_counter()
        report = solve.refine_report(c, views, init, regs, init_report, points, use_tracks)
        row[f"{name}_refine_s"] = round(time.perf_counter() - t1, 2)
        for v in VIEWS:
            cams = views[v].cameras
            raw = np.asarray(cams["raw_frames"])
            T_true = invert_T(scene_vio) @ truth[f"{v}_T_scene_cam"][raw]
            T_est = solve.world_cameras(report["views"][v], cams["T_world_cam"])
            row[f"{name}_{v}_centre"] = centre_errors(T_est, T_true)
            T_vio_true = invert_T(scene_vio) @ truth[f"{v}_T_scene_vio"]
            p = np.c_[cams["T_world_cam"][:, :3, 3], np.ones(len(raw))]
            off = (p @ np.asarray(report["views"][v]["T_world_vio"]).T - p @ T_vio_true.T)[:, :3]
            row[f"{name}_{v}_offset_cm"] = round(100 * float(np.linalg.norm(off, axis=1).mean()), 3)
            if name == "rigid":
                T_reg = np.asarray(report["views"][v]["T_world_vio_registration"]) @ cams["T_world_cam"]
                row[f"registration_{v}_centre"] = centre_errors(T_reg, T_true)
                # The best any rigid offset could do: least squares of the VIO centres onto the truth.
                row[f"floor_{v}_centre_median"] = round(rigid_floor_cm(cams["T_world_cam"], T_true), 3)
    return row


def rigid_floor_cm(T_vio, T_true) -> float:
    """Median per-frame centre error (cm) of the best yaw + translation of the VIO centres onto the
    true ones (least squares): what no rigid offset can remove."""
    a, b = np.asarray(T_vio)[:, :3, 3], np.asarray(T_true)[:, :3, 3]
    A, B = a - a.mean(0), b - b.mean(0)
    yaw = np.arctan2((A[:, 0] * B[:, 1] - A[:, 1] * B[:, 0]).sum(), (A[:, 0] * B[:, 0] + A[:, 1] * B[:, 1]).sum())
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return float(100 * np.median(np.linalg.norm(A @ R.T - B, axis=1)))


def table(rows: list[dict]) -> str:
    lines = ["| session | VIO | view | rigid floor median | registration median | rigid: median / p95 / max | "
             "drift knots: median / p95 / max | offset error rigid / drift | refine s rigid / drift |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        for v in ("v1", "v2"):
            a, b = r[f"rigid_{v}_centre"], r[f"drift_{v}_centre"]
            lines.append(f"| {r['session']} | {r['cameras']} | {v} | {r[f'floor_{v}_centre_median']:.2f} | "
                         f"{r[f'registration_{v}_centre']['median']:.2f} | {a['median']:.2f} / {a['p95']:.2f} / {a['max']:.2f} | "
                         f"**{b['median']:.2f} / {b['p95']:.2f} / {b['max']:.2f}** | {r[f'rigid_{v}_offset_cm']:.2f} / "
                         f"{r[f'drift_{v}_offset_cm']:.2f} | {r['rigid_refine_s']} / {r['drift_refine_s']} |")
    for kind in sorted({r["cameras"] for r in rows}):
        sel = [r for r in rows if r["cameras"] == kind]
        for name in ("rigid", "drift"):
            med = np.array([r[f"{name}_{v}_centre"]["median"] for r in sel for v in ("v1", "v2")])
            p95 = np.array([r[f"{name}_{v}_centre"]["p95"] for r in sel for v in ("v1", "v2")])
            mx = np.array([r[f"{name}_{v}_centre"]["max"] for r in sel for v in ("v1", "v2")])
            off = np.array([r[f"{name}_{v}_offset_cm"] for r in sel for v in ("v1", "v2")])
            lines.append(f"| **all {kind}** ({len(sel)} sessions) | {kind} | {name} | | | median of views {np.median(med):.2f}, "
                         f"worst view median {med.max():.2f}, worst p95 {p95.max():.2f}, worst frame {mx.max():.2f} | | "
                         f"offset median {np.median(off):.2f} | |")
    return "\n".join(lines)


def main() -> None:
    import logging

    from embodmocap.calibrate.config import CalibrateConfig

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", nargs="+", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--knot-frames", type=int, default=None, help="drift_knot_frames (default: the stage's)")
    ap.add_argument("--sigma-m", type=float, default=None, help="drift_sigma_m (default: the stage's)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    cfg = CalibrateConfig()
    over = {k: v for k, v in (("drift_knot_frames", args.knot_frames), ("drift_sigma_m", args.sigma_m)) if v is not None}
    cfg = replace(cfg, refine=replace(cfg.refine, **over))
    rows = []
    for s in args.sessions:
        rows.append(one_session(s, cfg))
        print(json.dumps(rows[-1]), flush=True)
    args.out.write_text(json.dumps(rows, indent=1))
    print(table(rows))


if __name__ == "__main__":
    main()
