"""Issue 16 (session 5b): ``sim check`` of our fit against its own Stage I mesh, before and after
the two fixes for turned-over floor triangles.

Per session (folders with Stages I-IV done and a ``ground_truth/``, read only; nothing is written
into them), the fit checked in:

- ``stored``: the session's ``mesh_simplified.ply`` as Stage I wrote it (the clustering before
  this fix), with the closest triangle alone deciding the side (``side_radius_m=0``: the old
  check) and with the sheet vote (the new default);
- ``resimplified``: the session's stored ``mesh_raw.ply`` simplified again by the current code
  (``scene.solve.simplified``, default ``SceneConfig``: the Stage I "simplify" step reads nothing
  else), old and new side rule;
- ``true_mesh_oracle``: the true scene mesh placed by the studio's true ``T_scene_vio`` (new rule),
  the reference the Stage I rows should approach.

Also per mesh: the share of the floor's area facing down (floor = faces within 3 cm of the true
floor plane and within 25 deg of horizontal, found with the true ``T_scene_vio``: an evaluation
figure only).

    OMP_NUM_THREADS=1 PYTHONPATH=src .venv/bin/python benchmarks/bench_sim_side.py \
        --sessions /work/bench/16/s5/fits2/hard_{0,1,2,3,4} --json /work/bench/16/s5b/bench_sim_side.json
    # the check's time on a 60 s sequence, old side rule vs new (one process):
    ... bench_sim_side.py --time /work/bench/16/s5b/cli/hard_2 --json /work/bench/16/s5b/time60.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from bench_sim import KEYS, fit_in_true_mesh, truth_sequence  # noqa: E402


def floor_down_share(v, f, T_scene_vio) -> float:
    """Share of the floor's area (in the true scene frame) whose faces point down."""
    v = np.asarray(v, float) @ T_scene_vio[:3, :3].T + T_scene_vio[:3, 3]
    tri = v[np.asarray(f)]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    a = np.linalg.norm(n, axis=1)
    nz = n[:, 2] / np.maximum(a, 1e-18)
    floor = (np.abs(tri[..., 2]).max(axis=1) < 0.03) & (np.abs(nz) > 0.9)
    return float(a[floor & (nz < 0)].sum() / max(a[floor].sum(), 1e-18))


def session_rows(session: Path) -> tuple[list[dict], dict]:
    from embodmocap.io.mesh_file import read_mesh_ply
    from embodmocap.scene import solve
    from embodmocap.scene.config import SceneConfig
    from embodmocap.sim.check import plausibility
    from embodmocap.sim.config import SimCheckConfig

    truth, fit = truth_sequence(session)
    T = np.load(session / "ground_truth" / "scene_scene0_device.npz")["T_scene_vio"]
    scene = session / "scenes" / "scene0"
    raw_v, raw_f, raw_c = read_mesh_ply(scene / "mesh_raw.ply")
    t0 = time.perf_counter()
    simple = solve.simplified(raw_v, raw_f, raw_c, SceneConfig())
    t_simplify = time.perf_counter() - t0
    floor = {"raw": floor_down_share(raw_v, raw_f, T),
             "stored": floor_down_share(fit.scene_vertices, fit.scene_faces, T),
             "resimplified": floor_down_share(simple.vertices, simple.faces, T),
             "faces_raw": int(len(raw_f)), "faces_stored": int(len(fit.scene_faces)),
             "faces_resimplified": int(len(simple.faces)), "simplify_s": t_simplify}
    resimplified = dataclasses.replace(fit, scene_vertices=np.asarray(simple.vertices, float),
                                       scene_faces=np.asarray(simple.faces, np.int64))
    old_rule, new_rule = SimCheckConfig(side_radius_m=0.0), SimCheckConfig()
    rows = []
    for kind, sq, cfg in (("stored_closest_alone", fit, old_rule), ("stored_sheet_vote", fit, new_rule),
                          ("resimplified_closest_alone", resimplified, old_rule),
                          ("resimplified_sheet_vote", resimplified, new_rule),
                          ("true_mesh_oracle", fit_in_true_mesh(truth, fit), new_rule)):
        s = plausibility(sq, cfg)["summary"]
        rows.append({"session": session.name, "kind": kind, "frames": s["frames"], "seconds": s["seconds"],
                     "unsupported_frames": s["unsupported_frames"], **{k: s[k] for k in KEYS}})
        print(json.dumps({k: (round(x, 3) if isinstance(x, float) else x) for k, x in rows[-1].items()}), flush=True)
    print(json.dumps({"session": session.name, "floor_down_share": {k: round(x, 4) for k, x in floor.items()}}), flush=True)
    return rows, floor


def check_time_60s(session: Path, variants: tuple[tuple[str, dict], ...] = (
        ("closest_alone", {"side_radius_m": 0.0}), ("new", {"side_radius_m": 0.3}))) -> dict:
    """Seconds of ``plausibility`` on the session's fit tiled to 60 s, per (name, SimCheckConfig
    settings) variant (default: old rule vs new), vertex strides 1 and 4, one process."""
    from embodmocap.sim.check import plausibility
    from embodmocap.sim.config import SimCheckConfig
    from embodmocap.sim.session import load_sequence

    sq = load_sequence(session, detail=True)  # as `sim check` reads it
    p = sq.params
    idx = np.tile(np.arange(len(p)), int(np.ceil(60.0 * p.fps / len(p))))[: int(round(60.0 * p.fps))]
    long = sq.with_params(dataclasses.replace(p, global_orient=p.global_orient[idx], body_pose=p.body_pose[idx],
                                              transl=p.transl[idx]))
    out = {"session": session.name, "frames": int(len(idx)), "scene_faces": int(len(sq.scene_faces)),
           "detail_faces": int(len(sq.detail_faces)) if sq.detail_faces is not None else 0}
    for stride in (1, 4):
        for name, settings in variants:
            t0 = time.perf_counter()
            plausibility(long, SimCheckConfig(vertex_stride=stride, **settings))
            out[f"seconds_stride_{stride}_{name}"] = round(time.perf_counter() - t0, 2)
            print(json.dumps(out), flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=Path, nargs="+", default=[])
    ap.add_argument("--json", type=Path)
    ap.add_argument("--time", type=Path, help="only time the check on this session's fit tiled to 60 s")
    a = ap.parse_args()
    if a.time:
        out = check_time_60s(a.time)
        if a.json:
            a.json.write_text(json.dumps(out, indent=1))
        return
    res: dict = {"date": time.strftime("%Y-%m-%d"), "sessions": [str(s) for s in a.sessions], "check": [], "floor": {}}
    for s in a.sessions:
        rows, floor = session_rows(s)
        res["check"] += rows
        res["floor"][s.name] = floor
        if a.json:  # written after each session: a long run leaves what it finished
            a.json.write_text(json.dumps(res, indent=1))
    for kind in sorted({r["kind"] for r in res["check"]}):
        sel = [r for r in res["check"] if r["kind"] == kind]
        res[f"{kind}_mean"] = {k: float(np.mean([r[k] for r in sel])) for k in KEYS}
        print(kind, json.dumps({k: round(v, 3) for k, v in res[f"{kind}_mean"].items()}), flush=True)
    if a.json:
        a.json.write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
