"""Training data from a processed dataset: :class:`SequenceDataset` (PyTorch) and the height map /
contact helpers in :mod:`embodmocap.data.terrain`. Importing this package does not import torch;
``SequenceDataset`` does, on first use."""

from __future__ import annotations

from typing import Any

__all__ = ["SequenceDataset"]


def __getattr__(name: str) -> Any:
    if name == "SequenceDataset":
        from embodmocap.data.sequence_dataset import SequenceDataset

        return SequenceDataset
    raise AttributeError(name)
