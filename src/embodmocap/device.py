"""Where torch work runs: the ``--device`` option (``auto``, ``cpu`` or ``cuda``).

Stage IV's fit (:mod:`embodmocap.motion.smplify`) is the torch work of the pipeline; on a CUDA
machine it runs there with ``--device cuda`` (or ``auto``). Asking for ``cuda`` where torch sees
no CUDA device is one clear error before any work starts, never a silent fall-back to the CPU.
torch is imported only when a device is resolved (``embodmocap --help`` must not load it).
"""

from __future__ import annotations

from typing import Literal

from embodmocap.errors import InputError

#: Values of ``--device``.
Device = Literal["auto", "cpu", "cuda"]
DEVICES: tuple[str, ...] = ("auto", "cpu", "cuda")


def resolve_device(name: str) -> str:
    """``"cpu"`` or ``"cuda"`` for a ``--device`` value: ``auto`` is CUDA when torch sees a CUDA
    device, else the CPU.

    Raises:
        InputError: an unknown name, or ``cuda`` without a CUDA device (the message says whether
            torch is a CPU-only build and what to pass instead).
    """
    if name not in DEVICES:
        raise InputError(None, f"unknown device {name!r}", "pass --device auto, cpu or cuda")
    if name == "cpu":
        return "cpu"
    import torch

    has_cuda = torch.cuda.is_available()
    if name == "cuda" and not has_cuda:
        why = (f"torch {torch.__version__} is a CPU-only build" if torch.version.cuda is None
               else f"torch {torch.__version__} (CUDA {torch.version.cuda}) finds no CUDA device")
        raise InputError(None, f"--device cuda asks for a GPU, but {why}",
                         "run with --device cpu (or auto), or on a machine with an NVIDIA GPU and a CUDA build of torch")
    return "cuda" if has_cuda else "cpu"


def motion_on_device(motion_cfg, device: str | None):
    """A Stage IV config (:class:`~embodmocap.motion.config.MotionConfig`) whose torch work runs on
    ``device`` (checked: :func:`resolve_device`); unchanged when ``device`` is None."""
    from dataclasses import replace

    if device is None:
        return motion_cfg
    resolve_device(device)  # one clear error now, before any stage runs
    return replace(motion_cfg, smplify=replace(motion_cfg.smplify, device=device))
