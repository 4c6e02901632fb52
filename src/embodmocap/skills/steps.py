"""The skill clip finder's one step, declared (:mod:`embodmocap.io.steps`): its fingerprint, the
coverage test of :class:`~embodmocap.skills.config.SkillsConfig` and the architecture doc's table
come from here."""

from __future__ import annotations

from dataclasses import fields

from embodmocap.io.steps import StageSteps, Step
from embodmocap.skills.config import SkillsConfig

STEPS = StageSteps("skills", SkillsConfig, (
    # one step: every setting is its own
    Step("clips", reads=("sequences/<seq>/smpl_world.npz", "scene mesh", "body model"),
         settings=tuple(f.name for f in fields(SkillsConfig)),
         writes=("sequences/<seq>/skills/skills.json",), doc="contacts with the scene's surfaces -> skill clips"),
))
