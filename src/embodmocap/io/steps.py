"""Steps declared once: what each step of a stage reads, which settings it depends on, what it writes.

A stage's steps are a :class:`StageSteps` (in the stage package's ``steps.py``): one :class:`Step`
per step, with the files it reads, the config fields it depends on (dotted paths into the stage's
config dataclass; a nested config named whole covers every field below it), the run-time facts
that are neither (``context``: e.g. whether the scene is indoor), the steps of the same stage whose
outputs it reads (``after``) and the files it writes. Settings that do not change any output (a
device switch, a warning threshold) are listed in ``not_fingerprinted`` with the reason.

Everything else derives from the declaration:

- a step's fingerprint (:meth:`StageSteps.fingerprint`): the stage and step names, the step's
  version, the values of its declared settings, the fingerprints of the steps it comes after and
  the content of the files it reads, and its context. The run passes the files and facts by the
  declared names; a name missing or extra is a programming error (raised), so the declaration and
  the fingerprint cannot drift apart;
- the check that every setting of a stage's config reaches exactly one step's fingerprint or is
  declared as not fingerprinted (:meth:`StageSteps.coverage_problems`, run by ``tests/test_steps.py``):
  a setting that reaches none would let a rerun silently reuse outputs made with another value;
- the reads/writes table of ``docs/architecture.md`` (:func:`steps_markdown`, kept in step by the
  same test).
"""

from __future__ import annotations

import typing
from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any, Mapping

from embodmocap.io.stage_manifest import fingerprint, path_fingerprint


@dataclass(frozen=True)
class Step:
    """One step of a stage, as declared.

    Attributes:
        name: the step's name (the manifest's record is ``name``, or ``name_<view>`` for a step
            done per view).
        reads: the files the step reads whose content enters its fingerprint (names as the run
            passes them: ``"keypoints2d.npz"``, ``"scene capture"``...).
        settings: config fields (dotted paths, e.g. ``"smplify"`` or ``"scale.height_m"``) whose
            values enter the fingerprint.
        writes: the files it writes (paths under the session, for the documentation).
        after: steps of the same stage whose outputs it uses; their fingerprints enter its own.
        context: run-time facts, neither files nor settings, that change its outputs (e.g.
            ``"indoor"`` from session.toml).
        version: the recipe's version: raising it redoes the step on sessions made before.
        doc: one line for the documentation.
    """

    name: str
    reads: tuple[str, ...] = ()
    settings: tuple[str, ...] = ()
    writes: tuple[str, ...] = ()
    after: tuple[str, ...] = ()
    context: tuple[str, ...] = ()
    version: int = 1
    doc: str = ""


@dataclass(frozen=True)
class StageSteps:
    """The declared steps of one stage and its config class.

    Attributes:
        stage: the stage's name (as in its manifest).
        config: the stage's config dataclass.
        steps: its steps, in the order they run.
        not_fingerprinted: config fields (dotted) that change no output, each with the reason.
    """

    stage: str
    config: type
    steps: tuple[Step, ...]
    not_fingerprinted: Mapping[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        names = [s.name for s in self.steps]
        if len(set(names)) != len(names):
            raise ValueError(f"{self.stage}: a step is declared twice: {names}")
        for s in self.steps:
            unknown = [a for a in s.after if a not in names[:names.index(s.name)]]
            if unknown:
                raise ValueError(f"{self.stage}.{s.name}: comes after {unknown}, not declared before it")

    def step(self, name: str) -> Step:
        """The declaration of step ``name``."""
        for s in self.steps:
            if s.name == name:
                return s
        raise KeyError(f"{self.stage} has no step {name!r}")

    def fingerprint(self, name: str, cfg: Any, *, after: Mapping[str, str | None] | None = None,
                    reads: Mapping[str, Any] | None = None, context: Mapping[str, Any] | None = None) -> str:
        """The fingerprint of step ``name`` run with ``cfg``.

        Args:
            name: a declared step.
            cfg: the stage's config (an instance of :attr:`config`).
            after: the fingerprint of each step in the declaration's ``after`` (None for one that
                does not apply to this run, e.g. a switched-off step).
            reads: per declared read, what it is: a :class:`~pathlib.Path` (its content is
                fingerprinted, see :func:`~embodmocap.io.stage_manifest.path_fingerprint`), None
                (absent), a dict or list of those (e.g. one path per view), or a JSON value that
                stands for the content (e.g. the refined offsets read from a report).
            context: per declared context fact, its value (JSON-able).

        Raises:
            ValueError: the names given differ from the declared ones (a programming error).
        """
        s = self.step(name)
        after, reads, context = dict(after or {}), dict(reads or {}), dict(context or {})
        for what, given, declared in (("after", after, s.after), ("reads", reads, s.reads),
                                      ("context", context, s.context)):
            if set(given) != set(declared):
                raise ValueError(f"{self.stage}.{name}: {what} given {sorted(given)}, declared {sorted(declared)}")
        return fingerprint(self.stage, s.name, s.version, {k: setting(cfg, k) for k in s.settings},
                           {k: after[k] for k in s.after}, {k: _material(reads[k]) for k in s.reads},
                           {k: context[k] for k in s.context})

    def coverage_problems(self) -> list[str]:
        """Every config field that reaches no step's fingerprint and is not declared as not
        fingerprinted, or is declared more than once, and every declared name that is no field."""
        leaves = config_fields(self.config)
        nodes = set(leaves) | {p for leaf in leaves for p in _prefixes(leaf)}
        declared = [(k, s.name) for s in self.steps for k in s.settings] + \
                   [(k, "not_fingerprinted") for k in self.not_fingerprinted]
        problems = [f"{self.stage}: {where} names {k!r}, which is not a field of {self.config.__name__}"
                    for k, where in declared if k not in nodes]
        for leaf in leaves:
            owners = [where for k, where in declared if leaf == k or leaf.startswith(k + ".")]
            if not owners:
                problems.append(f"{self.stage}: setting {leaf!r} reaches no step's fingerprint (declare it in the "
                                "step whose output it changes, or in not_fingerprinted with the reason)")
            elif len(owners) > 1:
                problems.append(f"{self.stage}: setting {leaf!r} is declared {len(owners)} times ({', '.join(owners)})")
        return problems


def setting(cfg: Any, dotted: str) -> Any:
    """The value of config field ``dotted`` (``"scale.height_m"``) of ``cfg``."""
    value = cfg
    for part in dotted.split("."):
        value = getattr(value, part)
    return value


def config_fields(cls: type, prefix: str = "") -> list[str]:
    """Every leaf field of config dataclass ``cls`` as a dotted path, nested config dataclasses walked."""
    hints = typing.get_type_hints(cls)
    out: list[str] = []
    for f in fields(cls):
        t = hints.get(f.name)
        if isinstance(t, type) and is_dataclass(t):
            out += config_fields(t, f"{prefix}{f.name}.")
        else:
            out.append(prefix + f.name)
    return out


def _prefixes(dotted: str) -> list[str]:
    parts = dotted.split(".")
    return [".".join(parts[:i]) for i in range(1, len(parts))]


def _material(x: Any) -> Any:
    """What of a read enters a fingerprint: a path's content fingerprint, recursively in dicts and lists."""
    if isinstance(x, Path):
        return path_fingerprint(x)
    if isinstance(x, Mapping):
        return {k: _material(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_material(v) for v in x]
    return x


def steps_markdown(stages: list[StageSteps]) -> str:
    """The reads/writes table of ``docs/architecture.md``: one row per step of each stage."""
    rows = ["| stage | step | reads | after | settings | writes |", "|---|---|---|---|---|---|"]

    def cell(items) -> str:
        return ", ".join(f"`{x}`" for x in items) or "-"

    for st in stages:
        for s in st.steps:
            reads = list(s.reads) + [f"({c})" for c in s.context]
            rows.append(f"| {st.stage} | `{s.name}` | {cell(reads)} | {cell(s.after)} | {cell(s.settings)} | "
                        f"{cell(s.writes)} |")
        if st.not_fingerprinted:
            rows.append(f"| {st.stage} | (no step) | - | - | {cell(st.not_fingerprinted)} | - |")
    return "\n".join(rows) + "\n"
