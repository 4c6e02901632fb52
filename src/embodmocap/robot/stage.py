"""``embodmocap robot retarget``: one sequence's world SMPL motion -> a robot's motion, files and report.

Reads (through :class:`SessionLayout`): ``sequences/<seq>/smpl_world.npz``, the session's body
model, the sequence's scene mesh (the simplified one when Stage I wrote it). Writes into
``sequences/<seq>/robot/<robot>/`` (see :mod:`embodmocap.robot.files`): ``qpos.npz``,
``motion.csv``, ``motion.npz``, ``motion_gmr.pkl``, ``scene.obj``, ``scene.xml``,
``robot_report.json`` and the stage manifest ``manifest.json``. Steps ``retarget``, ``export`` and
``report`` are each skipped when their inputs and config are unchanged; an interrupted
``retarget`` resumes from its last checkpoint (``qpos_partial.npz``, every ``checkpoint_frames``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from embodmocap.errors import InputError
from embodmocap.io.atomic import write_json, write_npz
from embodmocap.io.layout import SessionLayout
from embodmocap.io.stage_manifest import StageManifest, tracked_stage
from embodmocap.robot import solve
from embodmocap.robot.config import RetargetConfig, RobotConfig, load_robot_config
from embodmocap.robot.steps import STEPS

log = logging.getLogger(__name__)


def robot_config(robot: str = "g1", robot_config: str | Path | None = None) -> RobotConfig:
    """The robot: a TOML file when given, else a built-in robot by name."""
    if robot_config is not None:
        return load_robot_config(robot_config)
    from embodmocap.robot.g1 import BUILTIN_ROBOTS

    if robot not in BUILTIN_ROBOTS:
        raise InputError(None, f"unknown robot {robot!r}", f"use one of {', '.join(BUILTIN_ROBOTS)} or --robot-config FILE.toml")
    return BUILTIN_ROBOTS[robot]


def _scene_mesh_path(layout: SessionLayout, scene: str) -> Path:
    sc = layout.scene(scene)
    if sc.mesh_simplified.is_file():
        return sc.mesh_simplified
    if sc.mesh_raw.is_file():
        return sc.mesh_raw
    raise InputError(sc.mesh_raw, "missing scene mesh needed to keep the robot above the scene",
                     f"run `embodmocap scene {layout.root}` first")


@dataclass(frozen=True)
class RobotOutputs:
    """What ``embodmocap robot retarget`` produced for one sequence."""

    name: str
    robot: str
    folder: Path
    """The robot folder (``sequences/<seq>/robot/<robot>/`` unless ``out`` was given)."""
    figures: dict
    """Quality figures and timings, as in the stage manifest."""
    skipped: tuple[str, ...]
    """Steps that were up to date and not redone."""


@tracked_stage
def run(config: RetargetConfig, session: str | Path, seq: str | None = None, *, robot: str = "g1",
        robot_config_path: str | Path | None = None, out: str | Path | None = None,
        force: bool = False) -> RobotOutputs:
    """Retarget sequence ``seq`` of ``session`` to a robot and write every robot file.

    ``robot`` names a built-in robot, ``robot_config_path`` a TOML robot config (it wins);
    ``out`` replaces the default folder ``sequences/<seq>/robot/<robot>/``."""
    from embodmocap.body.model import load_body_model
    from embodmocap.io.amass import read_amass
    from embodmocap.io.manifest import load_manifest
    from embodmocap.io.mesh_file import read_mesh_ply
    from embodmocap.robot import files
    from embodmocap.robot.model import RobotModel

    layout = SessionLayout(Path(session))
    manifest = load_manifest(layout.manifest)
    entry = manifest.sequence(seq)
    sl = layout.sequence(entry.name)
    rcfg = robot_config(robot, robot_config_path)
    rm = RobotModel.load(rcfg)
    out_dir = Path(out) if out is not None else sl.robot_dir(rcfg.name)
    out_dir.mkdir(parents=True, exist_ok=True)
    if not sl.smpl_world.is_file():
        raise InputError(sl.smpl_world, "missing world SMPL motion", f"run `embodmocap motion {layout.root} --seq {entry.name}` first")
    mesh_path = _scene_mesh_path(layout, entry.scene)
    inputs = [sl.smpl_world, mesh_path, manifest.body_model, rm.mjcf]
    sm = StageManifest(out_dir / "manifest.json", "robot", {"robot": asdict(rcfg), "retarget": asdict(config)},
                       inputs=inputs, root=layout.root)
    fp_in = STEPS.fingerprint("retarget", config, context={"robot": asdict(rcfg)}, reads={
        "sequences/<seq>/smpl_world.npz": sl.smpl_world, "scene mesh": mesh_path, "body model": manifest.body_model,
        "robot MJCF": rm.mjcf})

    params, frames = read_amass(sl.smpl_world)
    if frames is not None and len(frames) > 1 and np.any(np.diff(np.asarray(frames)) != 1):
        log.warning("%s: the sequence frames have gaps; the robot motion plays its rows back to back at %.3f fps "
                    "(speed limits and velocities across a gap are not meaningful)", sl.smpl_world, params.fps)
    mesh = read_mesh_ply(mesh_path)[:2]
    inp = solve.robot_inputs(params, load_body_model(manifest.body_model), mesh[0], mesh[1], config)

    qpos_path = out_dir / "qpos.npz"
    partial = out_dir / "qpos_partial.npz"
    with sm.step("retarget", fp_in, force=force) as st:
        if st.run:
            q_done = _load_checkpoint(partial, fp_in, rm.model.nq) if not force else None
            if q_done is not None:
                log.info("%s: resuming the retargeting at frame %d of %d", out_dir, len(q_done), len(params))
            t0 = time.perf_counter()
            solved = list(q_done) if q_done is not None else []
            last = [time.perf_counter()]

            def progress(t: int, q: np.ndarray) -> None:
                solved.append(q)
                n = len(solved)
                if n % config.checkpoint_frames == 0 and n < len(params):
                    write_npz(partial, fingerprint=np.array(fp_in), qpos=np.asarray(solved))
                if time.perf_counter() - last[0] > 5.0 or n == len(params):
                    last[0] = time.perf_counter()
                    log.info("retargeting %s to %s: frame %d/%d (%.0f frames/s)", entry.name, rcfg.name, n, len(params),
                             (n - (0 if q_done is None else len(q_done))) / max(time.perf_counter() - t0, 1e-9))

            q, ht = solve.retarget_motion(rm, inp, config, q_done=q_done, progress=progress)
            seconds = time.perf_counter() - t0
            files.write_qpos(qpos_path, rm, q, params.fps, frames=frames, scale=ht.scale, contacts=ht.contacts)
            partial.unlink(missing_ok=True)
            st.record([qpos_path], {"robot": rcfg.name, "frames": len(q), "scale": round(ht.scale, 4),
                                    "retarget_frames_per_s": round(len(q) / max(seconds, 1e-9), 1)})
    qd = files.read_qpos(qpos_path)
    q = rm.qpos(qd["root_pos"], qd["root_quat_wxyz"], qd["joint_pos"])
    with sm.step("export", STEPS.fingerprint("export", config, after={"retarget": fp_in}, reads={"qpos.npz": qpos_path}),
                 force=force) as st:
        if st.run:
            outs = [files.write_motion_csv(out_dir / "motion.csv", rm, q),
                    files.write_tracking_npz(out_dir / "motion.npz", rm, q, params.fps, config.tracking_fps),
                    files.write_gmr_pkl(out_dir / "motion_gmr.pkl", rm, q, params.fps)]
            outs += files.write_scene(out_dir, rm, inp.heightmap, mesh, q[0])
            st.record(outs)

    report_path = out_dir / "robot_report.json"
    with sm.step("report", STEPS.fingerprint("report", config, after={"retarget": fp_in}, reads={"qpos.npz": qpos_path}),
                 force=force) as st:
        if st.run:
            rep = solve.motion_report(rm, q, inp, config)
            rep["version"] = files.ROBOT_FILES_VERSION
            rep["sequence"] = entry.name
            write_json(report_path, rep)
            st.record([report_path], {k: rep[k] for k in ("keypoint_residual_mean_m", "joint_limit_violations",
                                                          "foot_skating_max_m", "foot_penetration_max_m",
                                                          "self_collision_frames")})
    log.info("robot %s for %s: %s", rcfg.name, entry.name, out_dir)
    return RobotOutputs(entry.name, rcfg.name, out_dir, sm.figures(), tuple(sm.skipped))


def retarget_sequence(session: str | Path, seq: str | None = None, *, robot: str = "g1",
                      robot_config_path: str | Path | None = None, config: RetargetConfig = RetargetConfig(),
                      out: str | Path | None = None, force: bool = False) -> Path:
    """:func:`run`, for scripts written before it: returns the robot folder."""
    return run(config, session, seq, robot=robot, robot_config_path=robot_config_path, out=out, force=force).folder


def _load_checkpoint(path: Path, fp: str, nq: int) -> np.ndarray | None:
    """Frames solved by an interrupted run with the same inputs, or None."""
    if not path.is_file():
        return None
    try:
        with np.load(path) as z:
            if str(z["fingerprint"]) != fp or z["qpos"].ndim != 2 or z["qpos"].shape[1] != nq:
                return None
            return np.array(z["qpos"])
    except (OSError, KeyError, ValueError):
        return None
