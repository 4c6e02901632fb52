"""`embodmocap batch` figures, all in one run (see BENCHMARKS.md, "Batch processing"):

1. wall time of N fresh sessions with 1 vs 2 local workers (the ratio), every output equal to what
   `embodmocap run` gave for the same session alone (world SMPL, joints, final cameras, scene mesh,
   every stage step's input fingerprint);
2. scheduler overhead per task: `batch` on the finished dataset (every task up to date) vs
   `embodmocap run` on each finished session, local pool and Ray in the same run;
3. a paper-scale projection (23 scenes, 104 sequences, 200k frames) from the measured per-frame
   costs of the stages (stated as a projection).

    OMP_NUM_THREADS=1 nice -n 19 python benchmarks/bench_batch.py REF_SESSION OUT [--sessions 3]

REF_SESSION is a synthetic session already processed by `embodmocap run` (the reference); its raw
inputs are copied N times per arm. Nothing here uses ground truth.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

RAW = ("captures", "perception", "ground_truth", "body_model.npz", "session.toml")


def _raw_copy(ref: Path, dst: Path) -> None:
    dst.mkdir(parents=True)
    for name in RAW:
        src = ref / name
        if src.is_dir():
            shutil.copytree(src, dst / name, symlinks=True)
        elif src.is_file():
            shutil.copy2(src, dst / name)


def _cli(*args: str) -> tuple[float, int, str]:
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "embodmocap.cli", *args], capture_output=True, text=True)
    return time.perf_counter() - t0, p.returncode, p.stdout[-3000:] + p.stderr[-3000:]


def _outputs(session: Path) -> dict:
    """The final outputs through the package's typed readers, and every step's input fingerprint."""
    from embodmocap.io.layout import SessionLayout
    from embodmocap.io.mesh_file import read_mesh_ply
    from embodmocap.io.smpl_file import read_smpl_npz
    from embodmocap.io.stage_files import read_cameras, read_world_joints

    lay = SessionLayout(session)
    sl = lay.sequence("seq0")
    params, frames = read_smpl_npz(sl.smpl_world)
    out = {"poses": params.poses, "trans": np.asarray(params.transl), "betas": np.asarray(params.betas),
           "frames": frames, "joints": read_world_joints(sl.joints_world).joints,
           "mesh_v": read_mesh_ply(lay.scene("scene0").mesh_simplified)[0]}
    for v in ("v1", "v2"):
        out[f"cam_{v}"] = read_cameras(sl.view(v).cameras_final).T_world_cam
    for m in (lay.scene("scene0").manifest, sl.manifest, sl.calibrate_manifest, sl.motion_manifest):
        steps = json.loads(m.read_text())["steps"]
        out[f"fp:{m.name}"] = {k: s["fingerprint"] for k, s in steps.items()}
    return out


def _same(a: dict, b: dict) -> list[str]:
    bad = []
    for k in a:
        if isinstance(a[k], dict):
            if a[k] != b[k]:
                bad.append(k)
        elif np.shape(a[k]) != np.shape(b[k]) or not np.array_equal(a[k], b[k]):
            diff = float(np.max(np.abs(a[k] - b[k]))) if a[k].shape == b[k].shape else float("nan")
            bad.append(f"{k} (max diff {diff:.3g})")
    return bad


def _stage_seconds(session: Path) -> dict[str, float]:
    from embodmocap.io.layout import SessionLayout

    lay = SessionLayout(session)
    sl = lay.sequence("seq0")
    out = {}
    for stage, m in (("scene", lay.scene("scene0").manifest), ("sequence", sl.manifest),
                     ("calibrate", sl.calibrate_manifest), ("motion", sl.motion_manifest)):
        out[stage] = sum(float(s["seconds"]) for s in json.loads(m.read_text())["steps"].values())
    out["frames"] = json.loads(sl.manifest.read_text())["figures"]["frames"]
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("ref", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--sessions", type=int, default=3)
    ap.add_argument("--skip-fresh", action="store_true", help="reuse OUT/w1 and OUT/w2 from an earlier run")
    a = ap.parse_args()
    res: dict = {"sessions": a.sessions, "date": time.strftime("%Y-%m-%d"), "cpu_count": os.cpu_count()}
    ref_out = _outputs(a.ref)
    walls = {}
    for w in (1, 2):
        ds = a.out / f"w{w}"
        if not a.skip_fresh:
            shutil.rmtree(ds, ignore_errors=True)
            for i in range(a.sessions):
                _raw_copy(a.ref, ds / f"s{i}")
            wall, rc, log = _cli("batch", str(ds), "--executor", "local", "--workers", str(w))
            print(f"fresh, {w} worker(s): {wall:.1f} s (rc {rc})\n{log[-1500:]}", flush=True)
            walls[w] = wall
        res[f"equal_to_run_w{w}"] = {s.name: _same(ref_out, _outputs(s)) or "equal" for s in sorted(ds.iterdir())
                                     if (s / "session.toml").is_file()}
    if walls:
        res["fresh_wall_s"] = {str(k): round(v, 1) for k, v in walls.items()}
        res["ratio_1_over_2"] = round(walls[1] / walls[2], 3)
    # Overhead: everything is up to date now.
    ds = a.out / "w2"
    sessions = sorted(s for s in ds.iterdir() if (s / "session.toml").is_file())
    tasks = 4 * len(sessions)
    t_run = 0.0
    for s in sessions:
        wall, rc, _ = _cli("run", str(s))
        t_run += wall
    res["run_finished_s"] = round(t_run, 2)
    res["run_finished_per_task_s"] = round(t_run / tasks, 3)
    for ex in ("local", "ray"):
        if ex == "ray":
            os.environ["RAY_AUTH_MODE"] = "disabled"
        wall, rc, log = _cli("batch", str(ds), "--executor", ex, "--workers", "1", "--ray-object-store-gb", "0.2")
        res[f"batch_finished_{ex}_s"] = round(wall, 2)
        res[f"batch_finished_{ex}_rc"] = rc
        res[f"batch_finished_per_task_{ex}_s"] = round(wall / tasks, 3)
        print(ex, wall, rc, log[-600:], flush=True)
    # Projection from the reference's own stage timings (single-process seconds).
    st = _stage_seconds(a.ref)
    per_frame = (st["sequence"] + st["calibrate"] + st["motion"]) / st["frames"]
    one = 23 * st["scene"] + 200_000 * per_frame
    res["stage_seconds_ref"] = st
    res["per_frame_s_stages_2_4"] = round(per_frame, 4)
    res["projection_hours_1_worker"] = round(one / 3600, 1)
    res["projection_hours_16_workers"] = round(one / 3600 / 16, 1)
    res["projection_hours_10_machines_x16"] = round(one / 3600 / 160, 2)
    (a.out / "bench_batch.json").write_text(json.dumps(res, indent=2))
    print(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
