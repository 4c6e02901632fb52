"""SAM 2 video masks through ``transformers`` (the ``"sam2"`` MaskSegmenter backend).

Real video propagation, on the CPU or a GPU, without torchvision: the backend drives
``Sam2VideoModel`` with a streaming ``Sam2VideoInferenceSession`` itself (the ``Sam2VideoProcessor``
would need torchvision), one frame at a time in time order, so the model's memory bank carries the
performer from frame to frame.

- Pre-processing: each frame is stretched to the model's square input (``config.image_size``,
  1024 for the released models) and normalised ``(rgb * rescale - mean) / std`` (ImageNet's
  unless the folder's ``preprocessor_config.json`` / ``video_preprocessor_config.json`` says
  otherwise).
- Prompts: the performer's box ``x1, y1, x2, y2`` (pixels) is given to SAM 2 as its two corner
  points (labels 2 and 3) scaled to the input square (``x * S / W``, ``y * S / H``). The first
  frame with a known box is prompted; a frame whose box is known again after ``reprompt_after``
  or more frames without one is prompted again (the person may have left and come back). Frames
  before the first prompt get empty masks; later frames without a box are propagated from memory.
- Post-processing: the low-resolution mask logits (S/4 square) are resized bilinearly to the
  image size and thresholded (``> mask_threshold``, 0 = probability 1/2). When SAM 2 judges the
  object absent (object score <= 0) the model itself sets the logits to -1024: an empty mask.
- Memory: the session keeps only what the model can still look at (the current frame's pixels,
  the last ``max(num_maskmem, max_object_pointers_in_encoder)`` tracked frames, the prompted
  frames), so it does not grow with the video's length.

Chunks: ``segment`` may be called on consecutive chunks of one video; a call whose first frame id
is not after the previous call's last one, or whose image size differs, starts a new video.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import require
from embodmocap.perception import hf_backends as hf
from embodmocap.perception import hub

log = logging.getLogger(__name__)

_CLASSES = {"sam2_video": "Sam2VideoModel", "sam2": "Sam2VideoModel"}
_EXAMPLE = hub.DEFAULT_MODELS["masks"]
_OBJ_ID = 1
"""The performer's object id in the SAM 2 session (one object per view)."""


def box_prompt(box: NDArray[np.floating], image_hw: tuple[int, int], side: int) -> NDArray[np.float32]:
    """(2, 2) corner points ``[[x1, y1], [x2, y2]]`` of a pixel box scaled to the ``side`` square input."""
    h, w = image_hw
    b = np.asarray(box, dtype=np.float64)[:4].reshape(2, 2)
    return (b * np.array([side / w, side / h])).astype(np.float32)


def upsample_mask_logits(torch, logits, image_hw: tuple[int, int], threshold: float = 0.0) -> NDArray[np.bool_]:
    """(h, w) mask logits (torch tensor) -> (H, W) bool mask: bilinear resize, then ``> threshold``."""
    x = logits.reshape(1, 1, *logits.shape[-2:]).float()
    up = torch.nn.functional.interpolate(x, size=tuple(image_hw), mode="bilinear", align_corners=False)
    return (up[0, 0] > threshold).cpu().numpy()


class Sam2VideoMasks:
    """The ``"sam2"`` backend: the performer's mask through a video with SAM 2.

    Args:
        model: local folder written by ``save_pretrained``, or a hub id (cached, else downloaded
            into the Hugging Face cache); None or "" = the default ``facebook/sam2.1-hiera-tiny``; a SAM 2 video (or image) checkpoint.
        device: "cpu", "cuda", "cuda:N" or "auto"; an unavailable CUDA falls back to the CPU.
        mask_threshold: logit above which a pixel is the person (0 = probability 1/2).
        reprompt_after: prompt again with the box when it is known after at least this many
            consecutive frames without one (>= 1).
        dtype: "float32", "float16" or "bfloat16".
        offline: never download (the model must be a folder or in the cache); HF_HUB_OFFLINE=1 does the same.

    Attributes:
        model_dir, model, device, input_side (the square input's side in pixels),
        prompted_frames (frame ids prompted with a box in the current video, in order).
    """

    name = "sam2"

    def __init__(self, model: str | Path | None = None, device: str = "cpu", mask_threshold: float = 0.0,
                 reprompt_after: int = 1, dtype: str = "float32", offline: bool = False) -> None:
        if reprompt_after < 1:
            raise ValueError(f"reprompt_after must be >= 1, got {reprompt_after}")
        self._torch = require("torch", "perception")
        self._transformers = require("transformers", "perception")
        self.mask_threshold, self.reprompt_after = float(mask_threshold), int(reprompt_after)
        self.model_dir = hub.resolve_model_folder(model, "masks", offline=offline)
        self.device = hf.pick_device(self._torch, device, "SAM 2")
        self._dtype = hf.torch_dtype(self._torch, dtype)
        self.model = hf.load_model(self.model_dir, _CLASSES, self.device, self._dtype,
                                   f"pass a SAM 2 model (e.g. {_EXAMPLE})")
        cfg = hf.read_preprocessor_config(self.model_dir, ("preprocessor_config.json", "video_preprocessor_config.json"))
        side = np.broadcast_to(np.asarray(self.model.config.image_size), (2,))
        self.input_side = int(side[0])
        self._rescale, self._mean, self._std = hf.normalisation(cfg, normalize_default=True)
        cfg_m = self.model.config
        # Tracked frames the model can still read: memory frames and object pointers reach back
        # this far; anything older is dropped so memory stays flat over long videos.
        self._keep = max(int(cfg_m.num_maskmem), int(cfg_m.max_object_pointers_in_encoder)) + 1
        self.reset()
        log.info("SAM 2 from %s on %s (input %d px)", self.model_dir, self.device, self.input_side)

    def reset(self) -> None:
        """Forget the current video (the next call starts a new one)."""
        self._session = None
        self._image_hw: tuple[int, int] | None = None
        self._last_id: int | None = None
        self._idx = 0  # session frame index of the next frame
        self._unseen_run = 0  # consecutive frames without a box just before the next frame
        self.prompted_frames: list[int] = []

    def segment(self, frames: Sequence[NDArray[np.uint8]], frame_ids: Sequence[int],
                boxes: NDArray[np.float64]) -> list[NDArray[np.bool_]]:
        """Per frame, the (H, W) mask of the person in ``boxes[i]`` ((T, 4); NaN rows = not seen)."""
        hf.check_frames(frames, frame_ids)
        boxes = np.asarray(boxes, dtype=np.float64)
        if boxes.ndim != 2 or boxes.shape[1] < 4 or len(boxes) != len(frames):
            raise ValueError(f"boxes must be ({len(frames)}, 4), got {boxes.shape}")
        boxes = boxes[:, :4]
        if not frames:
            return []
        hw = tuple(np.shape(frames[0])[:2])
        if self._session is None or self._image_hw != hw or (self._last_id is not None and frame_ids[0] <= self._last_id):
            self._start_video(hw)
        masks = []
        for frame, fid, box in zip(frames, frame_ids, boxes):
            if np.shape(frame)[:2] != hw:
                raise ValueError(f"frame {fid}: size {np.shape(frame)[:2]} differs from the video's {hw}")
            masks.append(self._step(frame, int(fid), box))
        return masks

    # --------------------------------------------------------------------------------------------

    def _start_video(self, hw: tuple[int, int]) -> None:
        self.reset()
        self._image_hw = hw
        self._session = self._transformers.Sam2VideoInferenceSession(
            video_height=hw[0], video_width=hw[1], inference_device=self.device,
            inference_state_device=self.device, video_storage_device=self.device, dtype=self._dtype,
        )

    def _pixel_values(self, frame: NDArray[np.uint8]):
        """(1, 3, S, S) normalised network input of one frame (a torch tensor on the device)."""
        side = (self.input_side, self.input_side)
        x = hf.pixel_values(hf.resize_rgb(np.asarray(frame), side)[None], self._rescale, self._mean, self._std)
        return self._torch.from_numpy(x).to(self.device, self._dtype)

    def _step(self, frame: NDArray[np.uint8], frame_id: int, box: NDArray[np.float64]) -> NDArray[np.bool_]:
        """The mask of one frame: prompt it, propagate to it, or (before any prompt) an empty mask."""
        torch, session = self._torch, self._session
        known = bool(np.isfinite(box).all() and box[2] > box[0] and box[3] > box[1])
        prompt = known and (not self.prompted_frames or self._unseen_run >= self.reprompt_after)
        self._unseen_run = 0 if known else self._unseen_run + 1
        self._last_id = frame_id
        if not prompt and not self.prompted_frames:
            return np.zeros(self._image_hw, dtype=bool)
        idx = self._idx
        self._idx += 1
        if prompt:
            points = torch.from_numpy(box_prompt(box, self._image_hw, self.input_side)).reshape(1, 1, 2, 2)
            labels = torch.tensor([[[2, 3]]], dtype=torch.int32)  # 2/3 = top-left / bottom-right box corner
            obj_idx = session.obj_id_to_idx(_OBJ_ID)
            session.add_point_inputs(obj_idx, idx, {"point_coords": points, "point_labels": labels})
            session.remove_mask_inputs(obj_idx, idx)
            session.obj_with_new_inputs = [_OBJ_ID]
            self.prompted_frames.append(frame_id)
        with torch.inference_mode():
            out = self.model(inference_session=session, frame_idx=idx, frame=self._pixel_values(frame))
        mask = upsample_mask_logits(torch, out.pred_masks[0, 0], self._image_hw, self.mask_threshold)
        self._prune(idx)
        return mask

    def _prune(self, idx: int) -> None:
        """Drop session state the model will not read again (see the module docstring, Memory)."""
        session = self._session
        for old in [k for k in session.processed_frames if k < idx]:
            del session.processed_frames[old]
        oldest = idx - self._keep
        for obj_idx in range(session.get_obj_num()):
            tracked = session.output_dict_per_obj[obj_idx]["non_cond_frame_outputs"]
            for old in [k for k in tracked if k < oldest]:
                del tracked[old]
            seen = session.frames_tracked_per_obj[obj_idx]
            for old in [k for k in seen if k < oldest]:
                del seen[old]
