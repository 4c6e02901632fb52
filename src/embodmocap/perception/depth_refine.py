"""Depth refinement: an RGB image plus the phone's LiDAR depth in, dense metric depth out.

Stage I (scene mesh, off by default on CPU) and Stage II (per-view depth) call one
:class:`DepthRefiner`; which one is a config choice (``make_depth_refiner(name, **options)``):

- ``"none"`` -> :class:`LidarDepth`: the sensor depth as it is (the geometric fallback, no weights).
- ``"promptda"`` -> :class:`PromptDepthAnything`: Prompt Depth Anything through Hugging Face
  ``transformers`` (the role of the paper's PromptDA and the release's LingBot depth). The network
  takes the RGB image resized so its long side is at most ``max_side`` with both sides multiples of
  14 (the ViT patch), and the sensor depth in metres at sensor resolution as the prompt. It
  predicts depth at the network input size, which is resized back with cubic interpolation.

Conventions shared by every backend:

- ``rgb``: (H, W, 3) uint8 RGB; ``depth``: (h, w) float metres, 0 = invalid (NaN, inf and negative
  values are treated as invalid too). Both images come from the same camera (same field of view),
  usually at different resolutions (e.g. 960x720 RGB and 256x192 depth).
- The result is a list of (H_out, W_out) float32 depth maps in metres, 0 = invalid, one per input
  frame and in the input order.

torch and transformers are imported only when a learned backend is built, so the package imports
without them; a missing ``transformers`` raises :class:`~embodmocap.errors.MissingExtraError`.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Protocol, runtime_checkable

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import distance_transform_edt

from embodmocap.errors import InputError, require

log = logging.getLogger(__name__)

PATCH = 14
"""Side of the ViT patch of Depth Anything / Prompt Depth Anything: network inputs are multiples."""

IMAGENET_MEAN = (0.485, 0.456, 0.406)
"""RGB mean used when the model folder has no ``preprocessor_config.json`` (PromptDA's own)."""
IMAGENET_STD = (0.229, 0.224, 0.225)
"""RGB standard deviation used when the model folder has no ``preprocessor_config.json``."""

_CONSTANT_PROMPT_BUMP_M = 1e-4
"""Added to one pixel of a constant prompt: the model divides by the prompt's (max - min)."""



@runtime_checkable
class DepthRefiner(Protocol):
    """Turns RGB + sensor depth into (refined) metric depth; see the module docstring for units."""

    name: str
    """The backend's name as given to :func:`make_depth_refiner`."""

    def refine(
        self, rgb_batch: Sequence[NDArray[np.uint8]], depth_batch: Sequence[NDArray[np.floating]]
    ) -> list[NDArray[np.float32]]:
        """One (H_out, W_out) float32 depth map in metres (0 = invalid) per input pair, in order."""
        ...


# ------------------------------------------------------------------------------------------------
# Shared checks and small array helpers


def _check_batch(rgb_batch: Sequence[Any], depth_batch: Sequence[Any]) -> None:
    """Raise ValueError when the two lists do not hold matching RGB / depth images."""
    if len(rgb_batch) != len(depth_batch):
        raise ValueError(f"got {len(rgb_batch)} RGB images but {len(depth_batch)} depth maps")
    for i, (rgb, depth) in enumerate(zip(rgb_batch, depth_batch)):
        rgb, depth = np.asarray(rgb), np.asarray(depth)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise ValueError(f"frame {i}: RGB must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
        if depth.ndim != 2 or not np.issubdtype(depth.dtype, np.floating):
            raise ValueError(f"frame {i}: depth must be (h, w) float metres, got {depth.shape} {depth.dtype}")
        # Same camera at two resolutions: the aspect ratios agree (a portrait RGB with a landscape
        # depth map means one of them was rotated and the prompt would be meaningless).
        ar_rgb, ar_depth = rgb.shape[1] / rgb.shape[0], depth.shape[1] / depth.shape[0]
        if abs(ar_rgb / ar_depth - 1.0) > 0.05:
            raise ValueError(
                f"frame {i}: RGB {rgb.shape[1]}x{rgb.shape[0]} and depth {depth.shape[1]}x{depth.shape[0]} "
                "have different aspect ratios (is one of them rotated?)"
            )


def clean_depth(depth: NDArray[np.floating]) -> NDArray[np.float32]:
    """A float32 copy of ``depth`` with NaN, inf and negative values set to 0 (invalid)."""
    d = np.asarray(depth, dtype=np.float32).copy()
    d[~np.isfinite(d) | (d < 0)] = 0.0
    return d


def fill_invalid_nearest(depth: NDArray[np.float32]) -> NDArray[np.float32]:
    """Invalid (0) pixels take the value of the nearest valid pixel (Euclidean, in pixels).

    Why: Prompt Depth Anything normalises each prompt by its own min and max, so a hole left at 0
    would drag the minimum to 0 and change the scale of the whole frame; PromptDA was trained on
    ARKit depth, which has no holes. A depth map with no valid pixel is returned unchanged (zeros).
    """
    valid = depth > 0
    if valid.all() or not valid.any():
        return depth.copy()
    _, (iy, ix) = distance_transform_edt(~valid, return_indices=True)
    return depth[iy, ix]


def network_input_size(height: int, width: int, max_side: int, multiple: int = PATCH) -> tuple[int, int]:
    """(h, w) of the network input for an (height, width) image.

    The image is shrunk (never enlarged) so that its long side fits ``max_side`` rounded down to a
    multiple of ``multiple``; each side is then rounded to the nearest multiple (at least one
    patch). Rounding never pushes the long side past the limit because the limit is itself a
    multiple. The aspect ratio changes by at most half a patch per side; the prediction covers the
    whole image either way, as the image is stretched, not cropped.
    """
    limit = max(multiple, (int(max_side) // multiple) * multiple)
    scale = min(1.0, limit / max(height, width))
    h = max(multiple, int(round(height * scale / multiple)) * multiple)
    w = max(multiple, int(round(width * scale / multiple)) * multiple)
    return h, w


# ------------------------------------------------------------------------------------------------
# Geometric fallback


class LidarDepth:
    """The ``"none"`` backend: returns the sensor depth (float32 copies, non-finite/negative -> 0).

    Output size = the depth map's own size. Needs no weights and no torch.
    """

    name = "none"

    def refine(
        self, rgb_batch: Sequence[NDArray[np.uint8]], depth_batch: Sequence[NDArray[np.floating]]
    ) -> list[NDArray[np.float32]]:
        """The input depth maps, cleaned (see :func:`clean_depth`), in order."""
        _check_batch(rgb_batch, depth_batch)
        return [clean_depth(d) for d in depth_batch]


# ------------------------------------------------------------------------------------------------
# Prompt Depth Anything


@dataclass(frozen=True)
class PromptDAOptions:
    """Options of the ``"promptda"`` backend."""

    model: str
    """Local folder written by ``save_pretrained`` (``config.json`` + ``model.safetensors``), or a
    Hugging Face hub id (taken from the standard cache, downloaded into it when missing unless
    ``offline``); "" = the default ``depth-anything/prompt-depth-anything-vits-hf``
    (:data:`embodmocap.perception.hub.DEFAULT_MODELS`)."""
    device: str = "cpu"
    """"cpu", "cuda", "cuda:N" or "auto" (= cuda when available). An unavailable CUDA device falls
    back to the CPU with a warning."""
    batch_size: int = 4
    """Frames per forward pass (the release runs chunks of 4-8)."""
    max_side: int = 1008
    """Long side of the network input in pixels, rounded down to a multiple of 14 (the release uses
    1008 for the scene, 960 / 720 for the views). Smaller images are not enlarged."""
    output: Literal["rgb", "depth"] = "rgb"
    """Resolution of the result: "rgb" = the RGB image's (H, W); "depth" = the sensor depth's (h, w)."""
    dtype: Literal["float32", "float16", "bfloat16"] = "float32"
    """Weights and activations type; half precision is meant for CUDA."""
    mask_invalid: bool = False
    """Zero the result where the sensor had no depth (nearest-neighbour map of the invalid pixels).
    Off by default: filling holes is part of what refinement is for."""
    offline: bool = False
    """Never download: the model must be a local folder or already in the Hugging Face cache (also
    when HF_HUB_OFFLINE=1 is set)."""

    def __post_init__(self) -> None:
        if self.batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {self.batch_size}")
        if self.max_side < PATCH:
            raise ValueError(f"max_side must be >= {PATCH}, got {self.max_side}")
        if self.output not in ("rgb", "depth"):
            raise ValueError(f"output must be 'rgb' or 'depth', got {self.output!r}")
        if self.dtype not in ("float32", "float16", "bfloat16"):
            raise ValueError(f"dtype must be float32, float16 or bfloat16, got {self.dtype!r}")


def _read_normalisation(model_dir: Path) -> tuple[float, NDArray[np.float32], NDArray[np.float32]]:
    """(rescale factor, mean (3,), std (3,)) from the folder's preprocessor_config.json, if any.

    Pixel values fed to the network are ``(rgb * rescale - mean) / std``.
    """
    rescale, mean, std = 1.0 / 255.0, IMAGENET_MEAN, IMAGENET_STD
    cfg_path = model_dir / "preprocessor_config.json"
    if cfg_path.is_file():
        try:
            cfg = json.loads(cfg_path.read_text())
        except (OSError, ValueError) as err:
            raise InputError(cfg_path, f"cannot be read as JSON ({err})", "fix or delete the file") from err
        if cfg.get("do_rescale", True):
            rescale = float(cfg.get("rescale_factor", rescale))
        else:
            rescale = 1.0
        if cfg.get("do_normalize", True):
            mean, std = cfg.get("image_mean", mean), cfg.get("image_std", std)
        else:
            mean, std = (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)
    return (rescale, np.asarray(mean, np.float32).reshape(3), np.asarray(std, np.float32).reshape(3))


def _pick_device(torch, asked: str) -> str:
    """The torch device to run on: ``asked``, or the CPU when CUDA is asked for but absent."""
    if asked == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if asked.startswith("cuda") and not torch.cuda.is_available():
        log.warning("device %r asked for but CUDA is not available: running Prompt Depth Anything on the CPU", asked)
        return "cpu"
    return asked


def _load_model(model_dir: Path, device: str, dtype):
    """The PromptDepthAnythingForDepthEstimation in ``model_dir``, in eval mode on ``device``."""
    transformers = require("transformers", "perception")
    if not (model_dir / "config.json").is_file():
        raise InputError(model_dir, "is not a Hugging Face model folder (no config.json)",
                         "pass the folder written by save_pretrained (config.json + model.safetensors)")
    try:
        config = transformers.AutoConfig.from_pretrained(model_dir, local_files_only=True)
    except (OSError, ValueError, KeyError) as err:
        raise InputError(model_dir / "config.json", f"cannot be read as a model config ({err})".replace("\n", " "),
                         "re-save the model with save_pretrained") from err
    if config.model_type != "prompt_depth_anything":
        raise InputError(model_dir / "config.json", f"model_type is {config.model_type!r}, not 'prompt_depth_anything'",
                         "pass a Prompt Depth Anything model (e.g. depth-anything/prompt-depth-anything-vits-hf)")
    try:
        model = transformers.PromptDepthAnythingForDepthEstimation.from_pretrained(
            model_dir, config=config, local_files_only=True
        )
    except (OSError, ValueError, RuntimeError) as err:
        raise InputError(model_dir, f"model weights cannot be loaded ({err})".replace("\n", " "),
                         "the folder needs the model.safetensors written by save_pretrained") from err
    return model.to(device=device, dtype=dtype).eval()


class PromptDepthAnything:
    """The ``"promptda"`` backend: Prompt Depth Anything (``transformers``) with the LiDAR as prompt.

    Per frame:

    1. RGB -> network input: resized with ``cv2.INTER_AREA`` to :func:`network_input_size`
       (long side <= ``max_side``, both sides multiples of 14), then ``(rgb * rescale - mean) / std``
       with the values of the model folder's ``preprocessor_config.json`` (ImageNet's if absent).
    2. Prompt: the sensor depth in metres at sensor resolution, invalid pixels filled from the
       nearest valid one (:func:`fill_invalid_nearest`); a constant prompt gets 0.1 mm added to one
       pixel (the model divides by max - min). The model scales its prediction to the prompt's
       [min, max] range itself.
    3. The predicted depth (network input size) is resized to the output size (RGB or depth, see
       ``output``) with bicubic interpolation (antialiased when shrinking), clipped to >= 0 and
       returned as float32 metres. Frames whose depth map has no valid pixel give all zeros.

    Frames are grouped by (RGB shape, depth shape) and run ``batch_size`` at a time; the model
    treats each frame of a batch independently (per-frame prompt normalisation, no batch
    statistics), so results do not depend on the batching.

    Attributes:
        options: the :class:`PromptDAOptions`.
        model_dir: the local folder the weights were loaded from.
        model: the loaded ``PromptDepthAnythingForDepthEstimation`` (eval mode).
        device: the torch device string in use.
    """

    name = "promptda"

    def __init__(self, model: str | Path | None = None, *, device: str = "cpu", batch_size: int = 4,
                 max_side: int = 1008, output: Literal["rgb", "depth"] = "rgb",
                 dtype: Literal["float32", "float16", "bfloat16"] = "float32", mask_invalid: bool = False,
                 offline: bool = False) -> None:
        from embodmocap.perception import hub

        model = hub.model_or_default(model, "depth")
        self.options = PromptDAOptions(str(model), device, batch_size, max_side, output, dtype, mask_invalid, offline)
        self._torch = require("torch", "perception")
        require("transformers", "perception")
        self.model_dir = hub.resolve_model_folder(model, "depth", offline=offline)
        self.device = _pick_device(self._torch, device)
        self._dtype = getattr(self._torch, dtype)
        self._rescale, self._mean, self._std = _read_normalisation(self.model_dir)
        self.model = _load_model(self.model_dir, self.device, self._dtype)
        n_params = sum(p.numel() for p in self.model.parameters())
        log.info("Prompt Depth Anything from %s on %s (%s, %.1f M parameters, max side %d, batch %d)",
                 self.model_dir, self.device, dtype, n_params / 1e6, max_side, batch_size)

    def refine(
        self, rgb_batch: Sequence[NDArray[np.uint8]], depth_batch: Sequence[NDArray[np.floating]]
    ) -> list[NDArray[np.float32]]:
        """Refined depth per frame (float32 metres, 0 = invalid), at the RGB or depth resolution."""
        _check_batch(rgb_batch, depth_batch)
        results: list[NDArray[np.float32] | None] = [None] * len(rgb_batch)
        groups: dict[tuple, list[int]] = {}
        for i, (rgb, depth) in enumerate(zip(rgb_batch, depth_batch)):
            groups.setdefault((np.shape(rgb), np.shape(depth)), []).append(i)
        bs = self.options.batch_size
        for idx in groups.values():
            for start in range(0, len(idx), bs):
                chunk = idx[start:start + bs]
                outs = self._run_chunk([rgb_batch[i] for i in chunk], [depth_batch[i] for i in chunk])
                for i, out in zip(chunk, outs):
                    results[i] = out
        return results  # type: ignore[return-value]

    # --------------------------------------------------------------------------------------------

    def _pixel_values(self, rgbs: Sequence[NDArray[np.uint8]]) -> NDArray[np.float32]:
        """(B, 3, h, w) normalised network input of same-shape RGB images."""
        H, W = rgbs[0].shape[:2]
        h, w = network_input_size(H, W, self.options.max_side)
        # INTER_AREA averages the pixels a target pixel covers (no aliasing when shrinking), as the
        # release does; for the rare enlargement by rounding it behaves like bilinear.
        resized = np.stack([rgb if (h, w) == (H, W) else cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
                            for rgb in rgbs])
        x = (resized.astype(np.float32) * self._rescale - self._mean) / self._std
        return np.ascontiguousarray(x.transpose(0, 3, 1, 2))

    @staticmethod
    def _prompts(depths: Sequence[NDArray[np.floating]]) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        """(B, 1, h, w) hole-filled prompts in metres and (B, h, w) sensor validity masks."""
        clean = np.stack([clean_depth(d) for d in depths])
        valid = clean > 0
        prompts = np.stack([fill_invalid_nearest(d) for d in clean])
        flat = prompts.reshape(len(prompts), -1)
        constant = flat.max(axis=1) - flat.min(axis=1) < _CONSTANT_PROMPT_BUMP_M
        flat[constant, 0] += _CONSTANT_PROMPT_BUMP_M
        return prompts[:, None], valid

    def _run_chunk(self, rgbs: Sequence[NDArray[np.uint8]],
                   depths: Sequence[NDArray[np.floating]]) -> list[NDArray[np.float32]]:
        """Refine same-shape frames in one forward pass."""
        torch = self._torch
        prompts, valid = self._prompts(depths)
        out_hw = rgbs[0].shape[:2] if self.options.output == "rgb" else valid.shape[1:]
        pixels = torch.from_numpy(self._pixel_values(rgbs)).to(self.device, self._dtype)
        prompt = torch.from_numpy(prompts).to(self.device, self._dtype)
        with torch.inference_mode():
            pred = self.model(pixel_values=pixels, prompt_depth=prompt).predicted_depth  # (B, h, w)
            pred = torch.nn.functional.interpolate(
                pred[:, None].float(), size=tuple(out_hw), mode="bicubic", align_corners=False, antialias=True
            )[:, 0]
            # Cubic overshoot at depth edges can dip below zero; negative depth means nothing.
            out = pred.clamp_(min=0.0).cpu().numpy().astype(np.float32, copy=False)
        has_depth = valid.reshape(len(valid), -1).any(axis=1)
        if not has_depth.all():
            log.warning("%d frame(s) have no valid sensor depth: their refined depth is left at 0",
                        int((~has_depth).sum()))
            out[~has_depth] = 0.0
        if self.options.mask_invalid:
            keep = np.stack([cv2.resize(v.astype(np.uint8), (out_hw[1], out_hw[0]), interpolation=cv2.INTER_NEAREST)
                             for v in valid]).astype(bool)
            out[~keep] = 0.0
        return list(out)


# ------------------------------------------------------------------------------------------------
# Factory


DEPTH_REFINERS: dict[str, type] = {"none": LidarDepth, "promptda": PromptDepthAnything}
"""Backend name -> class, as accepted by :func:`make_depth_refiner`."""


def make_depth_refiner(name: str, **options: Any) -> DepthRefiner:
    """The backend called ``name`` ("none" or "promptda") built with ``options``.

    "none" takes no options and ignores any given (a stage config may carry a model path while
    refinement is off); "promptda" takes the keyword arguments of :class:`PromptDepthAnything`.
    """
    key = name.strip().lower()
    if key not in DEPTH_REFINERS:
        raise ValueError(f"unknown depth refiner {name!r}; choose one of {sorted(DEPTH_REFINERS)}")
    if key == "none":
        if options:
            log.debug("depth refiner 'none' ignores options %s", sorted(options))
        return LidarDepth()
    return PromptDepthAnything(**options)
