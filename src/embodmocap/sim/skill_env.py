"""The six interaction skills as Gymnasium environments (``EmbodMocap/Skill-<name>-v0``).

``gymnasium.make("EmbodMocap/Skill-sit-v0", session=PATH)`` (follow, sit, climb, lie, prone,
support): the performer's MuJoCo humanoid (:mod:`embodmocap.sim.model`) in the captured scene (its
support heightfield), and the skill's clips read from ``SESSION/sequences/<seq>/skills/skills.json``
(written by ``embodmocap skills SESSION``; docs/formats.md). Each clip gives the task's goal (the
target, the object's box, the follow path) and its reference frames for the style reward.

**Reference**: a clip's frames from its ``start`` to the end of its hold (``contact_end``; its
``end`` for follow): the interaction itself, without the standing up that may follow.

**Episode**: a random clip; the humanoid starts in the clip's first reference state (or, with
``random_start``, a random one before its contact), in the clip's own scene and body; lasts
``episode_s`` = 10 s at 30 Hz; ends early (``terminated``) on a fall (head below
``fall_head_m`` above the floor) or a diverged simulation. At the end ``info`` holds ``success``
(the paper's test, :func:`embodmocap.skills.tasks.success`) and ``error_m`` (its contact error).

**Action** (69,) in [-1, 1]: PD targets of the 69 hinges, as in ``EmbodMocap/SceneTracking-v0``.

**Observation** (float32): proprioception (358), heading frame (origin at the root, x along its
facing on the ground, z up): body positions relative to the root (23 x 3), body rotations (24 x 6,
6D), linear and angular velocities (24 x 3 each), root height above the floor (1); then the
skill's task observation (:mod:`embodmocap.skills.tasks`: follow 20, sit 38, climb 27, lie 38,
prone 35, support 27).

**Reward**: the task reward (in [0, 1]). The style reward needs the discriminator, which lives in
the trainer (:mod:`embodmocap.sim.skill_train`): every step's ``info["amp_obs"]`` is the (s_t,
s_t+1) transition in the layout of :mod:`embodmocap.sim.amp`, and :attr:`SkillEnv.reference_transitions`
holds the clips' own transitions (the discriminator's real data).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.sim.amp import AMP_TRANSITION_SIZE, amp_frame_features, clip_transitions
from embodmocap.sim.config import HumanoidConfig, SceneCollisionConfig, SkillConfig
from embodmocap.sim.deps import gymnasium, mujoco
from embodmocap.sim.model import BODY_NAMES, hinge_ranges
from embodmocap.sim.reference import Clip, make_clip
from embodmocap.skills import tasks
from embodmocap.io.stage_files import read_skills
from embodmocap.skills.tasks.common import heading_frame, rot6d

log = logging.getLogger(__name__)
gym = gymnasium()

PROPRIO_SIZE = 23 * 3 + 24 * 6 + 24 * 3 + 24 * 3 + 1
_IDX = {n: i for i, n in enumerate(BODY_NAMES)}


def skills_json_path(session: Path, seq: str) -> Path:
    """``SESSION/sequences/<seq>/skills/skills.json``."""
    from embodmocap.io.layout import SessionLayout

    return SessionLayout(Path(session)).sequence(seq).skills_json


@dataclass(frozen=True)
class SkillClip:
    """One skill clip of skills.json, with its reference motion at the control rate.

    Attributes:
        id: the clip's id; skill: its skill; session, seq: where it comes from.
        ref: the reference clip (:class:`embodmocap.sim.reference.Clip`) of frames [start, end).
        contact: control-rate sample of the contact's start (None: follow).
        goal: the task's goal (batch of one), world frame.
        floor_z: the scene's floor height.
    """

    id: str
    skill: str
    session: Path
    seq: str
    ref: Clip
    contact: int | None
    goal: tasks.SkillGoal
    floor_z: float


def _goal(c, skill: str, root_q: NDArray, fps: float, floor_z: float, path: Path) -> tasks.SkillGoal:
    """The task goal of one skills.json clip (:class:`embodmocap.io.stage_files.SkillClip`; its
    reference root positions ``root_q`` (n, 3))."""
    one = lambda a: None if a is None else np.asarray(a, dtype=np.float64)[None]  # noqa: E731
    if skill == "follow":
        p = c.target.path
        if not p or len(p) < 2:
            raise InputError(path, f"follow clip {c.id} has no target path", "rerun `embodmocap skills`")
        return tasks.SkillGoal(path=np.asarray(p, dtype=np.float64), ground_z=one(floor_z))
    obj, pos = c.object, c.target.position
    if obj is None or pos is None:
        raise InputError(path, f"{skill} clip {c.id} has no object box or target position", "rerun `embodmocap skills`")
    R = np.asarray(obj.R_world_box, dtype=np.float64)
    size = np.asarray(obj.size, dtype=np.float64)
    axis = R[:2, 0] if size[0] >= size[1] else R[:2, 1]
    # Standing beside the object before lying: the last upright root position before the contact.
    k = c.contact_start
    k = len(root_q) - 1 if k is None else int(np.clip(k - c.start, 0, len(root_q) - 1))
    up = root_q[: k + 1, 2] - floor_z >= 0.9 * (root_q[0, 2] - floor_z)
    stand = root_q[int(np.nonzero(up)[0].max()) if up.any() else 0]
    return tasks.SkillGoal(target=one(pos), box_center=one(obj.center), box_rot=R[None],
                           box_corners=np.asarray(obj.corners, dtype=np.float64)[None],
                           long_axis=(axis / np.linalg.norm(axis))[None], stand_point=stand[None],
                           stand_z=one(root_q[0, 2]), ground_z=one(floor_z))


def load_skill_clips(session, skill: str, seq: str | None = None, control_hz: float = 30.0,
                     humanoid: HumanoidConfig = HumanoidConfig(),
                     scene: SceneCollisionConfig = SceneCollisionConfig()) -> list[SkillClip]:
    """The ``skill`` clips of a session, a folder of sessions, or a list of either."""
    from embodmocap.io.layout import SessionLayout
    from embodmocap.io.manifest import load_manifest
    from embodmocap.sim.env import _session_folders

    if skill not in tasks.SKILLS:
        raise ValueError(f"unknown skill {skill!r}: one of {', '.join(tasks.SKILLS)}")
    paths = [session] if isinstance(session, (str, Path)) else list(session)
    out: list[SkillClip] = []
    looked: list[Path] = []
    for p in paths:
        for folder in _session_folders(Path(p)):
            lay = SessionLayout(folder)
            names = [seq] if seq else [e.name for e in load_manifest(lay.manifest).active_sequences()
                                       if lay.sequence(e.name).smpl_world.is_file()]
            for name in names:
                path = skills_json_path(folder, name)
                looked.append(path)
                if not path.is_file():
                    raise InputError(path, "no skill clips (skills.json missing)",
                                     f"run `embodmocap skills {folder}` first")
                mine = read_skills(path).of_skill(skill)
                if not mine:
                    continue
                xml, hm, qpos, fps = _sequence_model(folder, name, humanoid, scene)
                floor = float(np.nanmin(hm.heights))
                for c in mine:
                    # The reference ends with the interaction (its hold's end, when it has one):
                    # a clip that goes on to stand up again would teach the style of leaving.
                    s = c.start
                    e = c.contact_end if c.contact_end is not None else c.end
                    if not (0 <= s < e <= len(qpos)) or e - s < 2:
                        raise InputError(path, f"clip {c.id} frames [{s}, {e}) outside the sequence's {len(qpos)}",
                                         "rerun `embodmocap skills` on the current motion")
                    ref = make_clip(f"{folder.name}/{name}/{c.id}", xml, hm, qpos[s:e], fps, control_hz)
                    contact = c.contact_start
                    contact = None if contact is None else int(round((contact - s) / fps * control_hz))
                    goal = _goal(c, skill, qpos[s:e, :3], fps, floor, path)
                    out.append(SkillClip(c.id, skill, folder, name, ref, contact, goal, floor))
    if not out:
        raise InputError(looked[0] if looked else Path(paths[0]), f"no {skill!r} clip in skills.json",
                         f"run `embodmocap skills` on a session with a {skill} interaction, or pick another skill")
    return out


_SEQUENCE_CACHE: dict[tuple, tuple] = {}


def _sequence_model(folder: Path, name: str, humanoid: HumanoidConfig, scene: SceneCollisionConfig) -> tuple:
    """``(xml, heightmap, qpos, fps)`` of a sequence, kept for the process: the six environments
    and a trainer's parallel copies share one build (the height map skins every frame). Keyed by
    the inputs' paths and modification times, so a refitted sequence is rebuilt."""
    from embodmocap.sim.session import load_sequence, sequence_mjcf

    sq = load_sequence(folder, name)
    key = (str(folder.resolve()), name, humanoid, scene,
           tuple((str(p), p.stat().st_mtime_ns) for p in sq.inputs if p.is_file()))
    if key not in _SEQUENCE_CACHE:
        xml, hm, qpos = sequence_mjcf(sq, humanoid, scene, keyframes=False)
        _SEQUENCE_CACHE.clear()  # one sequence at a time is the common case; bound the memory
        _SEQUENCE_CACHE[key] = (xml, hm, qpos, float(sq.params.fps))
    return _SEQUENCE_CACHE[key]


def _batch_goal(g: tasks.SkillGoal, time_s: float) -> tasks.SkillGoal:
    return tasks.SkillGoal(**{**vars(g), "time_s": np.array([time_s])})


class SkillEnv(gym.Env):
    """One interaction skill (see the module docstring for spaces, reward and episodes).

    Args:
        session: a session folder, a folder of sessions, or a list of them; or ``clips`` prebuilt.
        skill: follow, sit, climb, lie, prone or support.
        seq: only this sequence (default: every fitted one).
        config: the task's settings.
    """

    metadata = {"render_modes": [], "render_fps": 30}

    def __init__(self, session=None, skill: str = "sit", seq: str | None = None, config: SkillConfig = SkillConfig(),
                 humanoid: HumanoidConfig = HumanoidConfig(), scene: SceneCollisionConfig = SceneCollisionConfig(),
                 clips: list[SkillClip] | None = None, render_mode: str | None = None) -> None:
        self.mj = mujoco()
        self.skill = skill
        self.cfg = config
        self.clips = clips if clips is not None else load_skill_clips(session, skill, seq, config.control_hz, humanoid, scene)
        self.render_mode = render_mode
        self._models: dict[str, tuple] = {}
        lo, hi = hinge_ranges().T
        self._mid, self._half = (lo + hi) / 2, (hi - lo) / 2
        self._max_steps = int(round(config.episode_s * config.control_hz))
        self._use(0)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (PROPRIO_SIZE + tasks.OBS_SIZE[skill],), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (69,), np.float32)
        self._ref_transitions: NDArray | None = None

    # ------------------------------------------------------------------ clips and models

    def _use(self, c: int) -> None:
        clip = self.clips[c]
        key = clip.ref.xml
        if key not in self._models:
            m = self.mj.MjModel.from_xml_string(clip.ref.xml)
            self._models[key] = (m, self.mj.MjData(m), self._foot_geoms(m))
        self.model, self.data, self._feet = self._models[key]
        self.clip = clip
        self._substeps = max(1, int(round(1.0 / (self.cfg.control_hz * self.model.opt.timestep))))
        self._start, self._step = 0, 0

    def _foot_geoms(self, m) -> list[list[int]]:
        """Box geoms of the left and right foot (ankle and toe bodies)."""
        out = []
        for side in "LR":
            bodies = {_IDX[f"{side}_Ankle"] + 1, _IDX[f"{side}_Toe"] + 1}
            out.append([g for g in range(m.ngeom) if m.geom_bodyid[g] in bodies and m.geom_type[g] == self.mj.mjtGeom.mjGEOM_BOX])
        return out

    @property
    def reference_transitions(self) -> NDArray[np.float32]:
        """(M, 332) every clip's (s_t, s_t+1) transitions: the discriminator's real data."""
        if self._ref_transitions is None:
            rows = []
            for cl in self.clips:
                r = cl.ref
                rows.append(clip_transitions(amp_frame_features(r.qpos, r.qvel, r.xpos, cl.floor_z)))
            self._ref_transitions = np.concatenate(rows) if rows else np.zeros((0, AMP_TRANSITION_SIZE), np.float32)
        return self._ref_transitions

    # ------------------------------------------------------------------ gymnasium API

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = options or {}
        c = int(options.get("clip", self.np_random.integers(len(self.clips))))
        self._use(c)
        n = len(self.clip.ref)
        start = options.get("start")
        if start is None:
            last = self.clip.contact if self.clip.contact is not None else n - 1
            start = int(self.np_random.integers(max(min(last, n - 1), 1))) if self.cfg.random_start else 0
        self._start, self._step = int(start), 0
        self.set_state(self.clip.ref.qpos[self._start], self.clip.ref.qvel[self._start])
        self._amp = self._amp_frame()
        return self._observe(), {"clip": self.clip.id, "start": self._start}

    def set_state(self, qpos: NDArray, qvel: NDArray | None = None) -> None:
        """Put the humanoid in ``qpos`` (and ``qvel``), PD targets at its pose."""
        m, d = self.model, self.data
        self.mj.mj_resetData(m, d)
        d.qpos[:] = qpos
        if qvel is not None:
            d.qvel[:] = qvel
        d.ctrl[:] = np.clip(d.qpos[7:], self._mid - self._half, self._mid + self._half)
        self.mj.mj_forward(m, d)

    def step(self, action):
        a = np.clip(np.asarray(action, dtype=np.float64).reshape(69), -1.0, 1.0)
        m, d = self.model, self.data
        d.ctrl[:] = self._mid + a * self._half
        for _ in range(self._substeps):
            self.mj.mj_step(m, d)
        self._step += 1
        diverged = not np.isfinite(d.qpos).all() or not np.isfinite(d.qvel).all()
        if diverged:  # end, with finite numbers
            self.set_state(self.clip.ref.qpos[self._start])
        prev, self._amp = self._amp, self._amp_frame()
        state, goal = self.character_state(), self.goal()
        r = float(tasks.reward(self.skill, state, goal)[0])
        fell = d.xpos[_IDX["Head"] + 1, 2] - self.clip.floor_z < self.cfg.fall_head_m
        terminated = bool(diverged or fell)
        truncated = self._step >= self._max_steps
        info = {"amp_obs": np.concatenate([prev, self._amp]), "task_reward": r, "time_s": self._time()}
        if terminated or truncated:
            info["success"] = bool(tasks.success(self.skill, state, goal)[0]) and not diverged
            info["error_m"] = float(tasks.error(self.skill, state, goal)[0])
        return self._observe(), r, terminated, truncated, info

    # ------------------------------------------------------------------ state, goal, observation

    def _time(self) -> float:
        return (self._start + self._step) / self.cfg.control_hz

    def goal(self) -> tasks.SkillGoal:
        """The current clip's goal (batch of one), with the episode's time for follow."""
        return _batch_goal(self.clip.goal, self._time())

    def _amp_frame(self) -> NDArray[np.float32]:
        d = self.data
        return amp_frame_features(d.qpos[None], d.qvel[None], d.xpos[None, 1:], self.clip.floor_z)[0]

    def _velocities(self) -> tuple[NDArray, NDArray]:
        d = self.data
        ang = d.cvel[1:, :3]
        lin = d.cvel[1:, 3:] + np.cross(ang, d.xpos[1:] - d.subtree_com[1])
        return lin, ang

    def character_state(self) -> tasks.CharacterState:
        """The humanoid now as the task functions take it (batch of one)."""
        d = self.data
        x = d.xpos[1:]
        feet = np.stack([x[_IDX["L_Ankle"]], x[_IDX["R_Ankle"]]]).copy()
        for i, geoms in enumerate(self._feet):
            lows = []
            for g in geoms:
                R = d.geom_xmat[g].reshape(3, 3)
                lows.append(d.geom_xpos[g, 2] - np.abs(R[2]) @ self.model.geom_size[g])  # lowest box corner
            if lows:
                feet[i, 2] = min(lows)
        lin, _ = self._velocities()
        return tasks.CharacterState(root_pos=x[0][None].copy(), root_rot=d.xmat[1].reshape(1, 3, 3).copy(),
                                    root_vel=lin[0][None].copy(), head_pos=x[_IDX["Head"]][None].copy(),
                                    hand_pos=np.stack([x[_IDX["L_Hand"]], x[_IDX["R_Hand"]]])[None].copy(),
                                    foot_pos=feet[None])

    def _observe(self) -> NDArray[np.float32]:
        d = self.data
        x = d.xpos[1:]
        R = d.xmat[1:].reshape(-1, 3, 3)
        H = heading_frame(R[:1])[0]
        lin, ang = self._velocities()
        proprio = [((x[1:] - x[0]) @ H).ravel(), rot6d(H.T[None] @ R).ravel(), (lin @ H).ravel(), (ang @ H).ravel(),
                   [x[0, 2] - self.clip.floor_z]]
        task = tasks.observe(self.skill, self.character_state(), self.goal())[0]
        return np.concatenate([np.asarray(p, dtype=np.float64).ravel() for p in proprio] + [task]).astype(np.float32)

    def reference_result(self, c: int, frame: int = -1) -> tuple[bool, float]:
        """The success test and contact error of clip ``c``'s own reference frame ``frame`` (default
        its end), the humanoid put in that pose; the environment is reset afterwards."""
        self._use(c)
        n = len(self.clip.ref)
        k = frame % n
        self._start, self._step = k, 0
        self.set_state(self.clip.ref.qpos[k], self.clip.ref.qvel[k])
        state, goal = self.character_state(), self.goal()
        out = bool(tasks.success(self.skill, state, goal)[0]), float(tasks.error(self.skill, state, goal)[0])
        self.reset()
        return out
