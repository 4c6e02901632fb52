"""The plan of a batch: which stage of which scene or sequence runs, after what.

A dataset is a folder of session folders (each holding ``session.toml``), a single session folder,
or a text file listing session folders (one a line, ``#`` comments, relative to the file). Every
scene's Stage I is one task; every sequence's Stages II, III and IV are three tasks, each depending
on the one before and the first on its scene's Stage I. Sequences of a scene depend only on the
scene, so they run in parallel once it is done.

:func:`make_plan` is pure apart from reading the manifests: no stage is imported and nothing is
written, so the order can be tested and printed (``embodmocap batch --dry-run``) at no cost.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Literal

from embodmocap.errors import InputError
from embodmocap.io.dataset import session_folders
from embodmocap.io.layout import SessionLayout
from embodmocap.io.manifest import SessionManifest, load_manifest

StageName = Literal["scene", "sequence", "calibrate", "motion", "evaluate"]
#: The stages in the order a sequence goes through them (``scene`` runs per scene).
STAGES: tuple[StageName, ...] = ("scene", "sequence", "calibrate", "motion")
#: Name of the file a dataset folder may hold instead of session folders (one session a line).
LIST_SUFFIXES = (".txt", ".list")


@dataclass(frozen=True)
class Task:
    """One stage of one scene or sequence of one session.

    ``key`` is unique in a plan: ``<session name>/<stage>/<target>``; ``deps`` are the keys of the
    tasks that must have succeeded first.
    """

    session: Path
    stage: StageName
    target: str
    """The scene name (Stage I) or the sequence name (Stages II-IV)."""
    scene: str
    """The scene the target belongs to."""
    deps: tuple[str, ...] = ()

    @property
    def session_name(self) -> str:
        return self.session.name

    @property
    def key(self) -> str:
        return f"{self.session.name}/{self.stage}/{self.target}"

    @property
    def kind(self) -> str:
        """``scene``, ``sequence`` or ``session`` (``evaluate``): what ``target`` names."""
        return {"scene": "scene", "evaluate": "session"}.get(self.stage, "sequence")


@dataclass(frozen=True)
class Plan:
    """Tasks in an order that respects their dependencies (every dep comes earlier)."""

    tasks: tuple[Task, ...]
    skipped: tuple[tuple[Path, str, str], ...] = ()
    """(session, sequence, why) of sequences left out (marked ``failed`` in their manifest)."""

    def __len__(self) -> int:
        return len(self.tasks)

    def by_key(self) -> dict[str, Task]:
        return {t.key: t for t in self.tasks}

    def dependents(self) -> dict[str, list[str]]:
        """key -> keys of the tasks that depend on it directly."""
        out: dict[str, list[str]] = {t.key: [] for t in self.tasks}
        for t in self.tasks:
            for d in t.deps:
                out[d].append(t.key)
        return out

    def ready(self, done: Iterable[str], started: Iterable[str]) -> list[Task]:
        """Tasks not started yet whose dependencies are all done, in plan order."""
        done_set, started_set = set(done), set(started)
        return [t for t in self.tasks if t.key not in started_set and all(d in done_set for d in t.deps)]


def session_plan(manifest: SessionManifest, only: Iterable[StageName] = STAGES,
                 include_failed: bool = False, evaluate: bool = False) -> tuple[list[Task], list[tuple[Path, str, str]]]:
    """The tasks of one session (see the module docstring) and the sequences left out.

    With ``only`` a subset of :data:`STAGES`, tasks of other stages are left out and so are the
    dependencies on them: those stages are expected to be done already (each stage checks its
    upstream stages itself and fails with the command to run when they are not). With
    ``evaluate``, a last task (stage ``evaluate``, target the session's name) evaluates the session
    once every sequence's Stage IV task is done.
    """
    keep = set(only)
    root = manifest.root
    tasks: list[Task] = []
    skipped: list[tuple[Path, str, str]] = []
    for name in manifest.scenes:
        if "scene" in keep:
            tasks.append(Task(root, "scene", name, name))
    for name, seq in manifest.sequences.items():
        if seq.failed and not include_failed:
            skipped.append((root, name, "marked failed in session.toml"))
            continue
        prev = Task(root, "scene", seq.scene, seq.scene).key if "scene" in keep else None
        for stage in STAGES[1:]:
            if stage not in keep:
                continue
            t = Task(root, stage, name, seq.scene, (prev,) if prev else ())
            tasks.append(t)
            prev = t.key
    if evaluate:
        motion = tuple(t.key for t in tasks if t.stage == "motion")
        tasks.append(Task(root, "evaluate", root.name, "", motion))
    return tasks, skipped


def make_plan(dataset: str | Path, only: Iterable[StageName] = STAGES, include_failed: bool = False,
              evaluate: bool = False) -> Plan:
    """The plan of a whole dataset: every session's tasks, scenes first so they start early.

    Raises:
        InputError: a bad dataset path (:func:`session_folders`) or a bad ``session.toml``.
    """
    per: list[list[Task]] = []
    skipped: list[tuple[Path, str, str]] = []
    for folder in session_folders(dataset):
        tasks, sk = session_plan(load_manifest(SessionLayout(folder).manifest), only, include_failed, evaluate)
        per.append(tasks)
        skipped += sk
    # Stage I of every session first (they unlock the most work), then the sequences' stages in
    # session order; dependencies always come earlier, so any prefix order is valid.
    ordered = [t for ts in per for t in ts if t.stage == "scene"] + [t for ts in per for t in ts if t.stage != "scene"]
    return Plan(tuple(ordered), tuple(skipped))
