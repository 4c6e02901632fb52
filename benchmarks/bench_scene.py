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
    from embodmocap.synth.config import SynthConfig
    from embodmocap.synth.studio import synthesize

    if (out / "ground_truth" / "ground_truth.json").is_file():
        return
    synthesize(SynthConfig(seed=seed, preset=preset, seconds=0.5, scene_seconds=scene_seconds), out)


def run_stage(session: Path) -> tuple[float, int]:
    """Run the stage from scratch in a child process; (wall seconds, peak RSS in MB)."""
    return run_cli("scene", str(session), "--force")


def evaluate(session: Path) -> dict:
    import trimesh

    from embodmocap.evaluate.mesh_metrics import scene_mesh_metrics
    from embodmocap.geometry.transforms import apply_T, invert_T
    from embodmocap.io.captures import open_capture
    from embodmocap.io.layout import SessionLayout
    from embodmocap.scene.config import SceneConfig
    from embodmocap.scene.mesh import read_mesh_ply
    from embodmocap.scene.sfm import image_poses
    from embodmocap.scene.stage import read_keyframes

    lay = SessionLayout(session)
    out = lay.scene("scene0")
    man = json.loads(out.manifest.read_text())
    info = json.loads(lay.ground_truth.info.read_text())
    indoor = info["config"]["preset"] == "indoor"
    gt = trimesh.load(lay.ground_truth.scene_mesh("scene0"), force="mesh")
    dev = np.load(lay.ground_truth.scene_device("scene0"))
    kf = read_keyframes(out)
    cap = open_capture(lay.scene_capture("scene0"))
    v, f, _ = read_mesh_ply(out.mesh_raw)
    # Compare in the scene frame; "seen" surface from the key frames' true poses.
    m = scene_mesh_metrics(apply_T(dev["T_scene_vio"], v), f, np.asarray(gt.vertices), np.asarray(gt.faces),
                           dev["T_scene_cam"][kf["frame_ids"]], cap.depth_intrinsics,
                           SceneConfig().depth_trunc_m(indoor), n_samples=200_000)
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
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--presets", nargs="+", default=["indoor"])
    ap.add_argument("--scene-seconds", type=float, default=60.0)
    ap.add_argument("--out", type=Path, default=Path("bench_out/scene"))
    ap.add_argument("--tsdf-compare", action="store_true",
                    help="also run benchmarks/bench_tsdf.py (Open3D vs NumPy TSDF) on the first session")
    args = ap.parse_args()
    rows = []
    for preset in args.presets:
        for seed in args.seeds:
            session = args.out / f"{preset}_{seed}"
            synth(session, seed, preset, args.scene_seconds)
            wall, rss = run_stage(session)
            row = {"preset": preset, "seed": seed, "wall_s": round(wall, 1), "peak_rss_mb": rss, **evaluate(session)}
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


if __name__ == "__main__":
    main()
