"""Hugging Face ``transformers`` perception backends: shared loading / pre-processing, and the factory.

The backends themselves live in one module each:

- :mod:`embodmocap.perception.hf_detect` -> :class:`~embodmocap.perception.hf_detect.RtDetrPersonDetector`
  (role ``"detector"``, name ``"rtdetr"``): RT-DETR person boxes.
- :mod:`embodmocap.perception.hf_pose` -> :class:`~embodmocap.perception.hf_pose.VitPoseKeypoints`
  (role ``"keypoints"``, name ``"vitpose"``): top-down ViTPose, COCO-17.
- :mod:`embodmocap.perception.hf_sam2` -> :class:`~embodmocap.perception.hf_sam2.Sam2VideoMasks`
  (role ``"masks"``, name ``"sam2"``): SAM 2 video masks prompted by the performer's box.

Every backend takes ``model``: a local folder written by ``save_pretrained`` (``config.json`` +
``model.safetensors``, optionally ``preprocessor_config.json``), a Hugging Face hub id (downloaded
into the standard cache unless ``offline``), or nothing for the role's default id; see
:mod:`embodmocap.perception.hub`. The image processors of ``transformers``
need torchvision for these models, which the package does not require, so each backend does its
own pre- and post-processing with OpenCV / numpy / torch, reading the numbers (input size,
rescale factor, mean, std) from the folder's ``preprocessor_config.json`` when it has one.

torch and transformers are imported only when a backend is built (``require(..., "perception")``),
so the package imports without them.
"""

from __future__ import annotations

import importlib
import json
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError, require

log = logging.getLogger(__name__)

IMAGENET_MEAN = (0.485, 0.456, 0.406)
"""RGB mean used when a model folder has no ``preprocessor_config.json`` and the model normalises."""
IMAGENET_STD = (0.229, 0.224, 0.225)
"""RGB standard deviation used with :data:`IMAGENET_MEAN`."""

_DTYPES = ("float32", "float16", "bfloat16")


# ------------------------------------------------------------------------------------------------
# Model folders (where they come from: embodmocap.perception.hub)


def read_preprocessor_config(model_dir: Path, names: Sequence[str] = ("preprocessor_config.json",)) -> dict:
    """The first of ``names`` found in ``model_dir`` as a dict ({} when none is there)."""
    for name in names:
        path = model_dir / name
        if path.is_file():
            try:
                cfg = json.loads(path.read_text())
            except (OSError, ValueError) as err:
                raise InputError(path, f"cannot be read as JSON ({err})", "fix or delete the file") from err
            if not isinstance(cfg, dict):
                raise InputError(path, "is not a JSON object", "fix or delete the file")
            return cfg
    return {}


def normalisation(cfg: dict, *, normalize_default: bool) -> tuple[float, NDArray[np.float32], NDArray[np.float32]]:
    """(rescale, mean (3,), std (3,)) such that the network input is ``(rgb * rescale - mean) / std``.

    Reads ``do_rescale``/``rescale_factor``/``do_normalize``/``image_mean``/``image_std`` of a
    preprocessor config; missing keys take the model family's defaults (``normalize_default``:
    whether that family normalises at all; RT-DETR does not, ViTPose and SAM 2 do, with ImageNet's).
    """
    rescale = float(cfg.get("rescale_factor", 1.0 / 255.0)) if cfg.get("do_rescale", True) else 1.0
    if cfg.get("do_normalize", normalize_default):
        mean, std = cfg.get("image_mean", IMAGENET_MEAN), cfg.get("image_std", IMAGENET_STD)
    else:
        mean, std = (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)
    return rescale, np.asarray(mean, np.float32).reshape(3), np.asarray(std, np.float32).reshape(3)


def configured_size(cfg: dict, default_hw: tuple[int, int]) -> tuple[int, int]:
    """(height, width) of the network input from a preprocessor config's ``size``, else ``default_hw``."""
    size = cfg.get("size")
    if isinstance(size, dict) and "height" in size and "width" in size:
        return int(size["height"]), int(size["width"])
    if isinstance(size, dict) and "longest_edge" in size and "shortest_edge" not in size:
        side = int(size["longest_edge"])
        return side, side
    return default_hw


def pick_device(torch, asked: str, what: str) -> str:
    """The torch device to run on: ``asked``, "auto" -> cuda when available, CPU when CUDA is absent."""
    if asked == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if asked.startswith("cuda") and not torch.cuda.is_available():
        log.warning("device %r asked for but CUDA is not available: running %s on the CPU", asked, what)
        return "cpu"
    return asked


def torch_dtype(torch, name: str):
    """The torch dtype called ``name`` (float32, float16 or bfloat16)."""
    if name not in _DTYPES:
        raise ValueError(f"dtype must be one of {_DTYPES}, got {name!r}")
    return getattr(torch, name)


def load_model(model_dir: Path, classes: dict[str, str], device: str, dtype, hint: str):
    """The model in ``model_dir`` (eval mode on ``device``), of a class chosen by its ``model_type``.

    ``classes`` maps accepted ``config.model_type`` values to ``transformers`` class names; any
    other type, a missing/broken config or missing weights raise a one-line InputError whose fix
    is ``hint`` (which model to pass instead).
    """
    transformers = require("transformers", "perception")
    config_path = model_dir / "config.json"
    if not config_path.is_file():
        raise InputError(model_dir, "is not a Hugging Face model folder (no config.json)",
                         "pass the folder written by save_pretrained (config.json + model.safetensors)")
    try:
        config = transformers.AutoConfig.from_pretrained(model_dir, local_files_only=True)
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise InputError(config_path, f"cannot be read as a model config ({err})".replace("\n", " "),
                         "re-save the model with save_pretrained") from err
    if config.model_type not in classes:
        raise InputError(config_path, f"model_type is {config.model_type!r}, not one of {sorted(classes)}", hint)
    cls = getattr(transformers, classes[config.model_type])
    try:
        model = cls.from_pretrained(model_dir, config=config, local_files_only=True)
    except (OSError, ValueError, RuntimeError) as err:
        raise InputError(model_dir, f"model weights cannot be loaded ({err})".replace("\n", " "),
                         "the folder needs the model.safetensors written by save_pretrained") from err
    return model.to(device=device, dtype=dtype).eval()


# ------------------------------------------------------------------------------------------------
# Images


def check_frames(frames: Sequence[Any], frame_ids: Sequence[int]) -> None:
    """Raise ValueError unless ``frames`` are (H, W, 3) uint8 images, one per frame id."""
    if len(frames) != len(frame_ids):
        raise ValueError(f"got {len(frames)} frames but {len(frame_ids)} frame ids")
    for i, rgb in enumerate(frames):
        rgb = np.asarray(rgb)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise ValueError(f"frame {i}: RGB must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")


def resize_rgb(rgb: NDArray[np.uint8], hw: tuple[int, int]) -> NDArray[np.uint8]:
    """``rgb`` stretched to (h, w) (no aspect-ratio padding, as the HF processors of these models do).

    Shrinking uses area averaging (the processors resize with antialiasing), enlarging bilinear.
    """
    h, w = hw
    if rgb.shape[:2] == (h, w):
        return rgb
    shrink = h < rgb.shape[0] or w < rgb.shape[1]
    return cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)


def pixel_values(images: NDArray[np.uint8], rescale: float, mean: NDArray[np.float32],
                 std: NDArray[np.float32]) -> NDArray[np.float32]:
    """(B, 3, h, w) float32 network input ``(rgb * rescale - mean) / std`` of (B, h, w, 3) uint8 images."""
    x = (images.astype(np.float32) * np.float32(rescale) - mean) / std
    return np.ascontiguousarray(x.transpose(0, 3, 1, 2))


# ------------------------------------------------------------------------------------------------
# Factory


HF_BACKENDS: dict[tuple[str, str], str] = {
    ("detector", "rtdetr"): "embodmocap.perception.hf_detect:RtDetrPersonDetector",
    ("keypoints", "vitpose"): "embodmocap.perception.hf_pose:VitPoseKeypoints",
    ("masks", "sam2"): "embodmocap.perception.hf_sam2:Sam2VideoMasks",
}
"""(role, backend name) -> "module:Class" of the ``transformers`` backends (imported on demand)."""


def backend_class(role: str, name: str) -> type:
    """The class of backend ``name`` for ``role`` ("detector", "keypoints" or "masks")."""
    key = (role.strip().lower(), name.strip().lower())
    if key not in HF_BACKENDS:
        choices = ", ".join(f"{r}/{n}" for r, n in sorted(HF_BACKENDS))
        raise ValueError(f"unknown transformers backend {role!r}/{name!r}; choose one of {choices}")
    module, cls = HF_BACKENDS[key].split(":")
    return getattr(importlib.import_module(module), cls)


def make_backend(role: str, name: str, **options: Any):
    """Backend ``name`` for ``role`` built with ``options`` (the keyword arguments of its class).

    Covers the ``transformers`` entries of :data:`HF_BACKENDS`: ("detector", "rtdetr"),
    ("keypoints", "vitpose"), ("masks", "sam2").
    """
    return backend_class(role, name)(**options)
