"""Top-down ViTPose keypoints through ``transformers`` (the ``"vitpose"`` KeypointEstimator backend).

Geometry (the "unbiased" convention ViTPose is trained with). For a person box ``x1, y1, x2, y2``:

1. Crop window: centre ``c`` = the box centre; the box is widened or heightened to the network
   input's aspect ratio (w / h = 192 / 256 by default) and then scaled by ``padding`` (1.25), giving
   the window size ``s = (sw, sh)`` in pixels.
2. Network input (h_in x w_in): input pixel ``i`` (pixel centres at integers) samples the image at
   ``x = c_x - sw / 2 + i * sw / (w_in - 1)`` (same in y), i.e. the window's edges fall on the
   first and last pixel centres. Sampled bilinearly with ``cv2.warpAffine``; outside the image = 0
   (black), then ``(rgb * rescale - mean) / std`` (ImageNet's unless the folder says otherwise).
3. Heatmaps (K x h_hm x w_hm, K = 17 COCO keypoints): per keypoint the argmax pixel, refined to
   sub-pixel precision with one Newton step on the log of the slightly blurred heatmap (the DARK
   method: exact for a Gaussian peak), a step taken only where the log-heatmap is locally concave
   (along one axis only when the peak touches the heatmap border) and clipped to one pixel. Heatmap pixel ``u`` maps back to ``x = c_x - sw / 2 + u * sw / (w_hm - 1)``.
4. Confidence = the heatmap's maximum, clipped to [0, 1]. Boxes with a NaN or non-positive size
   give all-zero keypoints (confidence 0 = missing).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter

from embodmocap.errors import InputError, require
from embodmocap.perception import hf_backends as hf
from embodmocap.perception import hub
from embodmocap.types import COCO17_NAMES

log = logging.getLogger(__name__)

_CLASSES = {"vitpose": "VitPoseForPoseEstimation"}
_EXAMPLE = hub.DEFAULT_MODELS["keypoints"]
_DARK_SIGMA = 0.8
"""Standard deviation (heatmap pixels) of the blur before the DARK refinement (a 3x3 kernel)."""


def crop_windows(boxes: NDArray[np.floating], aspect: float, padding: float = 1.25
                 ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Crop windows of (N, 4) ``x1, y1, x2, y2`` boxes: centres (N, 2) and sizes (N, 2) ``sw, sh``.

    ``aspect`` is the network input's width / height; the box grows (never shrinks) along one axis
    to reach it, then both sides are multiplied by ``padding``.
    """
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    centres = (b[:, 0:2] + b[:, 2:4]) / 2.0
    w, h = b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]
    w, h = np.maximum(w, h * aspect), np.maximum(h, w / aspect)
    return centres, np.stack([w, h], axis=1) * padding


def window_to_grid(centres: NDArray[np.float64], sizes: NDArray[np.float64], grid_hw: tuple[int, int]
                   ) -> NDArray[np.float64]:
    """(N, 2, 3) affine maps from image pixels to a (h, w) grid spanning each window edge to edge."""
    h, w = grid_hw
    scale = np.stack([(w - 1) / sizes[:, 0], (h - 1) / sizes[:, 1]], axis=1)  # (N, 2)
    origin = centres - sizes / 2.0
    m = np.zeros((len(centres), 2, 3))
    m[:, 0, 0], m[:, 1, 1] = scale[:, 0], scale[:, 1]
    m[:, :, 2] = -origin * scale
    return m


def grid_to_image(coords: NDArray[np.floating], centres: NDArray[np.float64], sizes: NDArray[np.float64],
                  grid_hw: tuple[int, int]) -> NDArray[np.float64]:
    """(N, K, 2) grid-pixel coordinates of a (h, w) grid over each window -> image pixels."""
    h, w = grid_hw
    step = sizes / np.array([w - 1, h - 1], dtype=np.float64)  # (N, 2) image px per grid px
    origin = centres - sizes / 2.0
    return np.asarray(coords, np.float64) * step[:, None, :] + origin[:, None, :]


def decode_heatmaps(heatmaps: NDArray[np.floating]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(N, K, h, w) heatmaps -> sub-pixel peak coordinates (N, K, 2) ``x, y`` in heatmap pixels and
    the peak values (N, K) (the confidences before clipping). See the module docstring (step 3)."""
    hm = np.asarray(heatmaps, dtype=np.float64)
    n, k, h, w = hm.shape
    flat = hm.reshape(n, k, -1)
    idx = flat.argmax(axis=2)
    peak = np.take_along_axis(flat, idx[..., None], axis=2)[..., 0]
    ix, iy = (idx % w).astype(np.float64), (idx // w).astype(np.float64)

    # DARK: blur (3x3), log, Taylor expansion around the argmax; the log of a Gaussian is a
    # quadratic, so one Newton step lands on its true centre.
    logs = np.log(np.clip(gaussian_filter(hm, sigma=(0, 0, _DARK_SIGMA, _DARK_SIGMA), truncate=1.25), 1e-3, 50.0))
    pad = np.pad(logs, ((0, 0), (0, 0), (1, 1), (1, 1)), mode="edge")
    yy, xx = (idx // w + 1)[..., None], (idx % w + 1)[..., None]  # (N, K, 1) in padded coordinates

    def at(dy: int, dx: int) -> NDArray[np.float64]:
        rows = np.take_along_axis(pad, (yy + dy)[..., None], axis=2)[..., 0, :]  # (N, K, w + 2)
        return np.take_along_axis(rows, xx + dx, axis=2)[..., 0]

    c = at(0, 0)
    gx, gy = (at(0, 1) - at(0, -1)) / 2.0, (at(1, 0) - at(-1, 0)) / 2.0
    hxx, hyy = at(0, 1) - 2 * c + at(0, -1), at(1, 0) - 2 * c + at(-1, 0)
    hxy = (at(1, 1) - at(1, -1) - at(-1, 1) + at(-1, -1)) / 4.0
    # Central differences need both neighbours: along an axis where the argmax touches the border,
    # no step is taken (the 2D step is replaced by a 1D one along the other axis).
    in_x, in_y = (ix > 0) & (ix < w - 1), (iy > 0) & (iy < h - 1)
    det = hxx * hyy - hxy * hxy
    full = in_x & in_y & (hxx < 0) & (det > 1e-12)
    safe = np.where(full, det, 1.0)
    step_x = np.where(full, -(hyy * gx - hxy * gy) / safe, 0.0)
    step_y = np.where(full, -(hxx * gy - hxy * gx) / safe, 0.0)
    only_x, only_y = in_x & ~in_y & (hxx < 0), in_y & ~in_x & (hyy < 0)
    step_x = np.where(only_x, -gx / np.where(only_x, hxx, 1.0), step_x)
    step_y = np.where(only_y, -gy / np.where(only_y, hyy, 1.0), step_y)
    coords = np.stack([ix + np.clip(step_x, -1.0, 1.0), iy + np.clip(step_y, -1.0, 1.0)], axis=-1)
    return coords, peak


class VitPoseKeypoints:
    """The ``"vitpose"`` backend: COCO-17 keypoints of given boxes with ViTPose (top-down).

    Args:
        model: local folder written by ``save_pretrained``, or a hub id (cached, else downloaded
            into the Hugging Face cache); None or "" = the default ``usyd-community/vitpose-base-simple``; its head must predict 17 heatmaps.
        device: "cpu", "cuda", "cuda:N" or "auto"; an unavailable CUDA falls back to the CPU.
        batch_size: person crops per forward pass (crops of all frames of a call are pooled).
        padding: crop window size relative to the aspect-corrected box (1.25 as in training).
        dataset_index: expert of ViTPose+ (mixture-of-experts) backbones; 0 = COCO.
        dtype: "float32", "float16" or "bfloat16".
        offline: never download (the model must be a folder or in the cache); HF_HUB_OFFLINE=1 does the same.

    Attributes:
        model_dir, model, device, input_hw (network input (h, w), 256x192 by default).
    """

    name = "vitpose"

    def __init__(self, model: str | Path | None = None, device: str = "cpu", batch_size: int = 16,
                 padding: float = 1.25, dataset_index: int = 0, dtype: str = "float32", offline: bool = False) -> None:
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        if padding < 1.0:
            raise ValueError(f"padding must be >= 1, got {padding}")
        self._torch = require("torch", "perception")
        self.batch_size, self.padding, self.dataset_index = int(batch_size), float(padding), int(dataset_index)
        self.model_dir = hub.resolve_model_folder(model, "keypoints", offline=offline)
        self.device = hf.pick_device(self._torch, device, "ViTPose")
        self._dtype = hf.torch_dtype(self._torch, dtype)
        self.model = hf.load_model(self.model_dir, _CLASSES, self.device, self._dtype,
                                   f"pass a ViTPose model (e.g. {_EXAMPLE})")
        backbone = self.model.config.backbone_config
        default_hw = tuple(int(v) for v in np.broadcast_to(np.asarray(backbone.image_size), (2,)))
        cfg = hf.read_preprocessor_config(self.model_dir)
        self.input_hw = hf.configured_size(cfg, default_hw)
        self._rescale, self._mean, self._std = hf.normalisation(cfg, normalize_default=True)
        self._experts = int(getattr(backbone, "num_experts", 1))
        if self.model.config.num_labels != len(COCO17_NAMES):
            raise InputError(self.model_dir / "config.json",
                             f"the model predicts {self.model.config.num_labels} keypoints, not the 17 of COCO",
                             "pass a ViTPose model trained on COCO (17 keypoints)")
        log.info("ViTPose from %s on %s (input %dx%d, batch %d)", self.model_dir, self.device,
                 self.input_hw[1], self.input_hw[0], self.batch_size)

    def estimate(self, frames: Sequence[NDArray[np.uint8]], frame_ids: Sequence[int],
                 boxes: Sequence[NDArray[np.float64]]) -> list[NDArray[np.float64]]:
        """Per frame, (N, 17, 3) keypoints ``x, y, confidence`` for that frame's N boxes (same order).

        Box rows are ``x1, y1, x2, y2`` (a fifth score column is ignored).
        """
        hf.check_frames(frames, frame_ids)
        if len(boxes) != len(frames):
            raise ValueError(f"got {len(frames)} frames but {len(boxes)} box arrays")
        if not frames:
            return []
        per_frame = [np.asarray(b, np.float64).reshape(-1, np.shape(b)[-1] if np.size(b) else 4)[:, :4]
                     for b in boxes]
        owner = np.concatenate([np.full(len(b), i) for i, b in enumerate(per_frame)]).astype(int)
        all_boxes = np.concatenate(per_frame) if per_frame else np.zeros((0, 4))
        valid = np.isfinite(all_boxes).all(axis=1) & (all_boxes[:, 2] > all_boxes[:, 0]) & \
            (all_boxes[:, 3] > all_boxes[:, 1])
        keypoints = np.zeros((len(all_boxes), len(COCO17_NAMES), 3))
        todo = np.flatnonzero(valid)
        for start in range(0, len(todo), self.batch_size):
            rows = todo[start:start + self.batch_size]
            keypoints[rows] = self._run_chunk([frames[owner[r]] for r in rows], all_boxes[rows])
        splits = np.cumsum([len(b) for b in per_frame])[:-1]
        return np.split(keypoints, splits)

    def crops(self, frames: Sequence[NDArray[np.uint8]], boxes: NDArray[np.float64]
              ) -> tuple[NDArray[np.uint8], NDArray[np.float64], NDArray[np.float64]]:
        """(N, h_in, w_in, 3) crops of box ``i`` in ``frames[i]``, with their window centres and sizes."""
        h, w = self.input_hw
        centres, sizes = crop_windows(boxes, w / h, self.padding)
        maps = window_to_grid(centres, sizes, self.input_hw)
        out = np.stack([cv2.warpAffine(np.asarray(f), m, (w, h), flags=cv2.INTER_LINEAR,
                                       borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0))
                        for f, m in zip(frames, maps)])
        return out, centres, sizes

    def _run_chunk(self, frames: Sequence[NDArray[np.uint8]], boxes: NDArray[np.float64]) -> NDArray[np.float64]:
        """(N, 17, 3) keypoints of N (frame, box) pairs in one forward pass."""
        torch = self._torch
        crops, centres, sizes = self.crops(frames, boxes)
        x = torch.from_numpy(hf.pixel_values(crops, self._rescale, self._mean, self._std)).to(self.device, self._dtype)
        kwargs = {}
        if self._experts > 1:
            kwargs["dataset_index"] = torch.full((len(x),), self.dataset_index, dtype=torch.long, device=self.device)
        with torch.inference_mode():
            heatmaps = self.model(pixel_values=x, **kwargs).heatmaps.float().cpu().numpy()  # (N, 17, h, w)
        coords, peak = decode_heatmaps(heatmaps)
        xy = grid_to_image(coords, centres, sizes, heatmaps.shape[2:])
        return np.concatenate([xy, np.clip(peak, 0.0, 1.0)[..., None]], axis=-1)
