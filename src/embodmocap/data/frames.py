"""``FrameDataset``: frames of a training export for monocular models (PyTorch).

    ds = FrameDataset("SESSION/training")                 # one frame per item
    clips = FrameDataset("SESSION/training", clip=16)     # 16 consecutive frames per item
    loader = torch.utils.data.DataLoader(ds, batch_size=32, shuffle=True, num_workers=4)

The folder is what ``embodmocap export SESSION --to training`` writes (``docs/training.md``). An
item reads only its own frames: one JPEG decode per frame (OpenCV), a slice of the memory-mapped
depth and mask stacks, rows of the view's labels (held in memory, a few KB per frame). Nothing is
decoded ahead and no video is opened, so random access costs the same as sequential access.
DataLoader workers each open their own memory maps (nothing unpicklable is held).

An item is a dict; with ``clip=N`` every per-frame entry gets a leading ``(N,)`` dimension:

================= ================= =====================================================
key               shape, dtype      meaning
================= ================= =====================================================
``rgb``           (3, H, W) uint8   the frame, RGB, channels first
``depth``         (h, w) float32    metric depth, metres, 0 = invalid (its own size, ``K_depth``)
``mask``          (H, W) bool       the performer's mask (when the export has masks)
``K``             (3, 3) float32    RGB intrinsics, pixels
``K_depth``       (3, 3) float32    depth intrinsics, pixels of the depth map
``T_world_cam``   (4, 4) float32    camera-to-world (Z-up metric world, OpenCV camera)
``global_orient`` (3,) float32      SMPL root rotation, camera frame (axis-angle)
``body_pose``     (69,) float32     SMPL joints 1..23 (axis-angle)
``betas``         (B,) float32      SMPL shape
``transl``        (3,) float32      SMPL ``transl``, camera frame (pelvis at ``J_0(betas) + transl``)
``joints_cam``    (24, 3) float32   the fitted body's SMPL joints, camera frame, metres
``keypoints``     (17, 3) float32   detected COCO-17 keypoints: pixels x, y and confidence
``keypoints_fit`` (17, 2) float32   the fitted body's COCO-17 keypoints projected with ``K``
``valid``         () bool           all three flags below
``smpl_valid``    () bool           Stage IV placed the body at this instant
``in_sync``       () bool           inside the span both views recorded, not a dropped frame
``depth_present`` () bool           the depth map has valid pixels
``frame``         () int64          sequence frame
``sequence``, ``view`` str
================= ================= =====================================================
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable

import numpy as np
import torch
from torch.utils.data import Dataset

from embodmocap.errors import InputError

#: labels.npz keys returned per frame, and their dtype in the item.
_PER_FRAME = {"T_world_cam": np.float32, "global_orient": np.float32, "body_pose": np.float32, "transl": np.float32,
              "joints_cam": np.float32, "keypoints": np.float32, "keypoints_fit": np.float32, "valid": bool,
              "smpl_valid": bool, "in_sync": bool, "depth_present": bool, "frames": np.int64}
_REQUIRED = tuple(_PER_FRAME) + ("K", "K_depth", "betas", "width", "height")


@dataclass(frozen=True)
class _View:
    """One exported view: its folder and labels (small arrays, pickled to the workers)."""

    sequence: str
    view: str
    path: str
    width: int
    height: int
    masks: bool
    labels: dict


class FrameDataset(Dataset):
    """Frames (or clips of consecutive frames) of a training export; see the module docstring.

    Args:
        root: the export folder (holds ``manifest.json``).
        clip: None = one frame per item; N = N consecutive frames of one view per item.
        stride: frames between the starts of consecutive clips (default: ``clip``, no overlap).
        sequences, views: keep only these (None = all).
        require_valid: keep only frames (clips whose every frame is) flagged ``valid``.
        load_rgb, load_depth, load_mask: leave out what a model does not need (saves the decode).

    Raises:
        InputError: ``root`` is missing or not a training export, or a view's files are missing.
    """

    def __init__(self, root: str | Path, clip: int | None = None, stride: int | None = None, *,
                 sequences: Iterable[str] | None = None, views: Iterable[str] | None = None,
                 require_valid: bool = True, load_rgb: bool = True, load_depth: bool = True,
                 load_mask: bool = True) -> None:
        from embodmocap.export.training import read_training_index

        if clip is not None and clip < 1:
            raise ValueError("clip must be None or >= 1")
        if stride is not None and stride < 1:
            raise ValueError("stride must be >= 1")
        self.root = Path(root)
        self.index_file = read_training_index(self.root)
        self.clip = clip
        self.load_rgb, self.load_depth, self.load_mask = load_rgb, load_depth, load_mask
        seqs = None if sequences is None else set(sequences)
        vws = None if views is None else set(views)
        self.views: list[_View] = []
        for entry in self.index_file["views"]:
            if (seqs is not None and entry["sequence"] not in seqs) or (vws is not None and entry["view"] not in vws):
                continue
            self.views.append(self._read_view(entry))
        n = clip or 1
        step = stride or n
        self.items: list[tuple[int, int]] = []  # (view, first frame row)
        for i, v in enumerate(self.views):
            ok = v.labels["valid"] if require_valid else np.ones(len(v.labels["valid"]), bool)
            # A clip's frames must be consecutive sequence frames (rows are frames 0..T-1 of the view).
            good = np.convolve(ok.astype(np.int64), np.ones(n, np.int64), mode="valid") == n if len(ok) >= n \
                else np.zeros(0, bool)
            starts = np.arange(0, len(good), step if clip is not None else 1)
            self.items += [(i, int(s)) for s in starts if good[s]]
        self._open: dict[str, Any] = {}

    def _read_view(self, entry: dict) -> _View:
        path = self.root / str(entry["path"])
        lab_path = path / "labels.npz"
        try:
            with np.load(lab_path, allow_pickle=False) as z:
                labels = {k: z[k] for k in z.files}
        except (OSError, ValueError) as err:
            raise InputError(lab_path, f"unreadable labels ({err})", "export the session again") from err
        missing = [k for k in _REQUIRED if k not in labels]
        if missing:
            raise InputError(lab_path, f"keys {missing} missing", "export the session again with this version")
        T = len(labels["valid"])
        n_rgb = sum(1 for _ in (path / "rgb").glob("*.jpg"))
        if n_rgb != T:
            raise InputError(path / "rgb", f"{n_rgb} JPEG frames, labels.npz has {T}", "export the session again")
        return _View(str(entry["sequence"]), str(entry["view"]), str(path), int(labels["width"]), int(labels["height"]),
                     bool(entry.get("masks")) and (path / "masks.npy").is_file(), labels)

    # DataLoader workers open their own memory maps.
    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_open"] = {}
        return state

    def __len__(self) -> int:
        return len(self.items)

    def _stack(self, view: _View, name: str) -> np.ndarray:
        key = f"{view.path}/{name}"
        arr = self._open.get(key)
        if arr is None:
            arr = self._open[key] = np.load(Path(view.path) / name, mmap_mode="r")
        return arr

    def _rgb(self, view: _View, t: int) -> np.ndarray:
        import cv2

        from embodmocap.export.training import rgb_name

        path = Path(view.path) / "rgb" / rgb_name(t)
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise InputError(path, "missing or unreadable JPEG frame", "export the session again")
        # BGR -> RGB and HWC -> CHW in one copy.
        return np.ascontiguousarray(bgr[:, :, ::-1].transpose(2, 0, 1))

    def frame_item(self, view_index: int, rows: np.ndarray) -> dict[str, Any]:
        """The entries of frames ``rows`` (N,) of view ``view_index``, each with a leading (N,)."""
        v = self.views[view_index]
        lab = v.labels
        item: dict[str, Any] = {k: torch.from_numpy(np.ascontiguousarray(lab[k][rows]).astype(dt))
                                for k, dt in _PER_FRAME.items()}
        item["frame"] = item.pop("frames")
        n = len(rows)
        for k in ("K", "K_depth"):
            item[k] = torch.from_numpy(np.repeat(lab[k][None].astype(np.float32), n, axis=0))
        item["betas"] = torch.from_numpy(np.repeat(lab["betas"][None].astype(np.float32), n, axis=0))
        if self.load_rgb:
            imgs = [self._rgb(v, int(t)) for t in rows]
            # One frame: a view with a leading axis, not a copy (the collate copies once anyway).
            item["rgb"] = torch.from_numpy(imgs[0][None] if len(imgs) == 1 else np.stack(imgs))
        if self.load_depth:
            # One slice of the memory map; rows are consecutive in clip mode.
            d = np.asarray(self._stack(v, "depth.npy")[rows[0]:rows[-1] + 1] if _consecutive(rows)
                           else self._stack(v, "depth.npy")[rows])
            item["depth"] = torch.from_numpy(d.astype(np.float32) / 1000.0)
        if self.load_mask and v.masks:
            packed = np.asarray(self._stack(v, "masks.npy")[rows[0]:rows[-1] + 1] if _consecutive(rows)
                                else self._stack(v, "masks.npy")[rows])
            item["mask"] = torch.from_numpy(np.unpackbits(packed, axis=-1, count=v.width).astype(bool))
        return item

    def __getitem__(self, i: int) -> dict[str, Any]:
        view_index, start = self.items[i]
        v = self.views[view_index]
        n = self.clip or 1
        item = self.frame_item(view_index, np.arange(start, start + n))
        if self.clip is None:
            item = {k: t[0] for k, t in item.items()}
        item["sequence"], item["view"] = v.sequence, v.view
        return item


def _consecutive(rows: np.ndarray) -> bool:
    return len(rows) > 0 and bool(np.all(np.diff(rows) == 1))
