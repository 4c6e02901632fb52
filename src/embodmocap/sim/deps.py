"""Lazy imports of the ``sim`` extra: one clear line naming the extra when a module is missing."""

from __future__ import annotations

from embodmocap.errors import require


def mujoco():
    """The ``mujoco`` module (extra ``sim``)."""
    return require("mujoco", "sim")


def gymnasium():
    """The ``gymnasium`` module (extra ``sim``)."""
    return require("gymnasium", "sim")
