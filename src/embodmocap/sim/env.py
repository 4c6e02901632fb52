"""The paper's scene-aware tracking task as a Gymnasium environment (``EmbodMocap/SceneTracking-v0``).

The performer's MuJoCo model (:mod:`embodmocap.sim.model`) stands in the captured scene (its support
heightfield) and follows a reference clip from a session (every fitted sequence, or one; a folder
of sessions gives all their clips; each clip keeps its own scene and body shape).

**Episode**: starts at a random reference frame (``random_start``) in the reference state, lasts
``episode_s`` = 10 s (300 control steps at 30 Hz; past its end the clip holds its last frame), and
ends early (``terminated``) when the mean body position error exceeds ``terminate_m``.

**Action** (69,) in [-1, 1]: PD targets of the 69 hinges, ``target = mid + a * half`` of each
hinge's range (MimicKit's normalisation). :meth:`TrackingEnv.reference_action` is the action whose
targets are the reference pose of the next step (the tracker's "ideal" action).

**Observation** (float32), all in the character's heading frame (origin at the root, x along the
root's facing direction projected on the ground, z up):

- proprioception: body positions relative to the root (23 x 3), body orientations as quaternions
  wxyz with w >= 0 (24 x 4), linear and angular velocities (24 x 3 each), root height above the
  support under it (1);
- targets: for each of ``future_steps`` (1, 2, 3 steps ahead: the paper's T, T+1, T+2) the
  reference bodies' positions relative to the simulated root (24 x 3), orientations (24 x 4),
  linear and angular velocities (24 x 3 each);
- height map: the paper's 11 x 11 egocentric grid, 0.2 m apart (2 m x 2 m), centred on the root
  and turning with the heading, row ``i`` at ``(i - 5) * 0.2`` m ahead, column ``k`` at ``(k - 5) *
  0.2`` m to the left, read from the 0.05 m support map (nearest cell), as heights relative to the
  root (support z - root z), the lowest support height outside the map.

**Reward** (the paper's): ``w_p exp(-100 mean|p - p^|^2) + w_r exp(-10 mean angle(q, q^)^2) + w_v
exp(-0.1 mean|v - v^|^2) + w_w exp(-0.1 mean|w - w^|^2) - w_s |a_t - a_{t-1}|^2``, means over the 24
bodies, world frame, clipped at 0 (a negative step reward with early termination would pay the
policy to fall); the maximum is 1 (weights 0.25 each).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap.geometry.heightmap import egocentric_heightmap
from embodmocap.geometry.rotations import canonical_quat, quat_conj, quat_mul, quat_to_matrix, wxyz_to_xyzw, xyzw_to_wxyz
from embodmocap.sim.config import HumanoidConfig, SceneCollisionConfig, TrackingConfig
from embodmocap.sim.deps import gymnasium, mujoco
from embodmocap.sim.model import hinge_ranges
from embodmocap.sim.reference import Clip, make_clip

log = logging.getLogger(__name__)
gym = gymnasium()


def tracking_table(lengths_s: NDArray, success_s: float = 8.0) -> dict:
    """The paper's tracking table from episode lengths (seconds): success = tracked longer than
    ``success_s`` (8 of 10 s); rates in %, lengths mean and std per group."""
    x = np.asarray(lengths_s, dtype=np.float64)
    ok = x > success_s

    def stats(v):
        return (float(v.mean()), float(v.std())) if len(v) else (float("nan"), float("nan"))

    (sm, ss), (fm, fs) = stats(x[ok]), stats(x[~ok])
    return {"episodes": int(len(x)), "success_rate": float(100 * ok.mean()) if len(x) else float("nan"),
            "failure_rate": float(100 * (~ok).mean()) if len(x) else float("nan"),
            "success_len_mean_s": sm, "success_len_std_s": ss, "failure_len_mean_s": fm, "failure_len_std_s": fs}


def tracking_success(lengths_s: NDArray, success_s: float = 8.0) -> float:
    """Fraction of episodes (started at random frames, 10 s long) that tracked longer than ``success_s``."""
    x = np.asarray(lengths_s, dtype=np.float64)
    return float((x > success_s).mean()) if len(x) else float("nan")


def _session_folders(path: Path) -> list[Path]:
    if (path / "session.toml").is_file():
        return [path]
    found = sorted(p.parent for p in path.glob("*/session.toml"))
    if not found:
        from embodmocap.errors import InputError

        raise InputError(path, "neither a session (no session.toml) nor a folder of sessions", "give a session folder")
    return found


def load_clips(session, seq: str | None = None, cfg: TrackingConfig = TrackingConfig(),
               humanoid: HumanoidConfig = HumanoidConfig(), scene: SceneCollisionConfig = SceneCollisionConfig()) -> list[Clip]:
    """Reference clips of a session, a folder of sessions, or a list of either (``seq``: only that sequence)."""
    from embodmocap.io.layout import SessionLayout
    from embodmocap.io.manifest import load_manifest
    from embodmocap.sim.session import load_sequence, sequence_mjcf

    paths = [session] if isinstance(session, (str, Path)) else list(session)
    clips = []
    for p in paths:
        for folder in _session_folders(Path(p)):
            names = [seq] if seq else [e.name for e in load_manifest(SessionLayout(folder).manifest).active_sequences()
                                       if SessionLayout(folder).sequence(e.name).smpl_world.is_file()]
            for name in names:
                sq = load_sequence(folder, name)
                xml, hm, qpos = sequence_mjcf(sq, humanoid, scene, keyframes=False)
                clips.append(make_clip(f"{folder.name}/{name}", xml, hm, qpos, sq.params.fps, cfg.control_hz))
    if not clips:
        from embodmocap.errors import InputError

        raise InputError(Path(paths[0]), "no fitted sequence to track", "run `embodmocap motion` first")
    return clips


def _heading(quat_wxyz: NDArray) -> float:
    """Yaw of the root's forward (body x) axis projected on the ground (MuJoCo's w x y z input)."""
    R = quat_to_matrix(wxyz_to_xyzw(quat_wxyz), invalid="nan")
    return float(np.arctan2(R[1, 0], R[0, 0])) if np.isfinite(R[0, 0]) else 0.0  # zero before mj_forward


class TrackingEnv(gym.Env):
    """Scene-aware motion tracking (see the module docstring for spaces, reward and episodes).

    Args:
        session: a session folder, a folder of sessions, or a list of them; or ``clips`` prebuilt.
        seq: track only this sequence (default: every fitted one).
        config: the task's settings.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 30}

    def __init__(self, session=None, seq: str | None = None, config: TrackingConfig = TrackingConfig(),
                 humanoid: HumanoidConfig = HumanoidConfig(), scene: SceneCollisionConfig = SceneCollisionConfig(),
                 clips: list[Clip] | None = None, render_mode: str | None = None) -> None:
        self.mj = mujoco()
        self.cfg = config
        self.clips = clips if clips is not None else load_clips(session, seq, config, humanoid, scene)
        self.render_mode = render_mode
        self._models: dict[int, tuple] = {}
        lo, hi = hinge_ranges().T
        self._mid, self._half = (lo + hi) / 2, (hi - lo) / 2
        self._future = np.asarray(config.future_steps, dtype=np.int64)
        self._max_steps = int(round(config.episode_s * config.control_hz))
        self._use(0)
        D = len(self._observe())
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (D,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (69,), np.float32)
        self._renderer = None
        #: ``"mujoco"`` (offscreen OpenGL, 640 x 480) or ``"raycast"`` (the package's ray caster,
        #: 320 x 240: :mod:`embodmocap.sim.raycast_view`, no OpenGL needed).
        self.render_backend = "mujoco"
        self._scene_mesh: tuple | None = None

    # ------------------------------------------------------------------ model per clip

    def _use(self, c: int) -> None:
        if c not in self._models:
            m = self.mj.MjModel.from_xml_string(self.clips[c].xml)
            self._models[c] = (m, self.mj.MjData(m))
        self.model, self.data = self._models[c]
        self.clip = self.clips[c]
        self._clip_index = c
        self._substeps = max(1, int(round(1.0 / (self.cfg.control_hz * self.model.opt.timestep))))
        self._mass = float(self.model.body_subtreemass[1])
        self._start, self._step = 0, 0
        self._prev_action = np.zeros(69)

    def _ref(self, k: int):
        """Reference state at sample k (held at rest past the end)."""
        cl = self.clip
        if k < len(cl):
            return cl.qpos[k], cl.xpos[k], cl.xquat[k], cl.vel[k], cl.angvel[k]
        z = np.zeros_like(cl.vel[-1])
        return cl.qpos[-1], cl.xpos[-1], cl.xquat[-1], z, z

    # ------------------------------------------------------------------ gymnasium API

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = options or {}
        c = int(options.get("clip", self.np_random.integers(len(self.clips))))
        self._use(c)
        n = len(self.clip)
        start = options.get("start")
        if start is None:
            start = int(self.np_random.integers(max(n - 1, 1))) if self.cfg.random_start else 0
        self._start, self._step = int(start), 0
        m, d = self.model, self.data
        self.mj.mj_resetData(m, d)
        d.qpos[:] = self.clip.qpos[self._start]
        d.qvel[:] = self.clip.qvel[min(self._start, n - 1)]
        d.ctrl[:] = np.clip(d.qpos[7:], self._mid - self._half, self._mid + self._half)
        self.mj.mj_forward(m, d)
        self._prev_action = self.reference_action()
        return self._observe(), {"clip": self.clip.name, "start": self._start}

    def reference_action(self) -> NDArray[np.float32]:
        """The action whose PD targets are the reference pose one step ahead."""
        q = self._ref(self._start + self._step + 1)[0][7:]
        return np.clip((q - self._mid) / self._half, -1.0, 1.0).astype(np.float32)

    def step(self, action):
        a = np.clip(np.asarray(action, dtype=np.float64).reshape(69), -1.0, 1.0)
        m, d = self.model, self.data
        d.ctrl[:] = self._mid + a * self._half
        k = self._start + self._step + 1
        for _ in range(self._substeps):
            if self.cfg.root_assist:
                self._assist(k)
            self.mj.mj_step(m, d)
        self._step += 1
        reward, err = self._reward(k, a)
        self._prev_action = a
        terminated = bool(err > self.cfg.terminate_m) or not np.isfinite(d.qpos).all()
        truncated = self._step >= self._max_steps
        info = {"tracking_error_m": err, "time_s": self._step / self.cfg.control_hz}
        if not np.isfinite(d.qpos).all():  # a diverged simulation: end, with a finite observation
            self.mj.mj_resetData(m, d)
            d.qpos[:] = self.clip.qpos[min(k, len(self.clip) - 1)]
            self.mj.mj_forward(m, d)
        return self._observe(), float(reward), terminated, truncated, info

    def _assist(self, k: int) -> None:
        """Residual root PD force/torque towards the reference root (``root_assist``)."""
        d = self.data
        q = self._ref(k)[0]
        s = self._mass / 70.0
        kp, kd = self.cfg.root_assist_kp * s, 2.0 * np.sqrt(self.cfg.root_assist_kp) * s
        f = kp * (q[:3] - d.qpos[:3]) - kd * d.qvel[:3]
        dq = canonical_quat(quat_mul(quat_conj(wxyz_to_xyzw(d.qpos[3:7])), wxyz_to_xyzw(q[3:7])))
        R = d.xmat[1].reshape(3, 3)
        rotvec_world = R @ (2.0 * dq[:3])  # small-angle body-frame error to world
        tau = 0.1 * kp * rotvec_world - 0.1 * kd * (R @ d.qvel[3:6])
        d.xfrc_applied[1, :3], d.xfrc_applied[1, 3:] = f, tau

    # ------------------------------------------------------------------ reward and observation

    def _bodies(self):
        d = self.data
        xpos, xquat = d.xpos[1:], d.xquat[1:]
        root_com = d.subtree_com[1]
        ang = d.cvel[1:, :3]
        lin = d.cvel[1:, 3:] + np.cross(ang, xpos - root_com)
        return xpos, xquat, lin, ang

    def _reward(self, k: int, a: NDArray) -> tuple[float, float]:
        xpos, xquat, lin, ang = self._bodies()
        _, rpos, rquat, rvel, rang = self._ref(k)
        dp = ((xpos - rpos) ** 2).sum(-1)
        dq = np.abs((xquat * rquat).sum(-1)).clip(0, 1)
        angle = 2.0 * np.arccos(dq)
        c = self.cfg
        r = (c.w_pos * np.exp(-100.0 * dp.mean()) + c.w_rot * np.exp(-10.0 * (angle ** 2).mean())
             + c.w_vel * np.exp(-0.1 * ((lin - rvel) ** 2).sum(-1).mean())
             + c.w_angvel * np.exp(-0.1 * ((ang - rang) ** 2).sum(-1).mean())
             - c.w_smooth * float(((a - self._prev_action) ** 2).sum()))
        # Clipped at 0: with early termination a negative step reward would teach the policy to
        # end episodes sooner (fall on purpose) rather than track.
        return max(float(r), 0.0), float(np.sqrt(dp).mean())

    def _observe(self) -> NDArray[np.float32]:
        xpos, xquat, lin, ang = self._bodies()
        root = xpos[0]
        yaw = _heading(xquat[0])
        c, s = np.cos(yaw), np.sin(yaw)
        Rh = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # world -> heading frame
        qh = np.array([0.0, 0.0, -np.sin(yaw / 2), np.cos(yaw / 2)])  # heading^-1 as a quaternion

        def in_heading(q):  # quaternions, MuJoCo's w x y z in and out (the observation keeps that layout)
            return xyzw_to_wxyz(canonical_quat(quat_mul(qh, wxyz_to_xyzw(q))))

        hm = self.clip.heightmap
        ground = egocentric_heightmap(hm, root[:2], np.float64(yaw), size=1, spacing=0.0)
        floor = float(np.nanmin(hm.heights))
        ground = float(ground.ravel()[0]) if np.isfinite(ground).all() else floor
        parts = [((xpos[1:] - root) @ Rh.T).ravel(), in_heading(xquat).ravel(), (lin @ Rh.T).ravel(),
                 (ang @ Rh.T).ravel(), [root[2] - ground]]
        k = self._start + self._step
        for f in self._future:
            _, rpos, rquat, rvel, rang = self._ref(k + int(f))
            parts += [((rpos - root) @ Rh.T).ravel(), in_heading(rquat).ravel(), (rvel @ Rh.T).ravel(),
                      (rang @ Rh.T).ravel()]
        grid = egocentric_heightmap(hm, root[:2], np.float64(yaw), size=self.cfg.heightmap_size,
                                    spacing=self.cfg.heightmap_spacing_m, fill=floor)
        parts.append((grid - root[2]).ravel())
        return np.concatenate([np.asarray(p, dtype=np.float64).ravel() for p in parts]).astype(np.float32)

    # ------------------------------------------------------------------ rendering

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        heading = 90.0 + np.degrees(_heading(self.data.xquat[1]))
        if self.render_backend == "raycast":
            from embodmocap.sim.raycast_view import free_camera_pose, heightmap_mesh, render_state

            if self._scene_mesh is None or self._scene_mesh[0] is not self.clip.heightmap:
                self._scene_mesh = (self.clip.heightmap, heightmap_mesh(self.clip.heightmap))
            T = free_camera_pose(self.data.xpos[1], 3.5, heading, -20.0)
            return render_state(self.mj, self.model, self.data, self.clip.heightmap, T, scene_mesh=self._scene_mesh[1])
        if self._renderer is None or self._renderer_model is not self.model:
            self._renderer = self.mj.Renderer(self.model, 480, 640)
            self._renderer_model = self.model
        cam = self.mj.MjvCamera()
        cam.lookat[:] = self.data.xpos[1]
        cam.distance, cam.azimuth, cam.elevation = 3.5, heading, -20.0
        self._renderer.update_scene(self.data, cam)
        return self._renderer.render()

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
