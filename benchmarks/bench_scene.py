"""Benchmark Stage I (`embodmocap scene`) on synthetic sessions against their ground truth.

For each seed: synthesise a session whose scene capture lasts ``--scene-seconds`` (views kept
minimal), run the whole stage in a child process (wall time and peak RSS of that process), then
measure against the ground truth:

- mesh accuracy: mean distance from the reconstructed surface to the true scene mesh (the
  reconstruction lives in the capture's VIO world; the true ``T_scene_vio`` maps it);
- completeness: fraction of the true surface seen by the key frames (true poses, depth
  truncation) that lies within 5 cm of the reconstruction;
- SfM: points, mean reprojection error, and the largest change of any key frame pose in the model.

Targets (issue 3): accuracy <= 1.5 cm indoor, completeness >= 90 %, >= 2,000 SfM points, reprojection
<= 1.5 px, poses untouched; a 60 s 30 fps capture in <= 3 minutes.

    .venv/bin/python benchmarks/bench_scene.py --seeds 0 1 2 --scene-seconds 60 --out /tmp/bench_scene

``--plain`` (issue 13) also fuses a plain Open3D ``ScalableTSDFVolume`` of *every* frame of the
same capture (the capture's own poses as Stage I uses them, the production voxel and truncation
band, all depth up to the LiDAR's 5 m, no confidence cut, no clean-up) and reports Stage I's
completeness and accuracy relative to it (completeness of both over the true surface that all
frames see within 5 m). With ``--plain``, ``--old-src DIR`` also runs the key-frame + mesh steps of another checkout
(e.g. the code before issue 13) on the same capture, in a child process, for a before/after row.
``--zip`` pairs ``--presets`` and ``--seeds`` one to one (preset names: benchmarks/_studio.py).
``--floor`` (session 6, scans that look at the floor) adds the walk area's floor seen by the scan
and kept in the Stage I meshes (:func:`walk_area_floor`). ``--old-stage`` times the whole stage of ``--old-src`` too (a hard-linked copy of the session), in
the same run, for the time ratio. ``--eval-only`` measures the Stage I outputs already in each
session (e.g. written by bench_calibrate.py's run of the stage) without running the stage, and
reuses a ``plain_tsdf.ply`` / ``old_mesh.ply`` already there (same capture, same reference).

    .venv/bin/python benchmarks/bench_scene.py --zip --presets indoor large high_ceiling low_texture repetitive \
        --seeds 0 2 3 4 5 --scene-seconds 15 --out /work/bench/13/calib --plain --old-src /work/bench/13/old/src
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from _child import run_cli

import numpy as np


def synth(out: Path, seed: int, preset: str, scene_seconds: float) -> None:
    from _studio import ensure_session

    ensure_session(out, seed, preset, 0.5, scene_seconds)


def run_stage(session: Path, src: str | None = None) -> tuple[float, int]:
    """Run the stage from scratch in a child process; (wall seconds, peak RSS in MB). ``src``: the
    ``src`` folder of another checkout to run instead of this one."""
    return run_cli("scene", str(session), "--force", src=src)


_OLD_MESH = """
import json, sys, time
import numpy as np
from embodmocap.io.captures import open_capture
from embodmocap.scene.config import SceneConfig
from embodmocap.scene.depth import fusion_frames
from embodmocap.scene.keyframes import choose_keyframes
from embodmocap.scene.mesh import clean_mesh, write_mesh_ply
from embodmocap.scene.tsdf import fuse_open3d
cap, indoor, out = open_capture(sys.argv[1]), sys.argv[2] == "1", sys.argv[3]
cfg = SceneConfig()
t0 = time.perf_counter()
sel = choose_keyframes(cap, cfg, indoor)
T = cap.trajectory.T_world_cam[sel.rows]
v, f, c = fuse_open3d(fusion_frames(cap, sel.frame_ids, T, cfg, indoor), cfg.voxel_m(indoor), cfg.sdf_trunc_m(indoor),
                      cfg.depth_trunc_m(indoor))
v, f, c = clean_mesh(v, f, c, cfg)
write_mesh_ply(out, v, f, c)
print(json.dumps({"fused_frames": int(len(sel)), "seconds": time.perf_counter() - t0}))
"""


def old_mesh(session: Path, src: str, out: Path) -> dict:
    """Key frames + mesh of the checkout at ``src`` on the session's scene capture (child process)."""
    import os

    lay_capture = session / "captures" / "scene0"
    info = json.loads((session / "ground_truth" / "ground_truth.json").read_text())
    env = dict(os.environ, PYTHONPATH=src)
    proc = subprocess.run([sys.executable, "-c", _OLD_MESH, str(lay_capture), "1" if info["config"]["preset"] == "indoor" else "0",
                           str(out)], check=True, capture_output=True, text=True, env=env)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def plain_tsdf(session: Path, out: Path) -> dict:
    """The reference: Open3D ScalableTSDFVolume of every frame (the capture's poses), production
    voxel and band, depth <= 5 m, no confidence cut, no clean-up."""
    import time

    from embodmocap.io.captures import open_capture
    from embodmocap.scene.config import SceneConfig
    from embodmocap.scene.depth import colour_at_depth_resolution
    from embodmocap.scene.mesh import write_mesh_ply
    from embodmocap.scene.tsdf import fuse_open3d

    cap = open_capture(session / "captures" / "scene0")
    info = json.loads((session / "ground_truth" / "ground_truth.json").read_text())
    indoor = info["config"]["preset"] == "indoor"
    cfg = SceneConfig()
    K = cap.depth_intrinsics
    traj = cap.trajectory

    def frames():
        for f, T in zip(traj.frame_ids, traj.T_world_cam):
            d = np.asarray(cap.frames.depth_m(int(f)), dtype=np.float32)
            d = np.where(np.isfinite(d) & (d > 0), d, 0).astype(np.float32)
            yield colour_at_depth_resolution(cap.frames.rgb(int(f)), K), d, K, T

    t0 = time.perf_counter()
    v, f, c = fuse_open3d(frames(), cfg.voxel_m(indoor), cfg.sdf_trunc_m(indoor), 5.0)
    write_mesh_ply(out, v, f, c)
    return {"fused_frames": int(len(traj)), "seconds": time.perf_counter() - t0}


def walk_area_floor(session: Path) -> dict:
    """Issue "scans that look at the floor" (session 6): how much of the walk area's floor (where
    the performer walks; 5 cm grid on z = 0) the scan saw and Stage I kept, in percent:
    ``floor_frustum_pct`` inside the depth frustum of some scan frame (true poses, every 3rd frame,
    67 deg x 4:3, 5 m, occlusion ignored); ``floor_mesh_pct`` / ``floor_simplified_pct`` within
    5 cm of a vertex of ``mesh_raw.ply`` / ``mesh_simplified.ply`` (through the true ``T_scene_vio``)."""
    from scipy.spatial import cKDTree

    from embodmocap.geometry.transforms import apply_T
    from embodmocap.io.layout import SessionLayout
    from embodmocap.scene.mesh import read_mesh_ply
    from embodmocap.synth.config import SynthConfig
    from embodmocap.synth.scene import build_scene
    from embodmocap.synth.studio import _rng

    lay = SessionLayout(session)
    info = json.loads(lay.ground_truth.info.read_text())
    c = info["config"]
    spec = build_scene(c["preset"], _rng(int(c["seed"]), 1), c.get("room", "standard")).spec
    lo, hi = np.asarray(spec.walk_area_min_xy, float), np.asarray(spec.walk_area_max_xy, float)
    g = np.stack(np.meshgrid(np.arange(lo[0], hi[0], 0.05), np.arange(lo[1], hi[1], 0.05), indexing="ij"), -1)
    P = np.column_stack([g.reshape(-1, 2), np.zeros(g.shape[0] * g.shape[1])])
    dev = np.load(lay.ground_truth.scene_device("scene0"))
    tx = np.tan(np.radians(SynthConfig().hfov_deg / 2))
    seen = np.zeros(len(P), bool)
    for Tk in dev["T_scene_cam"][::3]:
        pc = (P - Tk[:3, 3]) @ Tk[:3, :3]
        z = pc[:, 2]
        seen |= (z > 0.05) & (z < 5.0) & (np.abs(pc[:, 0]) < tx * z) & (np.abs(pc[:, 1]) < 0.75 * tx * z)
    out = {"floor_frustum_pct": round(100 * float(seen.mean()), 1)}
    for key, path in (("floor_mesh_pct", lay.scene("scene0").mesh_raw), ("floor_simplified_pct", lay.scene("scene0").mesh_simplified)):
        if path.is_file():
            v, _, _ = read_mesh_ply(path)
            d, _ = cKDTree(apply_T(dev["T_scene_vio"], v)).query(P, distance_upper_bound=0.05)
            out[key] = round(100 * float(np.isfinite(d).mean()), 1)
    return out


def evaluate(session: Path) -> dict:
    import trimesh

    from embodmocap.evaluate.mesh_metrics import scene_mesh_metrics
    from embodmocap.geometry.transforms import apply_T, invert_T
    from embodmocap.io.captures import open_capture
    from embodmocap.io.layout import SessionLayout
    from embodmocap.scene.config import SceneConfig
    from embodmocap.scene.mesh import read_mesh_ply
    from embodmocap.scene.sfm import image_poses
    from embodmocap.io.stage_files import read_keyframes

    lay = SessionLayout(session)
    out = lay.scene("scene0")
    man = json.loads(out.manifest.read_text())
    info = json.loads(lay.ground_truth.info.read_text())
    indoor = info["config"]["preset"] == "indoor"
    gt = trimesh.load(lay.ground_truth.scene_mesh("scene0"), force="mesh")
    dev = np.load(lay.ground_truth.scene_device("scene0"))
    kf = read_keyframes(out.keyframes)
    cap = open_capture(lay.scene_capture("scene0"))
    v, f, _ = read_mesh_ply(out.mesh_raw)
    # Compare in the scene frame; "seen" surface from the key frames' true poses.
    m = scene_mesh_metrics(apply_T(dev["T_scene_vio"], v), f, np.asarray(gt.vertices), np.asarray(gt.faces),
                           dev["T_scene_cam"][kf["frame_ids"]], cap.depth_intrinsics,
                           SceneConfig().depth_trunc_m(indoor), n_samples=200_000)
    extra = {}
    if PLAIN:
        # Issue 13: against the plain TSDF of all frames, over the surface all frames see <= 5 m.
        seen_T = dev["T_scene_cam"][:: 3]
        meshes = {"ours": (v, f)}
        if PLAIN:
            if not (EVAL_ONLY and (out.root / "plain_tsdf.ply").is_file()):
                p = plain_tsdf(session, out.root / "plain_tsdf.ply")
                extra["plain_seconds"] = round(p["seconds"], 1)
            pv, pf, _ = read_mesh_ply(out.root / "plain_tsdf.ply")
            meshes["plain"] = (pv, pf)
        if OLD_SRC:
            if not (EVAL_ONLY and (out.root / "old_mesh.ply").is_file()):
                o = old_mesh(session, OLD_SRC, out.root / "old_mesh.ply")
                extra["old_fused_frames"] = o["fused_frames"]
            ov, of, _ = read_mesh_ply(out.root / "old_mesh.ply")
            meshes["old"] = (ov, of)
        for name, (mv, mf) in meshes.items():
            mm = scene_mesh_metrics(apply_T(dev["T_scene_vio"], mv), mf, np.asarray(gt.vertices), np.asarray(gt.faces),
                                    seen_T, cap.depth_intrinsics, 5.0, n_samples=200_000)
            extra[f"{name}_all_completeness_pct"] = round(100 * mm["completeness"], 2)
            extra[f"{name}_all_accuracy_cm"] = round(100 * mm["accuracy_m"], 3)
        if PLAIN:
            extra["completeness_vs_plain_pct"] = round(100 * extra["ours_all_completeness_pct"]
                                                       / max(extra["plain_all_completeness_pct"], 1e-9), 2)
            extra["accuracy_minus_plain_cm"] = round(extra["ours_all_accuracy_cm"] - extra["plain_all_accuracy_cm"], 3)
            if OLD_SRC:
                extra["old_completeness_vs_plain_pct"] = round(100 * extra["old_all_completeness_pct"]
                                                               / max(extra["plain_all_completeness_pct"], 1e-9), 2)
    if FLOOR:
        extra.update(walk_area_floor(session))
    by_frame = {int(i): T for i, T in zip(kf["frame_ids"], kf["T_world_cam"])}
    pose_change = max(float(np.abs(invert_T(by_frame[int(Path(n).stem.split("_")[1])]) @ T - np.eye(4)).max())
                      for n, T in image_poses(out.sfm_dir).items())
    figs = man["figures"]
    steps = {k: v["seconds"] for k, v in man["steps"].items()}
    return {
        "accuracy_cm": round(100 * m["accuracy_m"], 3), "accuracy_median_cm": round(100 * m["accuracy_median_m"], 3),
        "completeness_pct": round(100 * m["completeness"], 2), "sfm_points": figs["sfm_points"],
        "sfm_reproj_px": figs["sfm_mean_reproj_error_px"], "sfm_track": figs["sfm_mean_track_length"],
        "max_pose_change": pose_change, "keyframes": figs["keyframes"], "frames": cap.num_frames,
        "mesh_faces": figs["mesh_faces"], "fusion_fps": figs["fusion_fps"], "step_seconds": steps,
        "fused_frames": figs.get("fused_frames"), "depth_pixels_used_fraction": figs.get("depth_pixels_used_fraction"),
        **extra,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--presets", nargs="+", default=["indoor"])
    ap.add_argument("--scene-seconds", type=float, default=60.0)
    ap.add_argument("--out", type=Path, default=Path("bench_out/scene"))
    ap.add_argument("--tsdf-compare", action="store_true",
                    help="also run benchmarks/bench_tsdf.py (Open3D vs NumPy TSDF) on the first session")
    ap.add_argument("--zip", action="store_true", help="pair --presets and --seeds one to one")
    ap.add_argument("--plain", action="store_true", help="compare with a plain Open3D TSDF of every frame")
    ap.add_argument("--old-src", default=None, help="src folder of another checkout: its key frames + mesh too")
    ap.add_argument("--old-stage", action="store_true", help="time the whole stage of --old-src too (same run)")
    ap.add_argument("--eval-only", action="store_true",
                    help="measure the Stage I outputs already in the sessions (no synthesis, no stage run)")
    ap.add_argument("--floor", action="store_true",
                    help="also measure the walk area's floor in the scan's frustums and in the Stage I meshes")
    args = ap.parse_args()
    global PLAIN, OLD_SRC, EVAL_ONLY, FLOOR
    PLAIN, OLD_SRC, EVAL_ONLY, FLOOR = args.plain, args.old_src, args.eval_only, args.floor
    pairs = list(zip(args.presets, args.seeds)) if args.zip else [(p, s) for p in args.presets for s in args.seeds]
    rows = []
    for preset, seed in pairs:
        session = args.out / f"{preset}_{seed}"
        if args.eval_only:
            row = {"preset": preset, "seed": seed, "wall_s": None, "peak_rss_mb": None}
        else:
            synth(session, seed, preset, args.scene_seconds)
            wall, rss = run_stage(session)
            row = {"preset": preset, "seed": seed, "wall_s": round(wall, 1), "peak_rss_mb": rss}
        if args.old_stage and args.old_src:
            copy = args.out / f".old_{preset}_{seed}"
            if not copy.exists():
                subprocess.run(["cp", "-al", str(session), str(copy)], check=True)
            subprocess.run(["rm", "-rf", str(copy / "scenes")], check=True)
            old_wall, old_rss = run_stage(copy, src=args.old_src)
            row.update({"old_wall_s": round(old_wall, 1), "old_peak_rss_mb": old_rss,
                        "time_ratio_new_over_old": round(wall / old_wall, 3)})
        row.update(evaluate(session))
        rows.append(row)
        print(json.dumps(row), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "bench_scene.json").write_text(json.dumps(rows, indent=2))
    print("\n| preset | seed | frames | key frames | wall (s) | peak RSS (MB) | accuracy (cm) | completeness (%) "
          "| SfM points | reproj (px) | max pose change |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['preset']} | {r['seed']} | {r['frames']} | {r['keyframes']} | {r['wall_s']} | {r['peak_rss_mb']} "
              f"| {r['accuracy_cm']} | {r['completeness_pct']} | {r['sfm_points']} | {r['sfm_reproj_px']} "
              f"| {r['max_pose_change']:.1e} |")
    if args.tsdf_compare and rows:
        first = args.out / f"{args.presets[0]}_{args.seeds[0]}"
        subprocess.run([sys.executable, str(Path(__file__).with_name("bench_tsdf.py")), "--session", str(first),
                        "--json", str(args.out / "bench_tsdf.json")], check=True)


PLAIN, OLD_SRC, EVAL_ONLY, FLOOR = False, None, False, False

if __name__ == "__main__":
    main()
