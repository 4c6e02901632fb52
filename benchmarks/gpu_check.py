"""Stage IV's fit on the CPU and on CUDA in one run: wall time and agreement (issue 30, item 3).

Needs only numpy, scipy and torch (+ this repository's ``src`` on the path): the motion is the
synthetic studio's scripted performer (ground truth), seen by two cameras whose 2D keypoints are
its exact projections plus pixel noise; the 3D keypoints are the truth plus noise; the start is the
truth perturbed (as ``tests/test_smplify.py`` does). The same fit (``fit_world_smpl``, the
product's windows and iterations) runs on ``cpu`` and on ``cuda`` (float64, the product's dtype, and
float32), each timed after a short warm-up fit on its device (CUDA context, kernels) that is
reported apart. Agreement: the largest and mean distance between the joints of the CPU and the
CUDA fits, and each fit's MPJPE against the truth.

With ``--session SESSION`` (a session whose Stages I-III are done, all dependencies installed)
``embodmocap motion SESSION --force --device cpu|cuda`` is timed too, on copies, and the
``smpl_world.npz`` joints of both compared.

Writes ``$OUT/gpu_check.json`` and ``$OUT/gpu_check.md`` (``OUT`` defaults to /tmp/out).

    python benchmarks/gpu_check.py --seconds 60
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

SRC = Path(__file__).resolve().parents[1] / "src"


def _problem(seconds: float, seed: int = 0):
    """(body model, kp3d (T, 17, 3), conf (T, 17), views, init, truth coco (T, 17, 3))."""
    import torch

    from embodmocap.body.model import load_body_model
    from embodmocap.geometry.transforms import invert_T, look_at_T
    from embodmocap.motion.smplify import ViewObservations
    from embodmocap.synth.motion import script_motion
    from embodmocap.synth.scene import build_scene
    from embodmocap.types import SmplParams

    body = load_body_model(None)
    rng = np.random.default_rng(seed)
    spec = build_scene("indoor", np.random.default_rng(seed)).spec
    betas = np.array([0.5, -0.3, 0.2, 0.0, 0.1, 0, 0, 0, 0, 0])
    params = script_motion(spec, body, betas, seconds, 30.0, np.random.default_rng(seed)).params
    coco = body.from_params(params, dtype=torch.float64).coco17.numpy()
    T = len(coco)
    K = np.array([[700.0, 0.0, 360.0], [0.0, 700.0, 480.0], [0.0, 0.0, 1.0]])
    centre = coco.reshape(-1, 3).mean(0)
    views = []
    for name, a0, rate in (("v1", 0.3, 0.0), ("v2", 1.9, 0.004)):
        ang = a0 + rate * np.arange(T)
        cams = np.stack([look_at_T(centre + [4 * np.cos(a), 4 * np.sin(a), 0.3], centre) for a in ang])
        Tcw = invert_T(cams)
        p = np.einsum("tij,tkj->tki", Tcw[:, :3, :3], coco) + Tcw[:, None, :3, 3]
        uv = p @ K.T
        uv = uv[..., :2] / uv[..., 2:] + rng.normal(size=(T, 17, 2)) * 2.0
        views.append(ViewObservations(K, cams, np.concatenate([uv, np.ones((T, 17, 1))], -1), name))
    kp3d = coco + rng.normal(size=coco.shape) * 0.02
    init = SmplParams(betas=params.betas + rng.normal(size=10) * 0.5,
                      global_orient=params.global_orient + rng.normal(size=(T, 3)) * 0.1,
                      body_pose=params.body_pose + rng.normal(size=(T, 69)) * 0.1,
                      transl=params.transl + rng.normal(size=3) * 0.1 + rng.normal(size=(T, 3)) * 0.02, fps=30.0)
    return body, kp3d, np.ones((T, 17)), views, init, coco


def _fit(problem, device: str, dtype: str, frames: int | None = None):
    """(wall seconds, fitted COCO-17 (T, 17, 3) on the CPU, result) of one fit."""
    import torch

    from embodmocap.motion.smplify import SmplifyConfig, ViewObservations, fit_world_smpl
    from embodmocap.types import SmplParams

    body, kp3d, conf, views, init, _ = problem
    if frames is not None:  # the warm-up: a short fit
        cut = slice(0, frames)
        kp3d, conf = kp3d[cut], conf[cut]
        views = [ViewObservations(v.K, v.T_world_cam[cut], v.keypoints[cut], v.name) for v in views]
        init = SmplParams(init.betas, init.global_orient[cut], init.body_pose[cut], init.transl[cut], fps=init.fps)
    cfg = SmplifyConfig(device=device, dtype=dtype)
    if device == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    res = fit_world_smpl(body, kp3d, conf, views, init, None, cfg)
    if device == "cuda":
        torch.cuda.synchronize()
    wall = time.perf_counter() - t0
    coco = body.from_params(res.params, dtype=torch.float64).coco17.numpy()
    return wall, coco, res


def _session_check(session: Path, work: Path) -> dict:
    """``embodmocap motion`` on copies of ``session`` with --device cpu and cuda: times and joints."""
    out = {}
    joints = {}
    for dev in ("cpu", "cuda"):
        dst = work / f"session_{dev}"
        if dst.exists():
            shutil.rmtree(dst)
        shutil.copytree(session, dst)
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "embodmocap.cli", "motion", str(dst), "--force", "--device", dev],
                              capture_output=True, text=True, env=dict(os.environ, PYTHONPATH=str(SRC)))
        out[f"motion_{dev}_s"] = round(time.perf_counter() - t0, 2)
        if proc.returncode != 0:
            out[f"motion_{dev}_error"] = (proc.stdout + proc.stderr)[-1500:]
            return out
        path = next(dst.glob("sequences/*/joints_world.npz"))
        with np.load(path) as z:
            joints[dev] = z["joints"]
    d = np.linalg.norm(joints["cpu"] - joints["cuda"], axis=-1)
    out["motion_joint_diff_max_mm"] = round(float(np.nanmax(d)) * 1000, 3)
    out["motion_joint_diff_mean_mm"] = round(float(np.nanmean(d)) * 1000, 3)
    return out


def _compare(rows: list[dict], fits: dict) -> None:
    """Each fit's distance to the CPU float64 fit and its speed-up over it (when that one exists)."""
    ref = fits.get(("cpu", "float64"))
    cpu = next((r for r in rows if r.get("device") == "cpu" and "fit_s" in r), None)
    for r in rows:
        c = fits.get((r["device"], r["dtype"]))
        if ref is not None and c is not None:
            d = np.linalg.norm(c - ref, axis=-1)
            r["diff_vs_cpu_max_mm"] = round(float(d.max()) * 1000, 4)
            r["diff_vs_cpu_mean_mm"] = round(float(d.mean()) * 1000, 4)
            r["speedup_vs_cpu"] = round(cpu["fit_s"] / r["fit_s"], 2)


def _write(out_dir: Path, result: dict) -> str:
    """``gpu_check.json`` and ``gpu_check.md`` (the table) under ``out_dir``; returns the table."""
    info, rows = result["info"], result["fits"]
    (out_dir / "gpu_check.json").write_text(json.dumps(result, indent=2))
    lines = [f"Stage IV fit, {info['frames']} frames (synthetic, two views), {info['gpu']} / {info['cpu_threads']} CPU threads, "
             f"torch {info['torch']}", "", "| device | dtype | fit s | speed-up vs cpu | MPJPE vs truth mm | "
             "max / mean joint diff vs cpu mm | warm-up s |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['device']} | {r['dtype']} | {r['error']} | | | | |")
            continue
        lines.append(f"| {r['device']} | {r['dtype']} | {r['fit_s']} | {r.get('speedup_vs_cpu', '-')} | "
                     f"{r['mpjpe_vs_truth_mm']} | {r.get('diff_vs_cpu_max_mm', '-')} / {r.get('diff_vs_cpu_mean_mm', '-')} | "
                     f"{r['warmup_s']} |")
    if "session" in result:
        lines += ["", "embodmocap motion on the session: " + json.dumps(result["session"])]
    text = "\n".join(lines) + "\n"
    (out_dir / "gpu_check.md").write_text(text)
    return text


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="length of the synthetic motion (30 fps)")
    ap.add_argument("--session", type=Path, default=None, help="also time `embodmocap motion` on this session")
    ap.add_argument("--skip-cpu", action="store_true", help="time CUDA only (when the CPU fit is too slow)")
    args = ap.parse_args()
    sys.path.insert(0, str(SRC))  # this checkout's package, installed or not
    out_dir = Path(os.environ.get("OUT") or "/tmp/out")
    out_dir.mkdir(parents=True, exist_ok=True)
    try:
        import scipy  # noqa: F401 (the fit's quaternion blending)
        import torch
    except ImportError as err:
        print(f"gpu_check: cannot run the fit: {err} (needs numpy, scipy and torch; set PYTHON=... to another python)")
        return 2

    info = {"python": platform.python_version(), "torch": torch.__version__, "cuda_build": torch.version.cuda,
            "cuda_available": torch.cuda.is_available(), "cpu_threads": torch.get_num_threads(),
            "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None, "seconds": args.seconds}
    print(json.dumps(info), flush=True)
    t0 = time.perf_counter()
    problem = _problem(args.seconds)
    info["frames"] = len(problem[5])
    info["synth_s"] = round(time.perf_counter() - t0, 2)
    truth = problem[5]
    rows, fits = [], {}
    result = {"info": info, "fits": rows}
    # CUDA first: should the CPU fit be slow, the GPU rows are already written when the time runs out.
    runs = [("cuda", "float64"), ("cuda", "float32")] + [("cpu", "float64")] * (not args.skip_cpu)
    for device, dtype in runs:
        if device == "cuda" and not torch.cuda.is_available():
            rows.append({"device": device, "dtype": dtype, "error": "torch sees no CUDA device"})
            continue
        warm, _, _ = _fit(problem, device, dtype, frames=60)
        wall, coco, res = _fit(problem, device, dtype)
        fits[device, dtype] = coco
        err = np.linalg.norm(coco - truth, axis=-1)
        rows.append({"device": device, "dtype": dtype, "fit_s": round(wall, 2), "warmup_s": round(warm, 2),
                     "windows": len(res.windows), "mpjpe_vs_truth_mm": round(float(err.mean()) * 1000, 3),
                     "phase_seconds": res.phase_seconds})
        print(json.dumps(rows[-1]), flush=True)
        _compare(rows, fits)
        _write(out_dir, result)
    if args.session is not None:
        result["session"] = _session_check(args.session, out_dir / "work")
        shutil.rmtree(out_dir / "work", ignore_errors=True)
    print(_write(out_dir, result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
