"""Simulation-ready output and scene-aware motion tracking in MuJoCo (extra ``sim``).

- :func:`export_mjcf` (``embodmocap export SESSION --to mjcf``): the performer's MuJoCo model from
  the fitted shape, the scene as a heightfield, the motion as keyframes (:mod:`.model`, :mod:`.scene`).
- :func:`sim_check` (``embodmocap sim check``): penetration, floating, foot skating, contacts and
  the residual root force of the fitted motion (:mod:`.check`).
- :class:`TrackingEnv` (Gymnasium id ``EmbodMocap/SceneTracking-v0``, registered on import):
  the paper's scene-aware tracking task (:mod:`.env`); PPO training and evaluation in :mod:`.train`.
- :class:`SkillEnv` (Gymnasium ids ``EmbodMocap/Skill-<name>-v0``, :data:`SKILL_ENV_IDS`, registered
  on import): the six interaction skills (:mod:`.skill_env`, AMP input :mod:`.amp`); PPO + AMP
  training and evaluation in :mod:`.skill_train` (``sim train --skill NAME``).

Importing this package needs only numpy; MuJoCo, Gymnasium and stable-baselines3 are imported when
used, with one clear error naming the extra when missing.
"""

from __future__ import annotations

import os

# MuJoCo picks its OpenGL backend when first imported; offscreen rendering (``sim eval``'s MP4)
# needs EGL on a headless machine. A user's own MUJOCO_GL wins.
os.environ.setdefault("MUJOCO_GL", "egl")

ENV_ID = "EmbodMocap/SceneTracking-v0"

__all__ = ["ENV_ID", "TrackingEnv", "export_mjcf", "sim_check", "tracking_success"]


def _register() -> None:
    try:
        import gymnasium
    except ImportError:  # the env itself raises the one-line error when used
        return
    if ENV_ID not in gymnasium.registry:
        gymnasium.register(ENV_ID, entry_point="embodmocap.sim.env:TrackingEnv")


_register()

#: The interaction skills' environments, ``EmbodMocap/Skill-<name>-v0`` (:mod:`.skill_env`).
SKILL_ENV_IDS = {name: f"EmbodMocap/Skill-{name}-v0" for name in ("follow", "sit", "climb", "lie", "prone", "support")}


def _register_skills() -> None:
    try:
        import gymnasium
    except ImportError:
        return
    for name, env_id in SKILL_ENV_IDS.items():
        if env_id not in gymnasium.registry:
            gymnasium.register(env_id, entry_point="embodmocap.sim.skill_env:SkillEnv", kwargs={"skill": name})


_register_skills()


def __getattr__(name: str):
    if name == "TrackingEnv":
        from embodmocap.sim.env import TrackingEnv

        return TrackingEnv
    if name == "tracking_success":
        from embodmocap.sim.env import tracking_success

        return tracking_success
    if name == "SkillEnv":
        from embodmocap.sim.skill_env import SkillEnv

        return SkillEnv
    if name == "export_mjcf":
        from embodmocap.sim.session import export_mjcf

        return export_mjcf
    if name == "sim_check":
        from embodmocap.sim.check import sim_check

        return sim_check
    raise AttributeError(name)
