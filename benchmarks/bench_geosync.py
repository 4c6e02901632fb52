"""Benchmark geometric sync, sub-frame sync and `embodmocap check` (issue 12, items 2-5).

Sessions are synthesised once under OUT and reused (``--prepare`` writes them and runs Stage I):

- ``normal_<seed>``: 6 s indoor/outdoor sessions whose second phone runs a random fraction of a
  frame off the first (``phone_offset_frames``, the truth is in ground_truth.json);
- ``fail_sep20``, ``fail_away``, ``fail_scene``: "built to fail" variants of ``normal_0`` (views 20
  degrees apart; performer out of view 2 for the second half; view 2 filmed in another room). They
  share seed 0's scene capture byte for byte, so Stage I's outputs are copied from ``normal_0``;
- ``long_60``: a 60 s session for the speed of `embodmocap check`.

Modes (each prints JSON rows and writes OUT/<mode>.json):

    OMP_NUM_THREADS=1 python benchmarks/bench_geosync.py prepare --out /work/bench/12b --seeds 0 1 2 3 4 5
    OMP_NUM_THREADS=1 python benchmarks/bench_geosync.py prepare-fail --out /work/bench/12b
    OMP_NUM_THREADS=1 python benchmarks/bench_geosync.py prepare-long --out /work/bench/12b
    OMP_NUM_THREADS=1 python benchmarks/bench_geosync.py geosync --out /work/bench/12b --seeds 0 1 2 3 4 5
    OMP_NUM_THREADS=1 python benchmarks/bench_geosync.py subframe --out /work/bench/12b --seeds 0 1 2 3
    OMP_NUM_THREADS=1 python benchmarks/bench_geosync.py check --out /work/bench/12b
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

SEEDS = list(range(6))
OUTDOOR = {6, 7}


def phone_offset(seed: int) -> float:
    """The studio's sub-frame phone offset of session ``normal_<seed>`` (frames)."""
    return float(np.round(np.random.default_rng([12, seed]).uniform(-0.45, 0.45), 3))


def _synth(path: Path, **kw) -> None:
    from embodmocap.synth.config import SynthConfig
    from embodmocap.synth.studio import synthesize

    if (path / "ground_truth" / "ground_truth.json").is_file():
        return
    if path.exists():
        shutil.rmtree(path)
    t0 = time.perf_counter()
    synthesize(SynthConfig(**kw), path)
    print(json.dumps({"synth": path.name, "seconds": round(time.perf_counter() - t0, 1)}), flush=True)


def _scene(path: Path) -> None:
    from embodmocap.scene import stage as scene_stage
    from embodmocap.scene.config import SceneConfig

    t0 = time.perf_counter()
    scene_stage.run(SceneConfig(), path)
    print(json.dumps({"scene": path.name, "seconds": round(time.perf_counter() - t0, 1)}), flush=True)


def prepare(out: Path, seeds: list[int]) -> None:
    """The normal sessions of ``seeds`` with Stage I."""
    for s in seeds:
        _synth(out / f"normal_{s}", seed=s, preset="outdoor" if s in OUTDOOR else "indoor", seconds=6.0,
               scene_seconds=15.0, phone_offset_frames=phone_offset(s))
        _scene(out / f"normal_{s}")


def prepare_fail(out: Path) -> None:
    """The built-to-fail variants of normal_0, with normal_0's Stage I outputs (same scene capture)."""
    base = dict(seed=0, preset="indoor", seconds=6.0, scene_seconds=15.0, phone_offset_frames=phone_offset(0))
    _synth(out / "fail_sep20", **base, view_separation_deg=20.0)
    _synth(out / "fail_away", **base, view2_away_fraction=0.5)
    _synth(out / "fail_scene", **base, view2_other_scene=True)
    for name in ("fail_sep20", "fail_away", "fail_scene"):
        src, dst = out / "normal_0" / "scenes", out / name / "scenes"
        if src.is_dir() and not dst.is_dir():
            shutil.copytree(src, dst)


def prepare_long(out: Path) -> None:
    _synth(out / "long_60", seed=100, preset="indoor", seconds=60.0, scene_seconds=15.0, phone_offset_frames=0.2)
    _scene(out / "long_60")


REGISTER_FRAMES = None  # --register-frames: fewer registered frames per view in Stage III (CPU budget)


def _stages(session: Path) -> None:
    """Stages II and III with default settings (skipped when up to date)."""
    from dataclasses import replace

    from embodmocap.calibrate import stage as stage3
    from embodmocap.sequence import stage as stage2
    from embodmocap.sequence.config import SequenceConfig

    t0 = time.perf_counter()
    stage2.run(SequenceConfig(), session)
    cfg = stage3.CalibrateConfig()
    if REGISTER_FRAMES:
        cfg = replace(cfg, register=replace(cfg.register, num_frames=REGISTER_FRAMES))
    stage3.run(cfg, session)
    print(json.dumps({"stages_2_3": session.name, "seconds": round(time.perf_counter() - t0, 1)}), flush=True)


def true_residual_frames(session: Path) -> float:
    """View 2's sequence frame minus view 1's for the same instant, given the slicing in sync.json:
    raw frame j of view v is the motion's instant start_v + j + phase_v."""
    from embodmocap.io.layout import SessionLayout

    lay = SessionLayout(session)
    gt = json.loads(lay.ground_truth.info.read_text())
    rec = json.loads(lay.sequence("seq0").sync.read_text())
    start, phase = gt["view_motion_start"], gt.get("view_time_offset_frames", {"v1": 0.0, "v2": 0.0})
    E = {v: rec["views"][v]["frame"] for v in ("v1", "v2")}
    return (start["v1"] + E["v1"] + phase["v1"]) - (start["v2"] + E["v2"] + phase["v2"])


def laser_ignored(session: Path, search_s: float) -> dict:
    """The geometric sync alone with a window of +-search_s around the slicing (wide enough that
    the laser's centring does not matter), from Stage III's registration offsets and the keypoints."""
    from embodmocap.io.layout import VIEWS, SessionLayout
    from embodmocap.sequence.geosync import geometric_sync
    from embodmocap.sequence.subframe import frame_times

    sl = SessionLayout(session).sequence("seq0")
    calib = json.loads(sl.calibration.read_text())
    fps = float(json.loads(sl.manifest.read_text())["figures"]["fps"])
    data = []
    for v in VIEWS:
        cams = np.load(sl.view(v).cameras)
        T = np.asarray(calib["views"][v]["T_world_vio_registration"]) @ cams["T_world_cam"]
        data.append((cams["K"], T, np.load(sl.view(v).keypoints)["keypoints"], frame_times(cams, fps)))
    t0 = time.perf_counter()
    r = geometric_sync(*data[0], *data[1], fps=fps, search_s=search_s)
    return {"offset_frames": r.offset_s * fps, "confidence": r.confidence, "std_frames": r.std_frames,
            "seconds": time.perf_counter() - t0}


def run_geosync(out: Path, seeds: list[int]) -> list[dict]:
    from embodmocap.io.layout import SessionLayout
    from embodmocap.io.stage_files import read_final_sync

    rows = []
    for s in seeds:
        session = out / f"normal_{s}"
        try:
            _stages(session)
        except Exception as err:  # noqa: BLE001 - a failed session is a reported row, not hidden
            rows.append({"session": session.name, "error": f"{type(err).__name__}: {err}"})
            print(json.dumps(rows[-1]), flush=True)
            continue
        rec = read_final_sync(SessionLayout(session).sequence("seq0")).record
        fps = 30.0
        truth = true_residual_frames(session)
        geo = rec["sources"]["geometric"]
        alone = laser_ignored(session, 5.0)
        rows.append({
            "session": session.name, "phone_offset_frames": phone_offset(s), "true_residual_frames": round(truth, 4),
            "laser_err_frames": round(0.0 - truth, 4),
            "geometric_err_frames": round(geo["residual_s"] * fps - truth, 4), "geometric_confidence": geo["confidence"],
            "geometric_std_frames": geo["std_frames"],
            "alone_5s_err_frames": round(alone["offset_frames"] - truth, 4), "alone_5s_confidence": round(alone["confidence"], 3),
            "alone_5s_seconds": round(alone["seconds"], 2),
            "chosen": rec["chosen"]["source"], "chosen_err_frames": round(rec["chosen"]["residual_s"] * fps - truth, 4),
        })
        print(json.dumps(rows[-1]), flush=True)
    ok = [r for r in rows if "error" not in r]
    for key in ("laser_err_frames", "geometric_err_frames", "alone_5s_err_frames", "chosen_err_frames"):
        a = np.abs([r[key] for r in ok])
        if len(a):
            print(f"{key}: median |err| {np.median(a):.3f}, max {a.max():.3f} frames over {len(a)} sessions")
    return rows


def run_nolaser(out: Path, seeds: list[int]) -> list[dict]:
    """Stages II-III end to end with the laser detector blinded (no event can pass its confidence):
    the views are sliced from their first frames and Stage III's geometric sync (+-5 s) alone gives
    the offset. Runs in ``nolaser_<seed>``, which links normal_<seed>'s inputs and Stage I outputs."""
    from dataclasses import replace

    from embodmocap.calibrate import stage as stage3
    from embodmocap.errors import InputError
    from embodmocap.io.layout import SessionLayout
    from embodmocap.io.stage_files import read_final_sync
    from embodmocap.sequence import stage as stage2
    from embodmocap.sequence.config import SequenceConfig
    from embodmocap.sequence.sync import SyncConfig

    rows = []
    for s in seeds:
        src, dst = out / f"normal_{s}", out / f"nolaser_{s}"
        dst.mkdir(exist_ok=True)
        for name in ("captures", "perception", "scenes", "ground_truth", "body_model.npz", "session.toml"):
            if not (dst / name).exists():
                (dst / name).symlink_to(src / name)
        t0 = time.perf_counter()
        stage2.run(SequenceConfig(sync=SyncConfig(min_confidence=1.01)), dst)
        cfg = stage3.CalibrateConfig()
        if REGISTER_FRAMES:
            cfg = replace(cfg, register=replace(cfg.register, num_frames=REGISTER_FRAMES))
        row = {"session": dst.name, "phone_offset_frames": phone_offset(s)}
        try:
            stage3.run(cfg, dst)
        except InputError as err:
            row["error"] = str(err)
        rec = read_final_sync(SessionLayout(dst).sequence("seq0")).record
        truth = true_residual_frames(dst)
        geo = rec["sources"].get("geometric", {})
        row.update({"slicing": rec["slicing"]["source"], "true_residual_frames": round(truth, 3),
                    "geometric_err_frames": None if geo.get("residual_s") is None else round(geo["residual_s"] * 30.0 - truth, 4),
                    "geometric_confidence": geo.get("confidence"), "geometric_std_frames": geo.get("std_frames"),
                    "chosen": rec["chosen"]["source"], "seconds": round(time.perf_counter() - t0, 1)})
        print(json.dumps(row), flush=True)
        rows.append(row)
    return rows


def run_subframe(out: Path, seeds: list[int]) -> list[dict]:
    """Stage IV with nearest-frame pairing (the laser slicing: sync.json's residual set to 0) and
    with sub-frame sync (the pipeline's choice), W-MPJPE of each against the truth."""
    from embodmocap.evaluate.session import sequence_errors
    from embodmocap.io.atomic import write_json
    from embodmocap.io.layout import SessionLayout
    from embodmocap.motion import stage as stage4

    rows = []
    for s in seeds:
        session = out / f"normal_{s}"
        _stages(session)
        lay = SessionLayout(session)
        path = lay.sequence("seq0").sync
        rec = json.loads(path.read_text())
        row = {"session": session.name, "phone_offset_frames": phone_offset(s),
               "residual_frames": rec["chosen"]["residual_frames"], "true_residual_frames": round(true_residual_frames(session), 3)}
        nearest = json.loads(json.dumps(rec))
        nearest["chosen"].update(residual_s=0.0, residual_frames=0.0)
        oracle = json.loads(json.dumps(rec))
        oracle["chosen"].update(residual_s=row["true_residual_frames"] / 30.0, residual_frames=row["true_residual_frames"])
        truth = _coco_truth(lay)
        try:
            for name, r in (("nearest", nearest), ("oracle_sync", oracle), ("subframe", rec)):
                write_json(path, r)
                t0 = time.perf_counter()
                stage4.run(stage4.MotionConfig(), session, force=True)
                e = sequence_errors(lay, "scene0", "seq0")
                row[f"{name}_w_mpjpe_mm"] = e["w_mpjpe_mm"]
                row[f"{name}_wa_mpjpe_mm"] = e["wa_mpjpe_mm"]
                row[f"{name}_pa_mpjpe_mm"] = e["pa_mpjpe_mm"]
                pts = np.load(lay.sequence("seq0").keypoints3d)["points"]
                err = np.linalg.norm(pts - truth[: len(pts)], axis=-1)
                row[f"{name}_keypoints3d_err_mm"] = round(1000 * float(np.nanmean(err)), 2)
                row[f"{name}_seconds"] = round(time.perf_counter() - t0, 1)
        finally:
            write_json(path, rec)
        print(json.dumps(row), flush=True)
        rows.append(row)
    return rows


def _coco_truth(lay) -> np.ndarray:
    """(T, 17, 3) true COCO-17 joints at view 1's sequence frames, in Stage I's world."""
    from embodmocap.geometry.transforms import invert_T

    g = np.load(lay.ground_truth.sequence("seq0"))
    T_ws = invert_T(np.load(lay.ground_truth.scene_device("scene0"))["T_scene_vio"])
    m = int(g["v1_motion_start"]) + np.load(lay.sequence("seq0").view("v1").cameras)["raw_frames"]
    return g["joints_coco17"][m] @ T_ws[:3, :3].T + T_ws[:3, 3]


def run_check(out: Path, seeds: list[int], only: list[str] | None = None) -> list[dict]:
    from embodmocap.check.config import CheckConfig
    from embodmocap.check.core import check_session

    rows = []
    names = only or [f"normal_{s}" for s in seeds] + ["fail_sep20", "fail_away", "fail_scene", "long_60"]
    for name in names:
        session = out / name
        if not (session / "session.toml").is_file():
            continue
        t0, c0 = time.perf_counter(), time.process_time()
        res = check_session(CheckConfig(), session)[0]
        f = res.figures
        rows.append({"session": name, "verdict": res.verdict, "wall_s": round(time.perf_counter() - t0, 1),
                     "cpu_s": round(time.process_time() - c0, 1), "seconds_of_capture": f.get("seconds"),
                     "both_seen": f.get("both_seen_fraction"), "angle_median_deg": (f.get("angle_deg") or {}).get("median"),
                     "registered": {v: d["registered"] for v, d in f.get("registration", {}).items()},
                     "geometric_offset_frames": f["sync"].get("geometric_offset_frames"),
                     "geometric_confidence": f["sync"].get("geometric_confidence"), "reasons": res.reasons})
        print(json.dumps(rows[-1]), flush=True)
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("mode", choices=["prepare", "prepare-fail", "prepare-long", "geosync", "nolaser", "subframe", "check"])
    ap.add_argument("--out", type=Path, default=Path("bench_out/geosync"))
    ap.add_argument("--seeds", type=int, nargs="*", default=SEEDS)
    ap.add_argument("--only", nargs="*", default=None, help="check: only these session folders")
    ap.add_argument("--register-frames", type=int, default=None,
                    help="Stage III: frames registered per view (default: the stage's 200)")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.mode == "prepare":
        prepare(args.out, args.seeds)
        return
    if args.mode == "prepare-fail":
        prepare_fail(args.out)
        return
    if args.mode == "prepare-long":
        prepare_long(args.out)
        return
    mod = sys.modules[__name__]
    mod.REGISTER_FRAMES = args.register_frames
    fn = getattr(mod, f"run_{args.mode}")
    rows = fn(args.out, args.seeds, args.only) if args.mode == "check" else fn(args.out, args.seeds)
    (args.out / f"{args.mode}.json").write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
