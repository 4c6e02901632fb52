"""``skills.json``'s reader and writer, now in :mod:`embodmocap.io.stage_files` (with every other
hand-over file); this module keeps the old import path working."""

from embodmocap.io.stage_files import (SKILLS, SkillClip, SkillObject, SkillsFile, SkillTarget,  # noqa: F401
                                       read_skills, write_skills)
from embodmocap.io.stage_files import SKILLS_FORMAT as FORMAT  # noqa: F401
from embodmocap.io.stage_files import skills_to_json as to_json  # noqa: F401
