"""Training data from a processed dataset: :class:`SequenceDataset` (PyTorch), :class:`FrameDataset`
(frames of a training export, :mod:`embodmocap.data.frames`) and the height map / contact helpers in
:mod:`embodmocap.data.terrain`. Importing this package does not import torch; the datasets do, on
first use."""

from __future__ import annotations

from typing import Any

__all__ = ["FrameDataset", "SequenceDataset"]


def __getattr__(name: str) -> Any:
    if name == "SequenceDataset":
        from embodmocap.data.sequence_dataset import SequenceDataset

        return SequenceDataset
    if name == "FrameDataset":
        from embodmocap.data.frames import FrameDataset

        return FrameDataset
    raise AttributeError(name)
