"""The synthetic dual-iPhone capture studio: a complete session with known answers.

``synthesize(config, out)`` writes, under ``out``, everything a real session would hold (the scene
capture, the two view captures, precomputed perception in standard formats, ``session.toml``) plus a
separate ``ground_truth/`` folder. Reading it top to bottom:

1. build a furnished scene (room or yard) with a solid procedural texture;
2. give the performer a random body shape and a scripted motion that uses the furniture;
3. one device walks the empty scene: render RGB + LiDAR-like depth, write a capture;
4. two operators follow the performer; each view has its own VIO world (random yaw/offset + drift)
   and its own recording start; a laser dot on a wall goes off at one instant (the sync event);
   render RGB (with the performer), depth, person mask; write each capture and the perception a
   real detector would give (keypoint JSON, mask PNGs, camera-space body prior);
5. write the ground truth and the manifest.

Timeline: the motion has frames ``0..M-1`` at ``fps``; the laser goes off at motion frame ``e``
(during the performer's initial idle). View ``k`` records motion frames ``start_k .. start_k +
n_k - 1``, so its raw sync frame (the first frame without the dot) is ``e - start_k``.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
from PIL import Image

from embodmocap.body.joints import smpl_to_coco17
from embodmocap.body.model import load_body_model
from embodmocap.body.testmodel import write_test_model
from embodmocap.geometry.transforms import apply_T, invert_T
from embodmocap.io.atomic import atomic_path, write_json, write_npz
from embodmocap.io.body_prior import write_body_prior
from embodmocap.io.layout import VIEWS, SessionLayout
from embodmocap.io.manifest import SceneEntry, SequenceEntry, SessionManifest, ViewEntry, write_manifest
from embodmocap.io.openpose import write_openpose_json
from embodmocap.synth import lidar, perception, trajectory
from embodmocap.synth.motion import MotionScriptConfig, script_motion
from embodmocap.synth import laser as laser_look
from embodmocap.synth.render import Renderer, RenderConfig
from embodmocap.synth.config import SynthConfig
from embodmocap.synth.scene import build_scene, write_scene_ply
from embodmocap.synth.sync_event import aim_at_dot, choose_dot, with_dot
from embodmocap.synth.vio import add_path_errors

log = logging.getLogger(__name__)

#: Version of the ground-truth files this module writes.
GT_VERSION = 1


@dataclass(frozen=True)
class SynthResult:
    """What ``synthesize`` wrote."""

    root: Path
    seconds_taken: float
    frames_rendered: int
    sync_frames: dict[str, int]


def _rng(seed: int, part: int) -> np.random.Generator:
    """An independent, reproducible generator per part, so changing one part's draws never
    shifts another part's."""
    return np.random.default_rng([seed, part])


def _take_rng(cfg: SynthConfig, part: int) -> np.random.Generator:
    """A generator of the performance's part ``part`` (performer, motion, operators, laser look,
    clocks, perception): take 0 draws the historic ones; another take draws its own while the room
    and its scan (:func:`_rng` of the seed) stay the same."""
    return _rng(cfg.seed, part) if cfg.take == 0 else np.random.default_rng([cfg.seed, part, cfg.take])


def _capture_writer(cfg: SynthConfig, out: Path):
    if cfg.format == "strayscanner":
        from embodmocap.io.captures.strayscanner import StrayScannerWriter

        return StrayScannerWriter(out, cfg.intrinsics(), cfg.fps)
    from embodmocap.io.captures.spectacular import SpectacularWriter

    return SpectacularWriter(out, cfg.intrinsics(), cfg.fps)


def synthesize(cfg: SynthConfig, out: str | Path) -> SynthResult:
    """Write a complete synthetic session into ``out`` (created; must not hold a session)."""
    t0 = time.perf_counter()
    # Absolute: the manifest resolves relative paths against the session folder, not the cwd.
    lay = SessionLayout(Path(os.path.abspath(out)))
    lay.root.mkdir(parents=True, exist_ok=True)
    K, K_depth = cfg.intrinsics(), cfg.depth_intrinsics()

    # 1. Scene (realistic laser sessions repaint the walls: the dot's background is part of the test).
    built = build_scene(cfg.preset, _rng(cfg.seed, 1), cfg.room)
    # The preset is part of the laser's seed: an indoor and an outdoor session of one seed draw
    # different dots (the benchmark's 40 views are 40 draws, not 20 seen twice).
    lrng = _rng(cfg.seed, 70 if cfg.preset == "indoor" else 71)
    wall_look = str(cfg.laser.walls[int(lrng.integers(len(cfg.laser.walls)))])
    if cfg.laser.mode != "easy":
        built = laser_look.with_wall_look(built, wall_look, lrng)
    if cfg.take:  # the walls are the scene's; the dot's look and the clothes are the take's
        lrng = _take_rng(cfg, 70 if cfg.preset == "indoor" else 71)

    # 2. Performer: shape and motion (scene frame).
    write_test_model(lay.body_model)
    body = load_body_model(lay.body_model)
    brng = _take_rng(cfg, 2)
    betas = np.zeros(body.num_betas)
    betas[:4] = brng.normal(0.0, [0.8, 0.6, 0.5, 0.5])
    # A false disappearance needs the view to see the dot before it, gone, and back before the event.
    lead_max_s = max(cfg.lead_min_s + 0.6, 1.0, cfg.laser.false_event_lead_s[1] + 0.4 if cfg.laser.false_event else 0.0)
    total_s = lead_max_s + cfg.seconds + 0.2
    script = script_motion(built.spec, body, betas, total_s, cfg.fps, _take_rng(cfg, 3),
                           MotionScriptConfig() if cfg.interactions is None else MotionScriptConfig(interactions=cfg.interactions))
    params = script.params
    M = len(params)
    out_body = body.from_params(params)
    verts = out_body.vertices.detach().cpu().numpy()
    coco = out_body.coco17.detach().cpu().numpy()
    # What the detector marks: COCO-17 points with the layout's own hip definition.
    layout = cfg.layout()
    kp_true = coco if layout == "COCO17" else smpl_to_coco17(out_body.joints, out_body.vertices, body.vertex_ids,
                                                             layout).detach().cpu().numpy()
    joints = out_body.joints.detach().cpu().numpy()
    faces = np.asarray(body.faces)

    # The sync event: inside the performer's initial idle, late enough for every view's lead.
    idle_end = next((end for name, start, end in script.segments if name == "idle"), int(lead_max_s * cfg.fps))
    event = int(min(round(lead_max_s * cfg.fps), max(idle_end - 3, round(cfg.lead_min_s * cfg.fps) + 1)))
    trng = _take_rng(cfg, 4)
    false_off = None  # motion frames [a, b) in which the dot is out of the false-event view
    if cfg.laser.false_event:
        frng = _take_rng(cfg, 90)
        a = event - int(round(frng.uniform(*cfg.laser.false_event_lead_s) * cfg.fps))
        false_off = (a, a + int(round(frng.uniform(*cfg.laser.false_event_gone_s) * cfg.fps)))
    starts, ends = {}, {}
    for v in VIEWS:
        lo = round(cfg.lead_min_s * cfg.fps)
        if false_off is not None and v == cfg.laser.false_event_view:
            lo = max(lo, event - false_off[0] + 8)  # the dot seen >= 8 frames before it leaves
        lead = int(trng.integers(min(lo, event), event + 1))
        starts[v] = event - lead
        ends[v] = M - int(trng.integers(0, round(cfg.tail_max_s * cfg.fps) + 1))

    # The operators' paths, and the laser dot: a wall point both see at the event, filmed until
    # shortly after it goes off (the cameras then turn back to the performer).
    pelvis = joints[:, 0]
    follow = trajectory.FollowConfig()
    if cfg.view_separation_deg is not None:
        follow = replace(follow, sep_deg=(cfg.view_separation_deg, cfg.view_separation_deg))
    T_v = trajectory.follow_views(built.spec, pelvis, cfg.fps, _take_rng(cfg, 10), follow)
    dot, normal = choose_dot(built, [T[event] for T in T_v], (verts[event], faces))
    built = with_dot(built, dot, normal)
    T_v = tuple(aim_at_dot(T, dot, event, cfg.fps) for T in T_v)
    if cfg.view2_away_fraction > 0:
        T_v = (T_v[0], trajectory.turn_away(T_v[1], int(round(M - cfg.view2_away_fraction * (M - event))), cfg.fps))
    clothes = laser_look.clothes_rgb(cfg.laser, lrng)
    rcfg = RenderConfig() if clothes is None else RenderConfig(body_rgb=clothes)
    renderer = Renderer(built, rcfg)
    renderers = {"v1": renderer, "v2": renderer}
    if cfg.view2_other_scene:
        # Another room (other seed), same laser dot coordinates: view 2 cannot register to the scene.
        other = build_scene(cfg.preset, _rng(cfg.seed + 7919, 1))
        renderers["v2"] = Renderer(with_dot(other, dot, normal), rcfg)
    looks: dict = {v: None for v in VIEWS}
    if cfg.laser.mode != "easy":  # the operators' hands wobble while they aim
        T_v = tuple(laser_look.hand_wobble(T, cfg.fps, cfg.laser, lrng) for T in T_v)
    if cfg.laser.mode == "realistic":
        dists = {v: laser_look.project(K, T_v[k][event], dot)[2] for k, v in enumerate(VIEWS)}
        looks = laser_look.draw_looks(cfg.laser, lrng, dists, K.fx, {v: event - starts[v] for v in VIEWS})

    # 3. Scene capture.
    frames_rendered = 0
    scene_T = trajectory.scene_walk(built.spec, cfg.scene_seconds, cfg.fps, _rng(cfg.seed, 5),
                                    trajectory.SceneWalkConfig(turns_per_lap=cfg.scan_turns_per_lap))
    scene_T_scene_vio = trajectory.random_T_scene_vio(_rng(cfg.seed, 6))
    scene_T_vio_cam = trajectory.add_drift(
        invert_T(scene_T_scene_vio) @ scene_T, cfg.fps, _rng(cfg.seed, 7), trajectory.DriftConfig()
    )
    log.info("scene capture: %d frames", len(scene_T))
    _write_capture(
        cfg, lay.scene_capture(cfg.scene_name), renderer, scene_T, scene_T_vio_cam, K, K_depth,
        body_verts=None, faces=faces, laser_on=np.zeros(len(scene_T), bool), rng=_rng(cfg.seed, 8),
        clock_offset_s=float(_rng(cfg.seed, 9).uniform(100, 1000)),
    )
    frames_rendered += len(scene_T)

    # 4. The views (every draw above was made for both, so v1 of a one-phone session is v1 of the
    # two-phone session of the same seed).
    filmed = VIEWS[:cfg.views]
    seq_gt: dict[str, np.ndarray] = {}
    sync_frames = {}
    detected: dict[str, np.ndarray] = {}
    for k, v in enumerate(filmed):
        span = np.arange(starts[v], ends[v])
        # Each frame's instant in motion frames: view 2 may run a fraction of a frame off view 1.
        phase = cfg.phone_phase_frames() if v == "v2" else 0.0
        t_motion = span + phase
        T_scene_cam = _at_times(T_v[k], t_motion)
        v_verts, v_coco = (_lerp_frames(a, t_motion) for a in (verts, kp_true))
        T_scene_vio = trajectory.random_T_scene_vio(_take_rng(cfg, 20 + k))
        T_vio_cam = trajectory.add_drift(
            invert_T(T_scene_vio) @ T_scene_cam, cfg.fps, _take_rng(cfg, 30 + k), trajectory.DriftConfig()
        )
        # The hard camera preset: scale error and drift that grow with the path (own generator, so
        # the standard studio's draws are untouched).
        T_vio_cam = add_path_errors(T_vio_cam, _take_rng(cfg, 90 + k), cfg.vio_errors())
        # The laser goes off half-way between motion frames e-1 and e.
        laser_on = (t_motion < event - 0.5) & (cfg.laser.mode != "none")
        if false_off is not None and v == cfg.laser.false_event_view:
            laser_on &= ~((t_motion >= false_off[0] - 0.5) & (t_motion < false_off[1] - 0.5))
        log.info("view %s: %d frames, sync frame %d", v, len(span), event - starts[v])
        gt_px, vis, masks_dir = _write_capture(
            cfg, lay.view_capture(cfg.sequence_name, v), renderers[v], T_scene_cam, T_vio_cam, K, K_depth,
            body_verts=v_verts, faces=faces, laser_on=laser_on, rng=_take_rng(cfg, 40 + k),
            clock_offset_s=float(_take_rng(cfg, 50 + k).uniform(100, 1000)),
            coco_world=v_coco, perception_dir=lay.perception(cfg.sequence_name, v),
            lighting=_lighting(_take_rng(cfg, 80 + k)) if cfg.lighting_change else None,
            look=looks[v], dot=dot,
        )
        frames_rendered += len(span)
        prng = _take_rng(cfg, 60 + k)
        noise = perception.HARD_KEYPOINT_NOISE if cfg.perception == "hard" else perception.KeypointNoiseConfig()
        kps = perception.noisy_keypoints(gt_px, vis, prng, noise)
        detected[v] = kps  # the keypoint files are written once both views' detections exist
        perc = lay.perception(cfg.sequence_name, v)
        if cfg.body_prior != "none":
            prior_params = type(params)(params.betas, params.global_orient[span], params.body_pose[span], params.transl[span], params.fps, params.gender)
            pcfg = perception.POOR_PRIOR_NOISE if cfg.body_prior == "poor" else perception.PriorNoiseConfig()
            prior = perception.body_prior(prior_params, T_scene_cam, body, prng, pcfg)
            write_body_prior(perc.body_prior, prior)
        sync_frames[v] = int(event - starts[v])
        seq_gt.update({
            f"{v}_T_scene_vio": T_scene_vio, f"{v}_T_scene_cam": T_scene_cam, f"{v}_T_vio_cam": T_vio_cam,
            f"{v}_motion_start": np.int64(starts[v]), f"{v}_sync_frame": np.int64(sync_frames[v]),
            f"{v}_keypoints2d_gt": gt_px, f"{v}_visibility": vis, f"{v}_time_offset_frames": np.float64(phase),
        })

    if cfg.edge_limb_frames > 0:  # the start of the sequence made hard for the left arm (issue 29)
        detected = perception.edge_limb_trouble(detected, sync_frames, cfg.edge_limb_frames, cfg.edge_limb,
                                                _take_rng(cfg, 90))
    for v in filmed:
        perc = lay.perception(cfg.sequence_name, v)
        for i, kp in enumerate(detected[v]):
            out_kp = perception.coco17_to_body25(kp) if layout == "BODY_25" else kp
            write_openpose_json(perc.keypoints_json(i), [out_kp] if kp[:, 2].max() > 0 else [])

    # 5. Ground truth and manifest.
    gt = lay.ground_truth
    write_scene_ply(built, gt.scene_mesh(cfg.scene_name))
    write_npz(gt.scene_device(cfg.scene_name), T_scene_vio=scene_T_scene_vio, T_scene_cam=scene_T, T_vio_cam=scene_T_vio_cam)
    write_npz(
        gt.sequence(cfg.sequence_name), version=np.int64(GT_VERSION),
        betas=params.betas, global_orient=params.global_orient, body_pose=params.body_pose, transl=params.transl,
        fps=np.float64(cfg.fps), joints_smpl24=joints, joints_coco17=coco, event_motion_frame=np.int64(event),
        joints_keypoints=kp_true, keypoint_layout=np.array(layout),
        segments=np.array([f"{n}:{s}:{e}" for n, s, e in script.segments]), **seq_gt,
    )
    write_json(gt.info, {
        "version": GT_VERSION, "config": asdict(cfg), "scene": cfg.scene_name, "sequence": cfg.sequence_name,
        "sync_frames": sync_frames, "motion_frames": M, "event_motion_frame": event,
        "view_motion_start": starts, "view_motion_end": ends, "laser_dot": dot, "laser_normal": normal,
        # Raw frame j of view v is the motion's instant start_v + j + offset_v (motion frames).
        "view_time_offset_frames": {v: (cfg.phone_phase_frames() if v == "v2" else 0.0) for v in filmed},
        # The false disappearance: its view and the raw frames of that view without the dot.
        "false_event": None if false_off is None else {
            "view": cfg.laser.false_event_view,
            "raw_frames": [int(false_off[0] - starts[cfg.laser.false_event_view]),
                           int(false_off[1] - starts[cfg.laser.false_event_view])]},
        "laser": {"mode": cfg.laser.mode, "wall": wall_look if cfg.laser.mode != "easy" else "scene",
                  "red_clothes": clothes is not None,
                  "views": {v: (asdict(looks[v]) if looks[v] is not None else None) for v in filmed}},
        "segments": [{"name": n, "start": s, "end": e} for n, s, e in script.segments],
        "furniture": {n: {"centre_xy": f.centre_xy, "yaw": f.yaw, "size": f.size, "top_z": f.top_z}
                      for n, f in built.spec.furniture.items()},
    })
    manifest = SessionManifest(
        root=lay.root,
        scenes={cfg.scene_name: SceneEntry(name=cfg.scene_name, capture=lay.scene_capture(cfg.scene_name), indoor=cfg.preset == "indoor")},
        sequences={cfg.sequence_name: SequenceEntry(
            name=cfg.sequence_name, scene=cfg.scene_name,
            views={v: ViewEntry(
                capture=lay.view_capture(cfg.sequence_name, v),
                keypoints=lay.perception(cfg.sequence_name, v).keypoints_dir,
                masks=lay.perception(cfg.sequence_name, v).masks_dir,
                body_prior=lay.perception(cfg.sequence_name, v).body_prior if cfg.body_prior != "none" else None,
            ) for v in filmed},
        )},
        body_model=lay.body_model,
    )
    write_manifest(manifest, lay.manifest)
    took = time.perf_counter() - t0
    log.info("synthetic session written to %s in %.1f s (%d frames rendered)", lay.root, took, frames_rendered)
    return SynthResult(lay.root, took, frames_rendered, sync_frames)


def _lighting(rng: np.random.Generator) -> tuple[float, np.ndarray]:
    """(exposure gain, (3,) white balance) of a view filmed under other light than the scan."""
    gain = float(rng.uniform(0.55, 0.75) if rng.random() < 0.5 else rng.uniform(1.35, 1.7))
    wb = 1.0 + rng.uniform(-0.15, 0.15, 3)
    return gain, wb / wb.mean()


def _lerp_frames(a: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Per-frame arrays (M, ...) at fractional motion frames t (N,), linearly (clamped to the ends).
    Exact (a copy of the rows) at integer t; between frames a smooth motion moves almost linearly."""
    from embodmocap.geometry.interpolate import bracket

    i0, w, _ = bracket(np.arange(len(a), dtype=np.float64), t)
    i1 = np.minimum(i0 + 1, len(a) - 1)
    w = w.reshape((-1,) + (1,) * (a.ndim - 1))
    return (1.0 - w) * a[i0] + w * a[i1]


def _at_times(T: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Camera poses (M, 4, 4) at fractional motion frames t (N,) (slerp + linear; exact at integers)."""
    from embodmocap.geometry.interpolate import interp_poses

    if np.all(t == np.round(t)):
        return T[t.astype(np.int64)]
    return interp_poses(T, np.arange(len(T), dtype=np.float64), np.clip(t, 0, len(T) - 1))[0]


def _write_capture(cfg, out, renderer, T_scene_cam, T_vio_cam, K, K_depth, *, body_verts, faces, laser_on, rng,
                   clock_offset_s, coco_world=None, perception_dir=None, lighting=None, look=None, dot=None):
    """Render and write one capture; for a view also write masks and return GT keypoints.
    ``lighting`` = (gain, white balance) relights the scene (:func:`embodmocap.synth.texture.relight`).

    Returns ``(gt_px (T,17,2), visibility (T,17), masks_dir)`` for a view, else ``(None, None, None)``.
    """
    n = len(T_scene_cam)
    writer = _capture_writer(cfg, out)
    lcfg = lidar.LidarConfig()
    gt_px = np.zeros((n, 17, 2))
    vis = np.zeros((n, 17))
    mrng = np.random.default_rng(rng.integers(1 << 62))
    try:
        for i in range(n):
            body = (body_verts[i], faces) if body_verts is not None else None
            post = None
            if look is not None:  # realistic dot: occluder and motion blur of this frame
                post = laser_look.frame_effects(look, K, T_scene_cam[max(i - 1, 0)], T_scene_cam[i],
                                                T_scene_cam[min(i + 1, n - 1)], dot, i)
            r = renderer.render(K, T_scene_cam[i], body, bool(laser_on[i]), K_depth, lighting=lighting,
                                laser_look=look, post=post)
            depth_mm, conf = lidar.simulate_lidar(r.depth_lr_m, rng, lcfg)
            writer.add_frame(r.rgb, depth_mm, conf, T_vio_cam[i], clock_offset_s + i / cfg.fps)
            if coco_world is not None:
                T_cam_scene = invert_T(T_scene_cam[i])
                pc = apply_T(T_cam_scene, coco_world[i])
                z = np.maximum(pc[:, 2], 1e-6)
                gt_px[i] = (K.K[:2, :2] @ (pc[:, :2] / z[:, None]).T).T + K.K[:2, 2]
                vis[i] = perception.joint_visibility(coco_world[i][None], K.K, T_scene_cam[i][None], r.depth_m[None])[0]
                mask = perception.noisy_mask(r.person_mask, mrng, perception.MaskNoiseConfig())
                path = perception_dir.mask_png(i)
                with atomic_path(path) as tmp:
                    Image.fromarray(mask.astype(np.uint8) * 255).save(tmp, format="PNG")
        imu_t, acc, gyr = trajectory.synth_imu(T_vio_cam, cfg.fps, rng)
        writer.add_imu(imu_t + clock_offset_s, acc, gyr)
    except BaseException:
        # Leave no capture that looks complete: the writer drops what it had written.
        getattr(writer, "abort", writer.close)()
        raise
    writer.close()
    if coco_world is None:
        return None, None, None
    return gt_px, vis, perception_dir.masks_dir if perception_dir else None
