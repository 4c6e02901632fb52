"""The step declarations (``<stage>/steps.py``, :mod:`embodmocap.io.steps`): every setting of Stages
I-IV, mono, skills and robot reaches exactly one step's fingerprint (or is declared as changing no output, with
the reason), changing a setting changes its step's fingerprint, and the architecture doc's
reads/writes table is the one the declarations give.

``EMBODMOCAP_WRITE_DOCS=1 pytest tests/test_steps.py`` rewrites the table in docs/architecture.md.
"""

from __future__ import annotations

import copy
import os
import typing
from pathlib import Path

import pytest

from embodmocap.calibrate.steps import STEPS as CALIBRATE
from embodmocap.io.steps import StageSteps, Step, config_fields, setting, steps_markdown
from embodmocap.mono.steps import STEPS as MONO
from embodmocap.motion.steps import STEPS as MOTION
from embodmocap.robot.steps import STEPS as ROBOT
from embodmocap.scene.steps import STEPS as SCENE
from embodmocap.sequence.steps import STEPS as SEQUENCE
from embodmocap.skills.steps import STEPS as SKILLS

STAGES = [SCENE, SEQUENCE, CALIBRATE, MOTION, MONO, SKILLS, ROBOT]
DOC = Path(__file__).resolve().parents[1] / "docs" / "architecture.md"
BEGIN, END = "<!-- steps table: begin (generated from the <stage>/steps.py declarations, tests/test_steps.py) -->", \
    "<!-- steps table: end -->"


@pytest.mark.parametrize("stage", STAGES, ids=lambda s: s.stage)
def test_every_setting_reaches_exactly_one_step(stage):
    assert stage.coverage_problems() == []
    if stage.stage not in ("skills", "robot"):  # flat configs
        # the walk reaches nested configs (e.g. SceneConfig.sfm.refine_poses), not only the top level
        assert any("." in leaf for leaf in config_fields(stage.config))


def _other(value, hint):
    """A value of the field's type different from ``value``."""
    args = typing.get_args(hint)
    if typing.get_origin(hint) is typing.Literal:
        return next(a for a in args if a != value)
    if isinstance(value, bool):
        return not value
    if isinstance(value, int):
        return value + 1
    if isinstance(value, float):
        return value * 2 + 1
    if isinstance(value, str):
        return value + "x"
    if isinstance(value, tuple):
        return value + value[:1] if value else (1,)
    if value is None:
        return 1.0
    raise AssertionError(f"no other value for {value!r}")


def _hint(cls, dotted):
    for part in dotted.split("."):
        hint = typing.get_type_hints(cls)[part]
        cls = hint
    return hint


def _with(cfg, dotted, value):
    """``cfg`` with one (nested) field changed, validation bypassed (only the fingerprint reads it)."""
    head, _, rest = dotted.partition(".")
    new = copy.copy(cfg)
    object.__setattr__(new, head, _with(getattr(cfg, head), rest, value) if rest else value)
    return new


def _dummy_fingerprint(stage: StageSteps, name: str, cfg) -> str:
    s = stage.step(name)
    return stage.fingerprint(name, cfg, after={a: "fp" for a in s.after}, reads={r: None for r in s.reads},
                             context={c: 0 for c in s.context})


@pytest.mark.parametrize("stage", STAGES, ids=lambda s: s.stage)
def test_changing_a_setting_changes_only_its_steps_fingerprint(stage):
    cfg = stage.config()
    base = {s.name: _dummy_fingerprint(stage, s.name, cfg) for s in stage.steps}
    for leaf in config_fields(stage.config):
        hint = _hint(stage.config, leaf)
        if typing.get_origin(hint) is typing.Union:  # Optional: another value of the non-None type
            hint = next(a for a in typing.get_args(hint) if a is not type(None))
        changed = _with(cfg, leaf, _other(setting(cfg, leaf), hint))
        moved = {s.name for s in stage.steps if _dummy_fingerprint(stage, s.name, changed) != base[s.name]}
        owners = {s.name for s in stage.steps if any(leaf == k or leaf.startswith(k + ".") for k in s.settings)}
        if leaf in stage.not_fingerprinted:
            assert moved == set(), leaf
        else:
            assert moved == owners and len(owners) == 1, (leaf, moved, owners)


def test_the_fingerprint_follows_reads_after_and_context(tmp_path):
    st = StageSteps("demo", type("Cfg", (), {}), (Step("a", reads=("f",)), Step("b", after=("a",), context=("x",))))
    f = tmp_path / "f.txt"
    f.write_text("one")
    fa = st.fingerprint("a", None, reads={"f": f})
    f.write_text("two")
    assert st.fingerprint("a", None, reads={"f": f}) != fa
    assert st.fingerprint("b", None, after={"a": "1"}, context={"x": 1}) != st.fingerprint("b", None, after={"a": "2"},
                                                                                           context={"x": 1})
    assert st.fingerprint("b", None, after={"a": "1"}, context={"x": 1}) != st.fingerprint("b", None, after={"a": "1"},
                                                                                           context={"x": 2})
    with pytest.raises(ValueError, match="declared"):
        st.fingerprint("a", None, reads={"f": f, "g": f})  # a read the declaration does not name
    with pytest.raises(ValueError, match="declared"):
        st.fingerprint("b", None, context={"x": 1})  # the step it comes after left out


def test_the_coverage_check_finds_a_missing_a_doubled_and_an_unknown_setting():
    from embodmocap.mono.config import MonoConfig

    st = StageSteps("mono", MonoConfig, (Step("a", settings=("chunk", "stitch", "stitch.min_conf", "nonsense")),),
                    not_fingerprinted={"overlap": "test"})
    found = "\n".join(st.coverage_problems())
    assert "'scale.feet.max_speed' reaches no step" in found  # nested, two levels down
    assert "'stitch.min_conf' is declared 2 times" in found
    assert "'nonsense', which is not a field" in found
    assert "'overlap'" not in found and "'chunk'" not in found


def test_the_architecture_doc_holds_the_declared_table():
    text = DOC.read_text()
    table = steps_markdown(STAGES)
    assert BEGIN in text and END in text, f"{DOC} lost its steps table markers"
    head, rest = text.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    fresh = f"{head}{BEGIN}\n{table}{END}{tail}"
    if os.environ.get("EMBODMOCAP_WRITE_DOCS") == "1":
        DOC.write_text(fresh)
        text = fresh
    assert fresh == text, "docs/architecture.md's steps table is out of date: EMBODMOCAP_WRITE_DOCS=1 pytest tests/test_steps.py"
