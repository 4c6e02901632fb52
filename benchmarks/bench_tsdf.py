"""TSDF throughput: Open3D's ScalableTSDFVolume against the plain NumPy reference, same key frames.

Makes a synthetic session (or reuses one given with ``--session``), picks the scene capture's key
frames as stage I does, reads their depth and colour into memory once (so decoding is not timed),
then integrates the same frames with Open3D and with :class:`~embodmocap.scene.tsdf.NumpyTSDF` at
the same voxel size, and reports frames/s of each, their ratio, extraction times and, when the
session has ground truth, each mesh's accuracy / completeness. Open3D is also timed at the
production voxel size. Not a test: run it by hand.

    .venv/bin/python benchmarks/bench_tsdf.py [--session DIR] [--voxel 0.02] [--json out.json]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before open3d loads (see embodmocap.scene)

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from embodmocap.evaluate.mesh_metrics import scene_mesh_metrics
from embodmocap.io.atomic import write_json
from embodmocap.io.captures import open_capture
from embodmocap.io.layout import SessionLayout
from embodmocap.io.manifest import load_manifest
from embodmocap.scene.config import SceneConfig
from embodmocap.scene.depth import fusion_frames
from embodmocap.scene.keyframes import choose_keyframes
from embodmocap.scene.tsdf import NumpyTSDF, fuse_open3d


def _session(args) -> Path:
    if args.session:
        return Path(args.session)
    from embodmocap.synth.config import SynthConfig
    from embodmocap.synth.studio import synthesize

    out = Path(tempfile.mkdtemp(prefix="bench_tsdf_")) / "session"
    t = time.perf_counter()
    synthesize(SynthConfig(seed=args.seed, seconds=1.0, scene_seconds=args.scene_seconds), out)
    print(f"synthesised {out} in {time.perf_counter() - t:.1f} s")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--session", help="existing session folder (default: synthesise one)")
    ap.add_argument("--scene-seconds", type=float, default=20.0, help="length of the synthesised scene capture")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--voxel", type=float, default=0.02, help="voxel (m) of the Open3D vs NumPy comparison")
    ap.add_argument("--max-frames", type=int, default=60, help="key frames integrated by NumPy (and Open3D)")
    ap.add_argument("--json", help="write the figures here")
    args = ap.parse_args()

    root = _session(args)
    lay = SessionLayout(root)
    scene_name, entry = next(iter(load_manifest(lay.manifest).scenes.items()))
    cap = open_capture(entry.capture)
    cfg = SceneConfig()
    indoor = entry.indoor
    sel = choose_keyframes(cap, cfg, indoor)
    gt_device = lay.ground_truth.scene_device(scene_name)
    if gt_device.is_file():  # true poses: the timing does not care, the accuracy figures do
        T = np.load(gt_device)["T_scene_cam"][sel.frame_ids]
    else:
        T = cap.trajectory.T_world_cam[sel.rows]
    ids, T = sel.frame_ids[: args.max_frames], T[: args.max_frames]
    frames = list(fusion_frames(cap, ids, T, cfg, indoor))
    n = len(frames)
    trunc = cfg.depth_trunc_m(indoor)
    K = cap.depth_intrinsics
    print(f"{n} key frames of {cap.path} (depth {K.width}x{K.height})")

    results: dict = {"session": str(root), "frames": n, "depth_size": [K.width, K.height], "voxel_m": args.voxel}
    meshes = {}

    t = time.perf_counter()
    v, f, _ = fuse_open3d(iter(frames), args.voxel, cfg.sdf_trunc_voxels * args.voxel, trunc)
    o3d_s = time.perf_counter() - t
    meshes["open3d"] = (v, f)

    # The NumPy grid covers the Open3D mesh's bounds plus the truncation band.
    pad = cfg.sdf_trunc_voxels * args.voxel
    ref = NumpyTSDF(v.min(0) - pad, v.max(0) + pad, args.voxel, pad, trunc)
    t = time.perf_counter()
    ref.integrate_frames(frames)
    np_int_s = time.perf_counter() - t
    t = time.perf_counter()
    vn, fn, _ = ref.extract_mesh()
    np_ext_s = time.perf_counter() - t
    meshes["numpy"] = (vn, fn)

    # Open3D integration alone (extraction timed apart) at the comparison and production voxels.
    import open3d as o3d

    def o3d_integrate(voxel: float) -> tuple[float, float]:
        vol = o3d.pipelines.integration.ScalableTSDFVolume(
            voxel_length=voxel, sdf_trunc=cfg.sdf_trunc_voxels * voxel,
            color_type=o3d.pipelines.integration.TSDFVolumeColorType.RGB8)
        intr = o3d.camera.PinholeCameraIntrinsic(K.width, K.height, K.fx, K.fy, K.cx, K.cy)
        t0 = time.perf_counter()
        for rgb, depth, _, Tc in frames:
            rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
                o3d.geometry.Image(rgb), o3d.geometry.Image(depth), depth_scale=1.0, depth_trunc=trunc,
                convert_rgb_to_intensity=False)
            vol.integrate(rgbd, intr, np.linalg.inv(Tc))
        t1 = time.perf_counter()
        vol.extract_triangle_mesh()
        return t1 - t0, time.perf_counter() - t1

    o3d_int_s, o3d_ext_s = o3d_integrate(args.voxel)
    prod_voxel = cfg.voxel_m(indoor)
    prod_int_s, prod_ext_s = o3d_integrate(prod_voxel)

    results.update({
        "open3d_integrate_fps": n / o3d_int_s, "open3d_extract_s": o3d_ext_s, "open3d_total_s": o3d_s,
        "numpy_integrate_fps": n / np_int_s, "numpy_extract_s": np_ext_s, "numpy_grid": [int(s) for s in ref.shape],
        "speedup_open3d_over_numpy": np_int_s / o3d_int_s,
        "production_voxel_m": prod_voxel, "open3d_production_integrate_fps": n / prod_int_s,
        "open3d_production_extract_s": prod_ext_s,
    })
    print(f"voxel {args.voxel} m: Open3D {n / o3d_int_s:7.1f} frames/s (extract {o3d_ext_s:.2f} s) | "
          f"NumPy {n / np_int_s:6.2f} frames/s on a {ref.shape} grid (extract {np_ext_s:.2f} s) | "
          f"ratio {np_int_s / o3d_int_s:.0f}x")
    print(f"voxel {prod_voxel} m (production): Open3D {n / prod_int_s:7.1f} frames/s (extract {prod_ext_s:.2f} s)")

    gt_mesh = lay.ground_truth.scene_mesh(scene_name)
    if gt_mesh.is_file():
        import trimesh

        gm = trimesh.load(gt_mesh, process=False)
        for name, (mv, mf) in meshes.items():
            m = scene_mesh_metrics(mv, mf, gm.vertices, gm.faces, T, K, trunc, n_samples=100_000)
            results[f"{name}_metrics"] = m
            print(f"{name:>7}: accuracy {100 * m['accuracy_m']:.2f} cm, completeness {100 * m['completeness']:.1f} %")
    if args.json:
        write_json(args.json, results)
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
