"""What a robot is to the retargeting (:class:`RobotConfig`) and how to retarget (:class:`RetargetConfig`).

A robot is data, not code: its MJCF, its root body, which robot body follows which SMPL joint and
how strongly, its feet and hands, its height and joint-limit margins. A user adds a robot (e.g. the
paper's HighTorque Hi) with a TOML file read by :func:`load_robot_config` (strictly: an unknown key
is an error); the Unitree G1 is built in (:data:`embodmocap.robot.g1.G1`). Importing this module
needs no optional dependency.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Literal

from embodmocap.body.joints import SMPL_JOINT_NAMES
from embodmocap.errors import InputError

#: ``mjcf`` values starting with this are paths inside the installed ``mjlab`` package.
MJLAB_PREFIX = "mjlab:"
#: ``mjcf`` values starting with this are paths inside ``embodmocap/robot/assets`` (models we ship).
ASSETS_PREFIX = "embodmocap:"


@dataclass(frozen=True)
class BodyLink:
    """One robot body that follows one SMPL joint."""

    body: str
    """Robot body name in the MJCF."""
    smpl_joint: str
    """SMPL joint it follows (a name of :data:`embodmocap.body.joints.SMPL_JOINT_NAMES`)."""
    position_weight: float = 1.0
    """Cost of its position error (per metre); 0 = position not tracked."""
    orientation_weight: float = 0.0
    """Cost of its orientation error (per radian); 0 = orientation not tracked. Only meaningful
    for bodies whose rest frame matches the joint's rest frame (pelvis, torso, feet): the robot's
    zero pose has the arms down where SMPL's rest pose has them out."""


@dataclass(frozen=True)
class RobotConfig:
    """A robot for the retargeting."""

    name: str
    """Short name; outputs go to ``sequences/<seq>/robot/<name>/``."""
    mjcf: str
    """MJCF file: an absolute path, a path relative to the TOML file that names it, or
    ``embodmocap:<path inside embodmocap/robot/assets>`` for the models shipped with this package,
    or ``mjlab:<path inside the mjlab package>`` for models in an installed mjlab."""
    root_body: str
    """The floating base body (it must carry the MJCF's free joint)."""
    links: tuple[BodyLink, ...]
    """Bodies that follow SMPL joints. The bodies mapped to ``left_hip``, ``left_knee``,
    ``left_ankle`` (and the right ones) measure the leg length used for scaling."""
    feet: tuple[str, str]
    """Left and right foot bodies (pinned during foot contacts, kept above the scene)."""
    hands: tuple[str, str]
    """Left and right hand bodies (kept above the scene, reported)."""
    height_m: float
    """Standing height of the robot, metres (the report; the scale when ``scale_from = "height"``)."""
    joint_limit_margin_rad: float = 0.02
    """The IK keeps every hinge joint this far inside its MJCF range, radians."""
    velocity_limits: tuple[tuple[str, float], ...] = ()
    """Joint speed limits, ``(regex on the joint name, rad/s)``; the first matching pattern wins;
    joints matching none are not speed limited (and not reported against a limit)."""
    avoid_collisions: tuple[tuple[str, str], ...] = ()
    """Pairs of bodies whose collision geoms the IK keeps apart (mink's collision avoidance),
    e.g. a hand and the hip it would pass through where the robot's hips are wider than the
    scaled human's."""
    csv_joint_order: tuple[str, ...] = ()
    """Joint order of the BeyondMimic/mjlab motion CSV; empty = every hinge joint in MJCF order
    (the actuated-joint order of models without an actuator list, e.g. mjlab's G1)."""

    def joint_velocity_limit(self, joint: str) -> float | None:
        """The speed limit of ``joint`` (rad/s), or None when no pattern matches."""
        for pattern, limit in self.velocity_limits:
            if re.fullmatch(pattern, joint):
                return float(limit)
        return None

    def link(self, smpl_joint: str) -> BodyLink | None:
        """The link that follows ``smpl_joint``, if any."""
        return next((lk for lk in self.links if lk.smpl_joint == smpl_joint), None)


@dataclass(frozen=True)
class RetargetConfig:
    """How human motion becomes robot motion (defaults suit the G1 and most humanoids)."""

    scale_from: Literal["leg", "height"] = "leg"
    """``leg``: scale = robot leg length / human leg length (hip to knee to ankle, both in their
    rest poses); ``height``: robot ``height_m`` / the human's rest height."""
    scale: float | None = None
    """Fixed scale instead of the measured one (None = measure)."""
    keep_path: bool = False
    """False: the whole motion is scaled about its mean pelvis position on the floor (a geometric
    similarity: a still human foot stays still, no skating is added, but the robot's path is the
    human's path shrunk); True: the pelvis follows the human's path at full size and only the
    body is scaled (the feet then lag, and pinning them costs residual)."""
    iterations: int = 12
    """Most IK iterations per frame (stops earlier when converged)."""
    first_frame_iterations: int = 300
    """Most IK iterations for the first frame (from the robot's zero pose, no speed limits)."""
    tolerance_m: float = 1e-4
    """A frame has converged when no tracked body moves more than this in one iteration, metres."""
    posture_weight: float = 2e-2
    """Cost pulling every joint towards the MJCF's zero pose (keeps joints the targets leave free,
    such as an upper arm's twist, near neutral)."""
    foot_pin_weight: float = 10.0
    """Position and orientation cost of a pinned foot (multiplies its link weights)."""
    lm_damping: float = 1e-3
    """Levenberg-Marquardt damping of every frame task (keeps steps finite near singularities)."""
    contact_height_m: float = 0.03
    """A human foot whose ankle is at most this far above its rest height over the scene ..."""
    contact_speed_mps: float = 0.25
    """... and whose ankle moves slower than this (horizontally) is in contact (pinned)."""
    contact_min_frames: int = 3
    """Shorter contact runs are ignored (not pinned)."""
    heightmap_cell_m: float = 0.05
    """Cell size of the scene height map used to keep the robot above the scene, metres."""
    tracking_fps: float = 50.0
    """Frame rate of the tracking npz (mjlab's ``csv_to_npz`` resamples to 50 fps by default)."""
    checkpoint_frames: int = 300
    """An interrupted retargeting resumes from the last multiple of this many frames."""
    self_collision_depth_m: float = 0.005
    """A frame counts as self-colliding when two robot collision geoms overlap by more than this."""


# ------------------------------------------------------------------------------------ TOML


_LINK_KEYS = {f.name for f in fields(BodyLink)}
_ROBOT_KEYS = {f.name for f in fields(RobotConfig)}


def robot_config_from_dict(doc: dict[str, Any], source: Path | None = None) -> RobotConfig:
    """Build a :class:`RobotConfig` from a parsed TOML document, strictly.

    ``velocity_limits`` is a table ``{pattern = rad/s}`` (its order is kept); ``links`` an array of
    tables with :class:`BodyLink`'s keys. A relative ``mjcf`` is resolved against ``source``'s
    folder. Raises :class:`InputError` naming the file and the bad key.
    """
    fix = "see docs/robot.md for the keys of a robot config"
    unknown = sorted(set(doc) - _ROBOT_KEYS)
    if unknown:
        raise InputError(source, f"unknown key(s) {', '.join(unknown)} in the robot config", fix)
    missing = sorted(k for k in ("name", "mjcf", "root_body", "links", "feet", "hands", "height_m") if k not in doc)
    if missing:
        raise InputError(source, f"missing key(s) {', '.join(missing)} in the robot config", fix)
    links = []
    for i, lk in enumerate(doc["links"]):
        if not isinstance(lk, dict) or set(lk) - _LINK_KEYS or not {"body", "smpl_joint"} <= set(lk):
            raise InputError(source, f"links[{i}] must be a table with body, smpl_joint and optionally "
                                     "position_weight, orientation_weight", fix)
        if lk["smpl_joint"] not in SMPL_JOINT_NAMES:
            raise InputError(source, f"links[{i}]: unknown SMPL joint {lk['smpl_joint']!r}",
                             f"use one of {', '.join(SMPL_JOINT_NAMES)}")
        links.append(BodyLink(str(lk["body"]), str(lk["smpl_joint"]), float(lk.get("position_weight", 1.0)),
                              float(lk.get("orientation_weight", 0.0))))
    mjcf = str(doc["mjcf"])
    if not mjcf.startswith((MJLAB_PREFIX, ASSETS_PREFIX)) and source is not None and not Path(mjcf).is_absolute():
        mjcf = str((Path(source).parent / mjcf).resolve())
    vel = doc.get("velocity_limits", {})
    if not isinstance(vel, dict):
        raise InputError(source, "velocity_limits must be a table {joint regex = rad/s}", fix)
    pairs = (("feet", doc["feet"]), ("hands", doc["hands"]))
    for key, val in pairs:
        if not (isinstance(val, list) and len(val) == 2):
            raise InputError(source, f"{key} must be [left body, right body]", fix)
    try:
        cfg = RobotConfig(
            name=str(doc["name"]), mjcf=mjcf, root_body=str(doc["root_body"]), links=tuple(links),
            feet=(str(doc["feet"][0]), str(doc["feet"][1])), hands=(str(doc["hands"][0]), str(doc["hands"][1])),
            height_m=float(doc["height_m"]), joint_limit_margin_rad=float(doc.get("joint_limit_margin_rad", 0.02)),
            velocity_limits=tuple((str(k), float(v)) for k, v in vel.items()),
            csv_joint_order=tuple(str(j) for j in doc.get("csv_joint_order", ())),
            avoid_collisions=tuple((str(a), str(b)) for a, b in doc.get("avoid_collisions", ())),
        )
    except (TypeError, ValueError) as err:
        raise InputError(source, f"bad value in the robot config ({err})", fix) from err
    if not re.fullmatch(r"[A-Za-z0-9_.-]+", cfg.name):
        raise InputError(source, f"robot name {cfg.name!r} must be letters, digits, '_', '.', '-'", fix)
    return cfg


def robot_config_from_record(rec: dict[str, Any]) -> RobotConfig:
    """The :class:`RobotConfig` recorded (``dataclasses.asdict`` through JSON) in a robot folder's
    stage manifest (``config.robot``)."""
    doc = dict(rec)
    doc["velocity_limits"] = {str(k): float(v) for k, v in doc.get("velocity_limits", [])}
    return robot_config_from_dict(doc)


def load_robot_config(path: str | Path) -> RobotConfig:
    """Read a robot config TOML file (see docs/robot.md); one clear error for a bad file."""
    try:
        import tomllib
    except ModuleNotFoundError:  # pragma: no cover - Python < 3.11
        import tomli as tomllib  # type: ignore[no-redef]

    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text())
    except FileNotFoundError as err:
        raise InputError(path, "robot config file not found", "check the --robot-config path") from err
    except tomllib.TOMLDecodeError as err:
        raise InputError(path, f"not valid TOML ({err})", "fix the file") from err
    return robot_config_from_dict(doc, path)


def robot_config_to_toml(cfg: RobotConfig) -> str:
    """The TOML text that :func:`load_robot_config` reads back as ``cfg`` (a template for users)."""
    q = lambda s: '"' + str(s).replace("\\", "\\\\").replace('"', '\\"') + '"'  # noqa: E731
    lines = [f"name = {q(cfg.name)}", f"mjcf = {q(cfg.mjcf)}", f"root_body = {q(cfg.root_body)}",
             f"feet = [{q(cfg.feet[0])}, {q(cfg.feet[1])}]", f"hands = [{q(cfg.hands[0])}, {q(cfg.hands[1])}]",
             f"height_m = {cfg.height_m!r}", f"joint_limit_margin_rad = {cfg.joint_limit_margin_rad!r}"]
    if cfg.csv_joint_order:
        lines.append("csv_joint_order = [" + ", ".join(q(j) for j in cfg.csv_joint_order) + "]")
    if cfg.avoid_collisions:
        lines.append("avoid_collisions = [" + ", ".join(f"[{q(a)}, {q(b)}]" for a, b in cfg.avoid_collisions) + "]")
    lines.append("")
    lines.append("[velocity_limits]")
    lines += [f"{q(p)} = {v!r}" for p, v in cfg.velocity_limits]
    for lk in cfg.links:
        lines += ["", "[[links]]", f"body = {q(lk.body)}", f"smpl_joint = {q(lk.smpl_joint)}",
                  f"position_weight = {lk.position_weight!r}", f"orientation_weight = {lk.orientation_weight!r}"]
    return "\n".join(lines) + "\n"

