"""RT-DETR person detection through ``transformers`` (the ``"rtdetr"`` PersonDetector backend).

Pre-processing (per frame): the RGB image is stretched to the model input size (the folder's
``preprocessor_config.json`` ``size``, 640x640 by default; no padding, aspect ratio not kept, as
RT-DETR was trained) and turned into ``rgb * rescale`` (RT-DETR does not mean/std-normalise by
default; a config with ``do_normalize: true`` is honoured).

Post-processing: the model predicts, per query, class logits and a box ``(cx, cy, w, h)``
normalised to [0, 1] of the image (0 = left/top image edge, 1 = right/bottom edge). The person
score of a query is ``sigmoid(logit[person])`` (RT-DETR is trained with a focal loss; models with
``use_focal_loss = false`` use a softmax over the classes). Queries whose person score reaches
``score_threshold`` are kept, sorted by decreasing score. Boxes are mapped to pixels of the
original image with pixel centres at integers (the image spans [-0.5, W - 0.5]):
``x = u * W - 0.5``, and clipped to the image. RT-DETR is trained without non-maximum
suppression (one query per object), so none is applied.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError, require
from embodmocap.perception import hf_backends as hf
from embodmocap.perception import hub

log = logging.getLogger(__name__)

_CLASSES = {"rt_detr": "RTDetrForObjectDetection", "rt_detr_v2": "RTDetrV2ForObjectDetection"}
_EXAMPLE = hub.DEFAULT_MODELS["detector"]


def normalized_cxcywh_to_xyxy(boxes: NDArray[np.floating], width: int, height: int) -> NDArray[np.float64]:
    """(..., 4) boxes ``cx, cy, w, h`` in [0, 1] of the image -> ``x1, y1, x2, y2`` pixels, clipped.

    Pixel centres are at integers, so normalised 0 is the left edge x = -0.5 and 1 the right edge
    x = W - 0.5.
    """
    b = np.asarray(boxes, dtype=np.float64)
    half = b[..., 2:4] / 2.0
    lo, hi = b[..., 0:2] - half, b[..., 0:2] + half
    scale = np.array([width, height], dtype=np.float64)
    xyxy = np.concatenate([lo * scale - 0.5, hi * scale - 0.5], axis=-1)
    limit = np.array([width, height, width, height], dtype=np.float64) - 0.5
    return np.clip(xyxy, -0.5, limit)


def person_scores(logits: NDArray[np.floating], person_id: int, focal: bool) -> NDArray[np.float64]:
    """(B, Q) person probability of each query from (B, Q, C) class logits.

    ``focal``: independent sigmoids per class (RT-DETR); otherwise a softmax over the C classes.
    """
    x = np.asarray(logits, dtype=np.float64)
    if focal:
        return 1.0 / (1.0 + np.exp(-x[..., person_id]))
    z = np.exp(x - x.max(axis=-1, keepdims=True))
    return z[..., person_id] / z.sum(axis=-1)


class RtDetrPersonDetector:
    """The ``"rtdetr"`` backend: person boxes from an RT-DETR (v1 or v2) object detector.

    Args:
        model: local folder written by ``save_pretrained``, or a hub id (cached, else downloaded
            into the Hugging Face cache); None or "" = the default ``PekingU/rtdetr_r50vd_coco_o365``.
        device: "cpu", "cuda", "cuda:N" or "auto"; an unavailable CUDA falls back to the CPU.
        batch_size: frames per forward pass.
        score_threshold: minimum person score in [0, 1] for a box to be kept.
        person_label: the class name of people in the model's ``id2label`` (case-insensitive).
        dtype: "float32", "float16" or "bfloat16" (half precision is meant for CUDA).
        offline: never download (the model must be a folder or in the cache); HF_HUB_OFFLINE=1 does the same.

    Attributes:
        model_dir, model, device, input_hw (network input (h, w)), person_id (class index).
    """

    name = "rtdetr"

    def __init__(self, model: str | Path | None = None, device: str = "cpu", batch_size: int = 8,
                 score_threshold: float = 0.5, person_label: str = "person", dtype: str = "float32",
                 offline: bool = False) -> None:
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        if not 0.0 <= score_threshold <= 1.0:
            raise ValueError(f"score_threshold must be in [0, 1], got {score_threshold}")
        self._torch = require("torch", "perception")
        self.batch_size = int(batch_size)
        self.score_threshold = float(score_threshold)
        self.model_dir = hub.resolve_model_folder(model, "detector", offline=offline)
        self.device = hf.pick_device(self._torch, device, "RT-DETR")
        self._dtype = hf.torch_dtype(self._torch, dtype)
        cfg = hf.read_preprocessor_config(self.model_dir)
        self.input_hw = hf.configured_size(cfg, (640, 640))
        self._rescale, self._mean, self._std = hf.normalisation(cfg, normalize_default=False)
        self.model = hf.load_model(self.model_dir, _CLASSES, self.device, self._dtype,
                                   f"pass an RT-DETR object detector (e.g. {_EXAMPLE})")
        self.person_id = self._find_label(person_label)
        self._focal = bool(getattr(self.model.config, "use_focal_loss", True))
        log.info("RT-DETR from %s on %s (input %dx%d, person = class %d, threshold %.2f)", self.model_dir,
                 self.device, self.input_hw[1], self.input_hw[0], self.person_id, self.score_threshold)

    def _find_label(self, person_label: str) -> int:
        """Index of ``person_label`` in the model's id2label (InputError naming config.json if absent)."""
        id2label = {int(k): str(v) for k, v in self.model.config.id2label.items()}
        hits = [i for i, lab in id2label.items() if lab.strip().lower() == person_label.strip().lower()]
        if not hits:
            shown = ", ".join(sorted(id2label.values())[:10])
            raise InputError(self.model_dir / "config.json", f"id2label has no class {person_label!r} (has {shown}...)",
                             "pass person_label= with the model's name for people")
        return min(hits)

    def detect(self, frames: Sequence[NDArray[np.uint8]], frame_ids: Sequence[int]) -> list[NDArray[np.float64]]:
        """Per frame, (N, 5) rows ``x1, y1, x2, y2, score`` (pixels, score-sorted); (0, 5) if none."""
        hf.check_frames(frames, frame_ids)
        out: list[NDArray[np.float64]] = []
        for start in range(0, len(frames), self.batch_size):
            out.extend(self._run_chunk(frames[start:start + self.batch_size]))
        return out

    def _pixel_values(self, frames: Sequence[NDArray[np.uint8]]) -> NDArray[np.float32]:
        """(B, 3, h, w) network input of any-size frames (each stretched to the input size)."""
        resized = np.stack([hf.resize_rgb(np.asarray(f), self.input_hw) for f in frames])
        return hf.pixel_values(resized, self._rescale, self._mean, self._std)

    def _run_chunk(self, frames: Sequence[NDArray[np.uint8]]) -> list[NDArray[np.float64]]:
        """Detections of up to ``batch_size`` frames in one forward pass."""
        torch = self._torch
        x = torch.from_numpy(self._pixel_values(frames)).to(self.device, self._dtype)
        with torch.inference_mode():
            pred = self.model(pixel_values=x)
            logits = pred.logits.float().cpu().numpy()  # (B, Q, C)
            boxes = pred.pred_boxes.float().cpu().numpy()  # (B, Q, 4) normalised cx, cy, w, h
        scores = person_scores(logits, self.person_id, self._focal)
        results = []
        for frame, s, b in zip(frames, scores, boxes):
            keep = np.flatnonzero(s >= self.score_threshold)
            keep = keep[np.argsort(-s[keep], kind="stable")]
            h, w = np.shape(frame)[:2]
            xyxy = normalized_cxcywh_to_xyxy(b[keep], w, h)
            results.append(np.concatenate([xyxy, s[keep, None]], axis=1).reshape(-1, 5))
        return results
