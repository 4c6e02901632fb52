"""Every app version's export of the studio room through ``inspect`` and Stage I: the floor's tilt.

Shows, per capture variant (tests/capture_variants.py writes each in its app version's layout from
one rendered walk of the studio's indoor room, gravity-aligned VIO world of known yaw and offset),
the problems ``inspect`` finds, the app version it names, and Stage I's gravity check: the tilt of
the mesh's floor from horizontal (``floor_tilt_deg``) and the error of its height against the
room's true floor (known from the studio). A last row tilts the capture's world by 3 deg (a capture
whose gravity is wrong) to show the warning.

    PYTHONPATH=src nice -n 5 python benchmarks/bench_capture_variants.py --out /tmp/variants [--only stray9 ...]
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from capture_variants import VARIANTS, render_walk, write_variant  # noqa: E402

from embodmocap.io.inspect_capture import check_capture  # noqa: E402
from embodmocap.io.manifest import SceneEntry, SessionManifest, write_manifest  # noqa: E402
from embodmocap.scene import stage  # noqa: E402
from embodmocap.scene.config import SceneConfig  # noqa: E402
from embodmocap.scene.sfm import SfmConfig  # noqa: E402

CFG = SceneConfig(voxel_m_indoor=0.02, sfm=SfmConfig(max_images=30))


def run_one(name: str, out: Path, tilt_deg: float = 0.0) -> dict:
    big = name == "stray15"
    walk = (render_walk(160, 120, (64, 48), 4.0, 60.0, tilt_deg=tilt_deg) if big else
            render_walk(160, 120, (64, 48), 6.0, 30.0, portrait=VARIANTS[name][1], tilt_deg=tilt_deg))
    root = out / (name + (f"_tilt{tilt_deg:g}" if tilt_deg else ""))
    shutil.rmtree(root, ignore_errors=True)
    root.mkdir(parents=True)
    cap = write_variant(name, root / "capture", walk, big_video=(1920, 1440) if big else None)
    report = check_capture(cap)
    write_manifest(SessionManifest(root=root, scenes={"room": SceneEntry("room", cap, True)}), root / "session.toml")
    warnings: list[str] = []

    class Catch(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            if record.levelno >= logging.WARNING and "floor" in record.getMessage():
                warnings.append(record.getMessage())

    handler = Catch()
    logging.getLogger("embodmocap.scene.stage").addHandler(handler)
    t0 = time.perf_counter()
    try:
        figs = stage.run(CFG, root).figures
    finally:
        logging.getLogger("embodmocap.scene.stage").removeHandler(handler)
    tilt = figs.get("floor_tilt_deg")
    z = figs.get("floor_z_m")
    return {
        "variant": name + (f" (world tilted {tilt_deg:g} deg)" if tilt_deg else ""),
        "version": report.variant, "frames": report.num_frames, "fps": round(report.fps, 2),
        "video": f"{report.rgb_size[0]}x{report.rgb_size[1]}" if report.rgb_size else "?",
        "problems": len(report.problems), "floor_tilt_deg": tilt,
        "floor_z_err_cm": None if z is None else round(100 * abs(z - walk.floor_z_vio), 2),
        "floor_area_m2": figs.get("floor_area_m2"), "warned": bool(warnings),
        "stage_s": round(time.perf_counter() - t0, 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True, help="scratch folder for the sessions")
    ap.add_argument("--only", nargs="*", default=None, help="variants to run (default: all)")
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = ap.parse_args()
    names = args.only or list(VARIANTS)
    rows = [run_one(n, args.out) for n in names]
    if not args.only:
        rows.append(run_one("stray9", args.out, tilt_deg=3.0))
    print("| variant | video, fps, frames | inspect problems | floor tilt (deg) | floor height error (cm) | floor area (m^2) | warned | Stage I (s) |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['variant']} | {r['video']}, {r['fps']:g}, {r['frames']} | {r['problems']} | {r['floor_tilt_deg']} | "
              f"{r['floor_z_err_cm']} | {r['floor_area_m2']} | {'yes' if r['warned'] else 'no'} | {r['stage_s']} |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
