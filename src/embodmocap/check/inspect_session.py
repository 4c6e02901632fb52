"""``embodmocap inspect SESSION``: check everything the stages will read, cheaply, all at once.

Beyond the captures (``inspect_capture``): every precomputed perception file (keypoint JSON parsed
with the bounded reader, mask and depth images by their headers, the body prior loaded), the body
model file loaded, and the session folder writable. Each check returns problem lines; nothing
stops at the first problem.
"""

from __future__ import annotations

import struct
from pathlib import Path

from embodmocap.errors import EmbodMocapError

#: At most this many problems are listed per folder (then a count of the others).
MAX_PER_FOLDER = 5

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_JPEG_SIGNATURE = b"\xff\xd8\xff"


def image_header_problem(path: Path) -> str | None:
    """None when ``path`` starts like a PNG (with a sane IHDR) or a JPEG; else what is wrong."""
    try:
        with open(path, "rb") as f:
            head = f.read(33)
    except OSError as err:
        return f"cannot be read ({err.strerror})"
    if not head:
        return "empty file (0 bytes)"
    if head.startswith(_PNG_SIGNATURE):
        if len(head) < 33 or head[12:16] != b"IHDR":
            return "truncated PNG header"
        w, h = struct.unpack(">II", head[16:24])
        return None if w > 0 and h > 0 else f"PNG header says {w}x{h} pixels"
    if head.startswith(_JPEG_SIGNATURE):
        return None
    return "not a PNG or JPEG image"


def _folder_lines(folder: Path, bad: list[str], what: str) -> list[str]:
    out = bad[:MAX_PER_FOLDER]
    if len(bad) > MAX_PER_FOLDER:
        out.append(f"{folder}: {len(bad) - MAX_PER_FOLDER} more {what} with problems")
    return out


def keypoint_problems(folder: Path) -> list[str]:
    """Every keypoint file of a view parsed (OpenPose per-frame JSON, or one COCO file)."""
    from embodmocap.io.openpose import keypoint_files, read_coco_keypoints, read_openpose_raw
    from embodmocap.perception.precomputed import looks_like_coco

    folder = Path(folder)
    if not folder.is_dir():
        return [] if not folder.is_file() else _one(lambda: read_coco_keypoints(folder))
    jsons = sorted(p for p in folder.iterdir() if p.suffix.lower() == ".json")
    try:
        if len(jsons) == 1 and looks_like_coco(jsons[0]):
            return _one(lambda: read_coco_keypoints(jsons[0]))
        files = keypoint_files(folder)
    except EmbodMocapError as err:
        return [str(err)]
    if not files:
        return [f"{folder}: no keypoint files (*_keypoints.json) found"]
    bad = []
    for path in files.values():
        bad += _one(lambda p=path: read_openpose_raw(p))
    return _folder_lines(folder, bad, "keypoint files")


def _one(fn) -> list[str]:
    try:
        fn()
    except EmbodMocapError as err:
        return [str(err)]
    return []


def image_folder_problems(folder: Path, what: str) -> list[str]:
    """Every image of a mask or depth folder checked by its header."""
    folder = Path(folder)
    if not folder.is_dir():
        return [f"{folder}: {what} folder not found"]
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    if not files:
        return [f"{folder}: no {what} images found"]
    bad = [f"{p}: {msg} ({what} image; re-export it)" for p in files if (msg := image_header_problem(p))]
    return _folder_lines(folder, bad, f"{what} images")


def body_prior_problems(path: Path) -> list[str]:
    from embodmocap.perception.precomputed import PrecomputedBodyPrior

    path = Path(path)
    if not path.is_file():
        return [f"{path}: body prior file not found"]
    return _one(lambda: PrecomputedBodyPrior(path))


def body_model_problems(path: Path | None) -> list[str]:
    """The body model file loaded and checked as Stage IV will load it."""
    if path is None or not Path(path).is_file():
        return []  # the generated test model, or a missing file the manifest check reports
    from embodmocap.body.pkl import load_model_arrays

    try:
        load_model_arrays(path)
    except EmbodMocapError as err:
        return [str(err)]
    except (OSError, ValueError, EOFError, MemoryError) as err:
        return [f"{path}: cannot be loaded as a body model ({type(err).__name__}: {err})"]
    return []


def writable_problems(root: Path) -> list[str]:
    from embodmocap.io.preflight import check_writable, output_folders

    out = []
    for folder in output_folders(root):
        try:
            check_writable(folder, "session folder" if folder == Path(root) else "output folder")
        except EmbodMocapError as err:
            out.append(str(err))
    return out


def view_perception_problems(view) -> list[str]:
    """Problems of one view's precomputed perception (a manifest ``ViewEntry``)."""
    out: list[str] = []
    if view.keypoints is not None and Path(view.keypoints).exists():
        out += keypoint_problems(Path(view.keypoints))
    if view.masks is not None and Path(view.masks).exists():
        out += image_folder_problems(Path(view.masks), "mask")
    if view.depth is not None and Path(view.depth).exists():
        out += image_folder_problems(Path(view.depth), "depth")
    if view.body_prior is not None and Path(view.body_prior).exists():
        out += body_prior_problems(Path(view.body_prior))
    return out
