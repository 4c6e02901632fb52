"""Issue 15, item 6: FrameDataset random-access read rate at 640x480 (target >= 200 frames/s on 2
DataLoader workers), and the training export's own time per frame.

The session is a studio session (640x480 RGB, 256x192 LiDAR depth, 30 fps) whose Stage II-IV
outputs are written from the studio's truth (``tests/training_session.py``: the read rate does not
depend on how good the fit is), made once under ``--work`` and reused. Every frame is read in a
random order (``shuffle=True``) for ``--epochs`` epochs; the first batch of each run (worker start)
is left out of the rate. Rows: 0 workers (one process), 2 workers, 2 workers in clip mode (8
consecutive frames per item), and 2 workers without RGB (depth, masks, labels only).

The machine is shared (other jobs run on its 2 cores), so each row also gives the CPU seconds the
main process and the workers spent and the rate they imply on 2 free cores (``frames_per_s_on_2_free_cores``:
frames / max(worker CPU / 2, main CPU), worker start-up included).

    OMP_NUM_THREADS=1 PYTHONPATH=src nice .venv/bin/python benchmarks/bench_frame_dataset.py \
        --work /work/bench/15t --seconds 6 --epochs 6 --repeat 2 --reexport \
        --json /work/bench/15t/bench_frame_dataset.json
    # the fit check alone, on a session the real pipeline processed:
    OMP_NUM_THREADS=1 PYTHONPATH=src nice .venv/bin/python benchmarks/bench_frame_dataset.py \
        --work /work/bench/15t --only-fit-check --fit-session /work/bench/12b/normal_0
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

# The session helper lives with the tests (it writes Stages II-IV from the studio's truth).
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))


def ensure_export(work: Path, seconds: float, reexport: bool) -> tuple[Path, dict]:
    """The training export of a 640x480 studio session under ``work`` (session made once; the
    export again with ``reexport``); export timing."""
    from embodmocap.export.training import export_training
    from embodmocap.synth.config import SynthConfig
    from training_session import make_training_session

    session = work / f"s640_{seconds:g}s"
    out = session / "training"
    timing: dict = {}
    if not (session / "sequences").is_dir():
        if session.exists():
            shutil.rmtree(session)
        make_training_session(session, SynthConfig(seed=0, seconds=seconds, scene_seconds=2.0))
    if reexport and out.exists():
        shutil.rmtree(out)
    if not (out / "manifest.json").is_file():
        t0 = time.perf_counter()
        export_training(session, out=out)
        timing["export_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    export_training(session, out=out)  # a rerun: every view is up to date
    timing["rerun_s"] = time.perf_counter() - t0
    return out, timing


def _cpu_s(who: int) -> float:
    import resource

    r = resource.getrusage(who)
    return r.ru_utime + r.ru_stime


def read_rate(root: Path, workers: int, epochs: int, batch: int, **kw) -> dict:
    """Frames per second reading every item of the dataset in random order, wall clock, and the
    CPU seconds the main process and the workers spent (workers: from the OS once they have exited)."""
    import resource

    import torch

    from embodmocap.data import FrameDataset

    ds = FrameDataset(root, **kw)
    per_item = kw.get("clip") or 1
    size = tuple(ds[0]["rgb"].shape[-2:]) if kw.get("load_rgb", True) else None
    cpu0 = (_cpu_s(resource.RUSAGE_SELF), _cpu_s(resource.RUSAGE_CHILDREN))
    loader = torch.utils.data.DataLoader(ds, batch_size=batch, shuffle=True, num_workers=workers,
                                         persistent_workers=workers > 0,
                                         generator=torch.Generator().manual_seed(0))
    frames, frames_all, t_start = 0, 0, None
    t0 = time.perf_counter()
    for _ in range(epochs):
        for b in loader:
            frames_all += len(b["frame"]) * per_item
            if t_start is None:  # the first batch pays the workers' start: leave it out of the wall rate
                t_start = time.perf_counter()
                continue
            frames += len(b["frame"]) * per_item
    seconds = time.perf_counter() - t_start
    seconds_all = time.perf_counter() - t0
    del loader  # shuts the persistent workers down, so their CPU time is counted
    import gc

    gc.collect()
    main_cpu = _cpu_s(resource.RUSAGE_SELF) - cpu0[0]
    worker_cpu = _cpu_s(resource.RUSAGE_CHILDREN) - cpu0[1]
    # Were the workers alone on 2 free cores: the slower of the workers (sharing 2 cores) and the
    # main process (collecting batches) sets the rate. Startup is included, so this is a floor.
    busy = max(worker_cpu / 2.0, main_cpu) if workers else main_cpu
    return {"workers": workers, "items": len(ds), "frames_read": frames, "seconds": round(seconds, 3),
            "frames_per_s": round(frames / seconds, 1), "cpu_main_s": round(main_cpu, 2),
            "cpu_workers_s": round(worker_cpu, 2), "wall_all_s": round(seconds_all, 2),
            "frames_per_cpu_s": round(frames_all / max(main_cpu + worker_cpu, 1e-9), 1),
            "frames_per_s_on_2_free_cores": round(frames_all / max(busy, 1e-9), 1),
            "rgb_hw": size, **{k: v for k, v in kw.items()}}


def fit_check(session: Path, work: Path) -> dict:
    """On a session processed by the real pipeline (read only; exported under ``work``): the
    camera-space body's round trip to the world fit (view 1: max error, mm), and view 2's detected
    keypoints against the projected fit (median px) with the body taken at view 2's own instants (as
    exported), at view 1's rows unchanged, and with the sub-frame offset's sign flipped."""
    import numpy as np
    import torch

    from embodmocap.body.model import load_body_model
    from embodmocap.export.training import export_training, params_in_camera, resample_motion
    from embodmocap.geometry.transforms import invert_T
    from embodmocap.io.manifest import load_manifest
    from embodmocap.io.smpl_file import read_smpl_npz
    from embodmocap.io.stage_files import read_world_joints

    out = export_training(session, out=work / f"fit_check_{session.name}")
    model = load_body_model(load_manifest(session / "session.toml").body_model)
    seq = json.loads((out / "manifest.json").read_text())["views"][0]["sequence"]
    sl = session / "sequences" / seq
    params, frames = read_smpl_npz(sl / "smpl_world.npz")
    lab = {v: dict(np.load(out / seq / v / "labels.npz")) for v in ("v1", "v2")}

    def pose(go, body_pose, tr):
        with torch.no_grad():
            o = model.forward(params.betas, go, body_pose, tr, dtype=torch.float64)
        return o.joints.numpy(), o.coco17.numpy()

    j1, _ = pose(lab["v1"]["global_orient"], lab["v1"]["body_pose"], lab["v1"]["transl"])
    T = lab["v1"]["T_world_cam"]
    world = np.asarray(read_world_joints(sl / "joints_world.npz").joints)
    n1 = min(len(j1), len(world))
    back = np.einsum("tij,tkj->tki", T[:n1, :3, :3], j1[:n1]) + T[:n1, None, :3, 3]
    z = lab["v2"]
    n = min(len(z["frames"]), len(frames))
    T_cw = invert_T(z["T_world_cam"][:n])

    def px(go, body_pose, tr) -> float:
        c = pose(go, body_pose, tr)[1]
        p = np.einsum("ij,tkj->tki", z["K"], c / c[..., 2:])[..., :2]
        kp = z["keypoints"][:n]
        seen = (kp[..., 2] > 0.3) & z["valid"][:n, None]
        return float(np.median(np.linalg.norm(kp[..., :2] - p, axis=-1)[seen]))

    go, tr = params_in_camera(params.global_orient[:n], params.transl[:n], params.betas, T_cw, model)
    t1 = np.arange(len(frames)) / params.fps  # view 1's rows (a fit without gaps)
    flipped_t = 2 * t1[:n] - z["body_time_s"][:n]
    pf, trf, *_ = resample_motion(np.concatenate([params.global_orient, params.body_pose], 1), params.transl, t1, flipped_t)
    gof, trcf = params_in_camera(pf[:, :3], trf, params.betas, T_cw, model)
    return {"session": session.as_posix(), "v1_round_trip_max_mm": float(1e3 * np.abs(back - world[:n1]).max()),
            "v2_offset_frames": float(np.median((z["body_time_s"][:n] - t1[:n]) * params.fps)),
            "v2_px_at_own_instants": px(z["global_orient"][:n], z["body_pose"][:n], z["transl"][:n]),
            "v2_px_view1_rows": px(go, params.body_pose[:n], tr), "v2_px_offset_flipped": px(gof, pf[:, 3:], trcf)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("/work/bench/15t"))
    ap.add_argument("--seconds", type=float, default=6.0)
    ap.add_argument("--epochs", type=int, default=6)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--repeat", type=int, default=2, help="runs of the four rows, interleaved")
    ap.add_argument("--reexport", action="store_true", help="time the export again (removes the old one)")
    ap.add_argument("--fit-session", type=Path, default=None,
                    help="also check a session processed by the real pipeline (read only)")
    ap.add_argument("--only-fit-check", action="store_true", help="only the --fit-session check")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()

    if args.only_fit_check:
        print(json.dumps(fit_check(args.fit_session, args.work), indent=1))
        return
    root, timing = ensure_export(args.work, args.seconds, args.reexport)
    index = json.loads((root / "manifest.json").read_text())
    rows = []
    for _ in range(args.repeat):  # interleaved, so that a change of the machine's load hits every row
        rows += [read_rate(root, 0, args.epochs, args.batch),
                 read_rate(root, 2, args.epochs, args.batch),
                 read_rate(root, 2, args.epochs, max(1, args.batch // 8), clip=8),
                 read_rate(root, 2, args.epochs, args.batch, load_rgb=False)]
    result = {"export": root.as_posix(), "frames": index["frames"], "valid_frames": index["valid_frames"],
              "views": len(index["views"]), **{k: round(v, 2) for k, v in timing.items()},
              "export_ms_per_frame": round(1e3 * timing["export_s"] / index["frames"], 2) if "export_s" in timing else None,
              "rows": rows}
    if args.fit_session is not None:
        result["fit_check"] = fit_check(args.fit_session, args.work)
    print(json.dumps(result, indent=1))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
