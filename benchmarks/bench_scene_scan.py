"""Scans that look at the floor (session 6): the studio's scene scan before and after, in tables.

1. ``--trajectories``: the 15 s scan's own poses (no rendering), per room and seed: the share of
   the walk area's floor inside some frame's depth frustum (5 cm grid, 67 deg x 4:3, 5 m, every 3rd
   frame), the 99th percentile turn rate and the share of frames whose top image edge is less than
   5 deg below the horizon (walls in view), for the outward-only scan, session 5's stop-and-turn
   glance and the default turning scan.
2. ``--before DIR --after DIR``: tables from two runs of ``bench_calibrate.py`` (Stage III) and
   ``bench_scene.py --eval-only --floor`` (Stage I) on the same seeds, one with the outward-only
   scan (presets ``+outward``), one with the default scan.
3. ``--range-weight R --sessions ... --out DIR``: Stage I's mesh again with
   ``SceneConfig.depth_weight_range_m = R`` on hard-linked copies (the sfm step reused), measured.

    OMP_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_scene_scan.py --trajectories --seeds 0 1 2 3 4
    OMP_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_scene_scan.py --before /work/bench/scan6/before \\
        --after /work/bench/scan6/after
    OMP_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_scene_scan.py --range-weight 2.5 --out /work/bench/scan6/rw25 \\
        --sessions /work/bench/scan6/after/indoor_3 /work/bench/scan6/after/large_2
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def floor_seen(spec, T: np.ndarray) -> float:
    from embodmocap.synth.config import SynthConfig
    from embodmocap.synth.trajectory import walk_area_floor_seen

    return walk_area_floor_seen(spec, T, SynthConfig().hfov_deg)


def trajectories(seeds: list[int]) -> None:
    from embodmocap.geometry.transforms import rotation_angle
    from embodmocap.synth import trajectory as tr
    from embodmocap.synth.scene import build_scene

    scans = {"outward only": tr.SceneWalkConfig(turns_per_lap=0.0),
             "glance (session 5)": tr.SceneWalkConfig(turns_per_lap=0.0, glance_every_s=15.0),
             "turning (default)": tr.SceneWalkConfig()}
    print("| room | scan | walk-area floor in frustums: per seed (%) | turn rate p99 (deg/s), max over seeds | frames with walls in view (%), min over seeds |")
    print("|---|---|---|---|---|")
    for room in ("standard", "large"):
        for name, cfg in scans.items():
            cov, rate, walls = [], [], []
            for seed in seeds:
                spec = build_scene("indoor", np.random.default_rng([seed, 1]), room).spec
                T = tr.scene_walk(spec, 15.0, 30.0, np.random.default_rng([seed, 5]), cfg)
                cov.append(100 * floor_seen(spec, T))
                dR = np.swapaxes(T[:-1, :3, :3], 1, 2) @ T[1:, :3, :3]
                rate.append(np.percentile(np.degrees(rotation_angle(dR)) * 30.0, 99))
                down = np.degrees(np.arcsin(-T[:, :3, 2][:, 2]))
                top = np.degrees(np.arctan(0.75 * np.tan(np.radians(33.5)))) - down
                walls.append(100 * np.mean(top > -5.0))
            print(f"| {room} | {name} | {' / '.join(f'{c:.0f}' for c in cov)} | {max(rate):.0f} | {min(walls):.0f} |")


def _rows(d: Path, stem: str) -> dict:
    out = {}
    for f in sorted(d.glob(f"{stem}*.json")):
        for r in json.loads(f.read_text()):
            out[(r["preset"].replace("+outward", ""), r["seed"])] = r
    return out


def tables(before: Path, after: Path) -> None:
    runs = {"outward only": (_rows(before, "bench_calibrate"), _rows(before, "bench_scene")),
            "turning (default)": (_rows(after, "bench_calibrate"), _rows(after, "bench_scene"))}
    keys = sorted({k for c, _ in runs.values() for k in c}, key=lambda k: (k[0] != "indoor", k[0], k[1]))
    print("| preset | seed | scan | walk-area floor: frustums / Stage I mesh (%) | Stage I accuracy (cm) | completeness (%) "
          "| SfM points | registered v1, v2 | registration only v1 / v2 (cm) | joint v1 / v2 (cm) | joint v1 / v2 (deg) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    agg: dict = {}
    for k in keys:
        for name, (cal, sc) in runs.items():
            c, s = cal.get(k), sc.get(k)
            if c is None or "error" in c or s is None:
                print(f"| {k[0]} | {k[1]} | {name} | missing |")
                continue
            print(f"| {k[0]} | {k[1]} | {name} | {s['floor_frustum_pct']} / {s['floor_mesh_pct']} | {s['accuracy_cm']} "
                  f"| {s['completeness_pct']} | {s['sfm_points']} | {c['v1_registered']}, {c['v2_registered']} "
                  f"| {c['v1_registration_cm']} / {c['v2_registration_cm']} | {c['v1_joint_cm']} / {c['v2_joint_cm']} "
                  f"| {c['v1_joint_deg']} / {c['v2_joint_deg']} |")
            for grp in ("easy (standard room)" if k[0] == "indoor" else "hard rooms", "all"):
                a = agg.setdefault((grp, name), {"n": [0, 0], "reg": [], "joint": [], "deg": [], "floor": [], "acc": [], "comp": []})
                for v in ("v1", "v2"):
                    got, tried = (int(x) for x in c[f"{v}_registered"].split("/"))
                    a["n"][0] += got
                    a["n"][1] += tried
                    a["reg"].append(c[f"{v}_registration_cm"])
                    a["joint"].append(c[f"{v}_joint_cm"])
                    a["deg"].append(c[f"{v}_joint_deg"])
                a["floor"].append(s["floor_mesh_pct"])
                a["acc"].append(s["accuracy_cm"])
                a["comp"].append(s["completeness_pct"])
    print()
    print("| studio | scan | views | frames registered | registration only: median cm | joint: median / max cm "
          "| joint: median deg | walk-area floor in the Stage I mesh (%) | Stage I accuracy: mean of seeds (cm) | completeness: min (%) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for (grp, name), a in sorted(agg.items(), key=lambda x: (x[0][0] == "all", x[0][0], x[0][1] != "outward only")):
        print(f"| {grp} | {name} | {len(a['joint'])} | {a['n'][0]}/{a['n'][1]} ({100 * a['n'][0] / max(a['n'][1], 1):.1f} %) "
              f"| {np.median(a['reg']):.2f} | {np.median(a['joint']):.2f} / {np.max(a['joint']):.2f} | {np.median(a['deg']):.3f} "
              f"| {min(a['floor'])}-{max(a['floor'])} | {np.mean(a['acc']):.2f} | {min(a['comp'])} |")


def range_weight(range_m: float, sessions: list[Path], out: Path) -> None:
    """Stage I with ``SceneConfig(depth_weight_range_m=range_m)`` on hard-linked copies of the
    sessions' inputs and scene outputs under OUT (the sfm step is reused, the mesh reruns), then
    ``bench_scene.py``'s Stage I figures with the walk-area floor."""
    import subprocess

    import bench_scene
    from embodmocap.scene import stage
    from embodmocap.scene.config import SceneConfig

    bench_scene.FLOOR = True
    out.mkdir(parents=True, exist_ok=True)
    for src in sessions:
        dst = out / src.name
        if not dst.exists():
            subprocess.run(["cp", "-al", str(src), str(dst)], check=True)
            subprocess.run(["rm", "-rf", str(dst / "sequences")], check=True)
        stage.run(SceneConfig(depth_weight_range_m=range_m), dst)
        r = bench_scene.evaluate(dst)
        print(json.dumps({"session": src.name, "range_m": range_m, **{k: r[k] for k in (
            "accuracy_cm", "completeness_pct", "floor_mesh_pct")}}), flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trajectories", action="store_true")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--before", type=Path)
    ap.add_argument("--after", type=Path)
    ap.add_argument("--range-weight", type=float, default=None,
                    help="rerun Stage I's mesh with this SceneConfig.depth_weight_range_m on copies of --sessions under --out")
    ap.add_argument("--sessions", type=Path, nargs="*", default=[])
    ap.add_argument("--out", type=Path, default=Path("bench_out/scan_range"))
    a = ap.parse_args()
    if a.range_weight is not None:
        range_weight(a.range_weight, a.sessions, a.out)
    if a.trajectories:
        trajectories(a.seeds)
    if a.before and a.after:
        tables(a.before, a.after)


if __name__ == "__main__":
    main()
