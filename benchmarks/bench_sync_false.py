"""Benchmark (issue 29, item 3): automatic sync with a false disappearance in one view, through the
real pipeline, no oracle.

Each session is a studio session whose false-event view (``laser.false_event``: the dot leaves that
view's frame shortly before the real switch-off and comes back) alternates v1 / v2 over the takes,
with realistic laser dots (wall looks cycled over the scenes), hard perception (OpenPose BODY_25
with the studio's hard detector noise) and the second phone a random fraction of a frame off. Stage I
(scene), Stage II (sequence: laser sync, slicing, observations) and Stage III (calibrate: the
registration, the geometric sync and the laser/geometry choice) run as the CLI runs them; the final
offset (``final_sync.json``, slicing + residual) is scored against the studio's truth. Nothing of
the truth reaches the pipeline.

To keep the CPU cost low, several takes share one room: take ``k`` of a seed
(:attr:`embodmocap.synth.config.SynthConfig.take`) films a new performance (performer, motion,
operators, dot look, clocks, lead of the false event) in the seed's room with the seed's scene
capture, byte for byte, so the first take's Stage I outputs are linked into the others and Stage I
finds them up to date (its fingerprints are content-based). Per session: the error of the final
offset in frames, its source, whether the geometry overrode the laser, whether the run stopped (the
first line of the error), and, with ``--check``, ``embodmocap check``'s verdict and whether it
names the override or the choice among a view's laser events.

Target: the right offset (|error| <= 1 frame) in >= 19 of 20 sessions, and no run stopped.

    OMP_NUM_THREADS=1 PYTHONPATH=src nice -n 5 .venv/bin/python benchmarks/bench_sync_false.py \\
        --scenes indoor:0 outdoor:1 indoor:2 outdoor:3 --takes 5 --out /tmp/sync_false \\
        --json /tmp/sync_false/sync_false.json --check

Sessions already complete under ``--out`` are reused (their stages resume); ``--redo`` reruns
Stages II-III (Stage I stays).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

WALLS = ("scene", "reddish", "magenta", "beige", "grey", "textured")
VIEWS = ("v1", "v2")
#: The default rooms (their index picks the wall look of the realistic dot).
ALL_SCENES = ("indoor:0", "outdoor:1", "indoor:2", "outdoor:3")


def session_config(preset: str, seed: int, scene_index: int, take: int, seconds: float, scene_seconds: float):
    """The studio settings of one take (see the module docstring)."""
    from embodmocap.synth.config import LaserConfig, SynthConfig

    laser = LaserConfig(mode="realistic", walls=(WALLS[scene_index % len(WALLS)],), false_event=True,
                        false_event_view=VIEWS[take % 2])
    offset = float(np.round(np.random.default_rng([29, seed, take]).uniform(-0.45, 0.45), 3))
    return SynthConfig(seed=seed, take=take, preset=preset, seconds=seconds, scene_seconds=scene_seconds,
                       perception="hard", laser=laser, phone_offset_frames=offset)


def _cli(args: list[str], log: Path) -> tuple[int, str]:
    """Run ``embodmocap ARGS`` in a child process (as a user would); the return code and the last
    error line (the CLI's one clear error)."""
    env = dict(os.environ, OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "1"))
    with open(log, "a") as f:
        f.write(f"\n$ embodmocap {' '.join(args)}\n")
        f.flush()
        p = subprocess.run([sys.executable, "-m", "embodmocap.cli", *args], stdout=f, stderr=subprocess.STDOUT, env=env)
    lines = [ln for ln in log.read_text().splitlines() if ln.strip()]
    err = next((ln for ln in reversed(lines) if "rror" in ln), lines[-1] if lines else "")
    return p.returncode, err[:300]


def run_take(root: Path, preset: str, seed: int, scene_index: int, take: int, args) -> dict:
    from embodmocap.evaluate.session import subframe_sync_err_frames
    from embodmocap.io.layout import SessionLayout
    from embodmocap.synth.studio import synthesize

    cfg = session_config(preset, seed, scene_index, take, args.seconds, args.scene_seconds)
    out = root / f"{preset}_{seed}_t{take}"
    lay = SessionLayout(out)
    t0 = time.perf_counter()
    first = root / f"{preset}_{seed}_t0"
    if not lay.ground_truth.info.is_file():
        if out.exists():
            shutil.rmtree(out)
        if take == 0 or not (first / "captures" / "scene0").is_dir():
            synthesize(cfg, out)
        else:
            # The scene capture of take k is take 0's byte for byte (SynthConfig.take;
            # tests/test_synth_studio.py): render a token one and link take 0's files in its place.
            synthesize(replace(cfg, scene_seconds=0.2), out)
            for rel in ("captures/scene0", "ground_truth/scene_scene0_device.npz", "ground_truth/scene_scene0_mesh.ply"):
                if (out / rel).is_dir():
                    shutil.rmtree(out / rel)
                elif (out / rel).exists():
                    (out / rel).unlink()
                if (first / rel).exists():
                    subprocess.run(["cp", "-al", str(first / rel), str(out / rel)], check=True)
            info = json.loads(lay.ground_truth.info.read_text())
            info["config"]["scene_seconds"] = cfg.scene_seconds
            lay.ground_truth.info.write_text(json.dumps(info, indent=2))
    t_synth = time.perf_counter() - t0
    if take > 0 and not (out / "scenes").exists() and (first / "scenes").exists():
        # The same scene capture: the first take's Stage I outputs are up to date here.
        subprocess.run(["cp", "-al", str(first / "scenes"), str(out / "scenes")], check=True)
    if args.redo and (out / "sequences").exists():
        shutil.rmtree(out / "sequences")
    info = json.loads(lay.ground_truth.info.read_text())
    row = {"session": out.name, "preset": preset, "seed": seed, "take": take, "truth": info["sync_frames"],
           "false_event": info["false_event"], "phone_offset_frames": cfg.phone_offset_frames, "stopped": None}
    log = out / "bench.log"
    times = {"synth": round(t_synth, 1)}
    for stage in ("scene", "sequence", "calibrate"):
        t1 = time.perf_counter()
        rc, err = _cli([stage, str(out)], log)
        times[stage] = round(time.perf_counter() - t1, 1)
        if rc != 0:
            row["stopped"] = f"{stage}: {err}"
            break
    row["seconds"] = times
    sl = lay.sequence("seq0")
    if row["stopped"] is None:
        rec = json.loads(sl.final_sync.read_text())
        ch = rec["chosen"]
        geo = rec["sources"].get("geometric") or {}
        laser = rec["sources"]["laser"]
        row.update(
            error_frames=subframe_sync_err_frames(lay, "seq0"), source=ch["source"],
            overrides_laser=bool(ch.get("overrides_laser")), reason=ch.get("reason"),
            geometric_confidence=geo.get("confidence"),
            laser_candidates={v: [c["frame"] for c in d.get("candidates", [])] for v, d in laser["views"].items()},
            laser_frames={v: d.get("frame") for v, d in laser["views"].items()},
            consistent_pair=(laser.get("consistent_pair") or {}).get("frames"),
            geometry_confirms=laser.get("geometry_confirms"),
            slicing=json.loads(sl.sync.read_text())["slicing"]["source"],
            warnings=rec.get("warnings", []))
    chose = row["stopped"] is None and (row["overrides_laser"] or row["consistent_pair"] is not None)
    if args.check and (chose or args.check_all) and row["stopped"] is None:
        t1 = time.perf_counter()
        p = subprocess.run([sys.executable, "-m", "embodmocap.cli", "check", str(out), "--json"],
                           capture_output=True, text=True, env=dict(os.environ, OMP_NUM_THREADS="1"))
        times["check"] = round(time.perf_counter() - t1, 1)
        try:
            res = json.loads(p.stdout)
            seqs = res.get("sequences", [res])
            s0 = seqs[0] if isinstance(seqs, list) else next(iter(seqs.values()))
            text = json.dumps(s0)
            row["check"] = {"rc": p.returncode, "verdict": s0.get("verdict"),
                            "decision": (s0.get("figures", {}).get("sync") or {}).get("decision"),
                            "names_override": "geometric offset will be used" in text,
                            "names_choice": "several laser events" in text}
        except (json.JSONDecodeError, StopIteration, AttributeError, IndexError) as e:
            row["check"] = {"rc": p.returncode, "error": f"{type(e).__name__}: {(p.stderr or p.stdout)[-300:]}"}
    if not args.keep:
        shutil.rmtree(out / "sequences", ignore_errors=True)
    return row


def summarise(rows: list[dict]) -> dict:
    ok = [r for r in rows if r["stopped"] is None and r.get("error_frames") is not None]
    errs = [abs(r["error_frames"]) for r in ok]
    out = {"sessions": len(rows), "stopped": len(rows) - len(ok),
           "within_1_frame": sum(e <= 1.0 for e in errs),
           "median_abs_error_frames": round(float(np.median(errs)), 3) if errs else None,
           "max_abs_error_frames": round(max(errs), 3) if errs else None,
           "sources": {s: sum(r["source"] == s for r in ok) for s in sorted({r["source"] for r in ok})},
           "geometry_overrode_laser": sum(r["overrides_laser"] for r in ok),
           "consistent_pair_used": sum(r["consistent_pair"] is not None for r in ok)}
    checked = [r for r in ok if "check" in r and "verdict" in r["check"]]
    if checked:
        over = [r for r in checked if r["overrides_laser"]]
        out["check"] = {"sessions": len(checked), "overrides": len(over),
                        "overrides_named": sum(r["check"]["names_override"] for r in over),
                        "verdicts": {v: sum(r["check"]["verdict"] == v for r in checked)
                                     for v in sorted({str(r["check"]["verdict"]) for r in checked})}}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=list(ALL_SCENES),
                    help="rooms as preset:seed")
    ap.add_argument("--takes", type=int, default=5, help="takes per room (false-event view alternates)")
    ap.add_argument("--first-take", type=int, default=0,
                    help="first take (a second worker can run takes 5.. of rooms whose take 0 ran elsewhere)")
    ap.add_argument("--seconds", type=float, default=3.0, help="performance after the event, seconds")
    ap.add_argument("--scene-seconds", type=float, default=8.0, help="scene capture, seconds")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--keep", action="store_true", help="keep the sequences' outputs")
    ap.add_argument("--redo", action="store_true", help="rerun Stages II-III")
    ap.add_argument("--check", action="store_true",
                    help="also run embodmocap check where Stage III chose against the laser's best pair")
    ap.add_argument("--check-all", action="store_true", help="with --check: on every session")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    rows, t0 = [], time.perf_counter()
    for take in range(args.first_take, args.first_take + args.takes):  # take-major: every room's Stage I early, then the takes
        for spec in args.scenes:
            preset, seed = spec.split(":")
            i = ALL_SCENES.index(spec) if spec in ALL_SCENES else len(ALL_SCENES) + int(seed)
            r = run_take(args.out, preset, int(seed), i, take, args)
            rows.append(r)
            print(json.dumps(r), flush=True)
            if args.json:
                _write(args, rows, t0)
    summary = _write(args, rows, t0)
    print(json.dumps(summary["summary"], indent=1))
    m = summary["summary"]
    return 0 if m["stopped"] == 0 and m["within_1_frame"] >= 0.95 * m["sessions"] else 1


def _write(args, rows, t0) -> dict:
    summary = {"calibration": "pipeline (Stages I-III, no oracle)", "seconds": args.seconds,
               "scene_seconds": args.scene_seconds, "summary": summarise(rows),
               "wall_s": round(time.perf_counter() - t0, 1), "rows": rows}
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.json.with_suffix(".tmp")
        tmp.write_text(json.dumps(summary, indent=2) + "\n")
        tmp.replace(args.json)
    return summary


if __name__ == "__main__":
    raise SystemExit(main())
