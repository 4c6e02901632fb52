"""Skill clips: where a fitted sequence sits, lies, climbs, leans on or walks (``embodmocap skills``).

:mod:`embodmocap.skills.contact` finds the scene's horizontal surfaces and which body parts touch
them frame by frame, :mod:`embodmocap.skills.clips` turns the contacts into labelled clips,
:mod:`embodmocap.skills.boxes` gives each surface's oriented bounding box and
:mod:`embodmocap.io.stage_files` reads and writes ``skills.json`` (docs/skills.md, docs/formats.md).
"""
