"""``--config FILE.toml``: a command's settings kept in a file, the command line winning.

The file mirrors the command's options: a top-level key is an option without its dashes
(``--voxel-m 0.02`` of ``embodmocap scene`` is ``voxel_m = 0.02``) and a table is a dotted option
group (``--scene.voxel-m 0.02`` of ``embodmocap run`` is ``[scene]`` then ``voxel_m = 0.02``).
Dashes and underscores in keys are interchangeable. A file written for ``run`` also serves the stage
commands: ``embodmocap motion --config f.toml`` reads its ``[motion]`` table and ignores the
other stages' tables. docs/config.example.toml is an example.

The values become the defaults of the command's dataclass (``tyro.cli(..., default=...)``), so an
option given on the command line replaces the file's value, and every value is checked against the
field's type here, before any work starts: an unknown key or a wrong type is one
:class:`~embodmocap.errors.InputError` naming the file and the key (with the nearest valid key).
"""

from __future__ import annotations

import dataclasses
import difflib
import enum
import types
import typing
from pathlib import Path
from typing import Any, Literal, Union

import tyro

from embodmocap.errors import InputError

#: Stage commands that also read their table of a file written for ``run``.
PIPELINE_STAGES = ("scene", "sequence", "calibrate", "motion")


def read_settings(path: Path) -> dict[str, Any]:
    """The file's tables, read with :mod:`tomllib`; a missing or malformed file is an InputError."""
    import tomllib

    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise InputError(path, "settings file not found", "check the --config path") from None
    except tomllib.TOMLDecodeError as err:
        raise InputError(path, f"not valid TOML: {err}", "see docs/config.example.toml") from None


def subcommands(commands: Any) -> dict[str, type]:
    """Subcommand name -> command dataclass of the CLI's ``Union[Annotated[cls, subcommand(name)], ...]``."""
    out = {}
    for annotated in typing.get_args(commands):
        name = next(m.name for m in annotated.__metadata__ if getattr(m, "name", None))
        out[name] = typing.get_args(annotated)[0]
    return out


def command_default(cls: type, name: str, data: dict[str, Any], path: Path) -> Any:
    """An instance of the command dataclass ``cls`` (subcommand ``name``) holding the file's values;
    fields the file does not set keep their defaults, required ones stay ``tyro.MISSING``."""
    from embodmocap.pipeline import PipelineConfig

    run_keys = {_key(f.name) for f in dataclasses.fields(PipelineConfig)}
    if name in PIPELINE_STAGES and data and {_key(k) for k in data} <= run_keys:
        table = {_key(k): v for k, v in data.items()}.get(name, {})
        data, where = (table if isinstance(table, dict) else {name: table}), name + "."
    else:
        where = ""
    return _fill(cls, None, data, path, where)


def _key(k: str) -> str:
    return k.replace("-", "_")


def _flattened(f: dataclasses.Field, hints: dict[str, Any]) -> bool:
    """Is ``f`` a group shown without a prefix (``tyro.conf.arg(name="")``, each command's config)?"""
    for meta in getattr(hints[f.name], "__metadata__", ()):
        if getattr(meta, "name", None) == "":
            return True
    return False


def _options(cls: type, hints: dict[str, Any]) -> dict[str, tuple[dataclasses.Field, tuple[str, ...]]]:
    """Every key the file may set at this level: field name -> (field, path of flattened groups)."""
    out: dict[str, tuple[dataclasses.Field, tuple[str, ...]]] = {}
    for f in dataclasses.fields(cls):
        if _flattened(f, hints):
            sub_hints = typing.get_type_hints(_strip(hints[f.name]), include_extras=True)
            for k, (g, p) in _options(_strip(hints[f.name]), sub_hints).items():
                out.setdefault(k, (g, (f.name, *p)))
        else:
            out.setdefault(f.name, (f, ()))
    return out


def _fill(cls: type, base: Any, data: dict[str, Any], path: Path, where: str) -> Any:
    """``base`` (or a fresh default of ``cls``) with the table ``data`` applied, checked key by key."""
    hints = typing.get_type_hints(cls, include_extras=True)
    options = _options(cls, hints)
    # Values per nested group: () is this dataclass, ("config",) its flattened config, ...
    per_group: dict[tuple[str, ...], dict[str, Any]] = {}
    for raw, value in data.items():
        k = _key(raw)
        if k not in options:
            raise InputError(path, *_unknown(where + raw, where, list(options)))
        f, group = options[k]
        owner = _group_type(cls, hints, group)
        hint = typing.get_type_hints(owner, include_extras=True)[f.name]
        per_group.setdefault(group, {})[f.name] = _coerce(value, hint, path, where + raw, owner, f)
    return _apply(cls, base, hints, (), per_group)


def _group_type(cls: type, hints: dict[str, Any], group: tuple[str, ...]) -> type:
    for name in group:
        cls = _strip(hints[name])
        hints = typing.get_type_hints(cls, include_extras=True)
    return cls


def _apply(cls: type, base: Any, hints: dict[str, Any], group: tuple[str, ...],
           per_group: dict[tuple[str, ...], dict[str, Any]]) -> Any:
    changes = dict(per_group.get(group, {}))
    for f in dataclasses.fields(cls):
        sub = (*group, f.name)
        if _flattened(f, hints) and any(g[: len(sub)] == sub for g in per_group):
            current = _current(base, f)
            sub_cls = _strip(hints[f.name])
            sub_hints = typing.get_type_hints(sub_cls, include_extras=True)
            changes[f.name] = _apply(sub_cls, current, sub_hints, sub, per_group)
    if base is None:
        missing = {f.name: tyro.MISSING for f in dataclasses.fields(cls)
                   if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING}
        return cls(**{**missing, **changes})
    return dataclasses.replace(base, **changes)


def _current(base: Any, f: dataclasses.Field) -> Any:
    if base is not None:
        return getattr(base, f.name)
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None


def _strip(hint: Any) -> Any:
    """``Annotated[T, ...]`` -> ``T``."""
    while typing.get_origin(hint) is typing.Annotated:
        hint = typing.get_args(hint)[0]
    return hint


def _coerce(value: Any, hint: Any, path: Path, key: str, owner: type, f: dataclasses.Field) -> Any:
    """``value`` as read from TOML, converted to the field's type or refused with one clear line."""
    hint = _strip(hint)
    origin, args = typing.get_origin(hint), typing.get_args(hint)

    def bad(expected: str) -> InputError:
        return InputError(path, f"key {key!r} = {value!r}: expected {expected}",
                          f"as the option --{key.rsplit('.', 1)[-1].replace('_', '-')} takes it; see its --help")

    if dataclasses.is_dataclass(hint):
        if not isinstance(value, dict):
            raise bad(f"a table [{key}]")
        return _fill(hint, _current(None, f), value, path, key + ".")
    if origin in (Union, types.UnionType):
        if isinstance(value, str) and value == "None" and type(None) in args:
            return None
        for arg in (a for a in args if a is not type(None)):
            try:
                return _coerce(value, arg, path, key, owner, f)
            except InputError:
                continue
        raise bad(" or ".join(_name(a) for a in args))
    if origin is Literal:
        if value in args:
            return value
        raise bad("one of " + ", ".join(repr(a) for a in args))
    if origin in (tuple, list) or hint in (tuple, list):
        if not isinstance(value, list):
            raise bad("a list")
        if origin is tuple and args and args[-1] is not Ellipsis and len(args) != len(value):
            raise bad(f"a list of {len(args)} values")
        item_hints = (args[:1] * len(value) if (origin is list or (args and args[-1] is Ellipsis)) else args) \
            if args else (Any,) * len(value)
        items = [_coerce(v, h, path, f"{key}[{i}]", owner, f) for i, (v, h) in enumerate(zip(value, item_hints))]
        return tuple(items) if (origin is tuple or hint is tuple) else items
    if hint is Any:
        return value
    if hint is bool:
        if isinstance(value, bool):
            return value
        raise bad("true or false")
    if hint is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise bad("an integer")
    if hint is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        raise bad("a number")
    if hint is str:
        if isinstance(value, str):
            return value
        raise bad("a string")
    if isinstance(hint, type) and issubclass(hint, Path):
        if isinstance(value, str):
            return Path(value)
        raise bad("a path (a string)")
    if isinstance(hint, type) and issubclass(hint, enum.Enum):
        for member in hint:
            if value in (member.name, member.value):
                return member
        raise bad("one of " + ", ".join(m.name for m in hint))
    if isinstance(hint, type) and isinstance(value, hint):
        return value
    raise bad(_name(hint))


def _name(hint: Any) -> str:
    return getattr(hint, "__name__", None) or str(hint)


def _unknown(key: str, where: str, valid: list[str]) -> tuple[str, str]:
    """The unknown-key problem and fix: the key, the nearest valid key when one is close."""
    leaf = _key(key.rsplit(".", 1)[-1])
    near = difflib.get_close_matches(leaf, valid, n=1, cutoff=0.6)
    hint = f"; did you mean {where + near[0]!r}?" if near else f"; valid keys here: {', '.join(sorted(valid))}"
    return f"unknown key {key!r}{hint}", "keys are the command's options; see docs/config.example.toml"
