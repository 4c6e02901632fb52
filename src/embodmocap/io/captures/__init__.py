"""Capture readers and writers, one module per phone app format.

:func:`open_capture` detects the format from the files present and returns a
:class:`~embodmocap.types.Capture` in the package's conventions (Z-up metric world, OpenCV cameras).
"""

from __future__ import annotations

from pathlib import Path

from embodmocap.errors import InputError
from embodmocap.io.captures.common import CaptureScan, depth_to_rgb_scale, read_depth_image
from embodmocap.io.captures.record3d import is_record3d, read_record3d, scan_record3d, write_record3d
from embodmocap.io.captures.spectacular import (
    SpectacularWriter, is_spectacular, read_spectacular, read_transforms_json, scan_spectacular,
    write_transforms_json,
)
from embodmocap.io.captures.strayscanner import StrayScannerWriter, is_strayscanner, read_strayscanner, scan_strayscanner
from embodmocap.types import Capture

__all__ = [
    "open_capture", "detect_format", "scan_capture", "read_strayscanner", "read_spectacular", "read_record3d",
    "StrayScannerWriter", "SpectacularWriter", "write_record3d", "read_transforms_json",
    "write_transforms_json", "read_depth_image", "depth_to_rgb_scale", "FORMATS", "LAYOUTS", "closest_layout",
]

#: What each format needs, for the error message when nothing matches.
FORMATS: dict[str, str] = {
    "strayscanner": "rgb.mp4 + odometry.csv (or depth/)",
    "spectacular": "data.jsonl + calibration.json (+ data.mov, frames2/, cameras_sai.jsonl)",
    "record3d": "a .r3d file, a folder with metadata + rgbd/, or metadata.json + rgb/ + depth/ (EXR + JPG export)",
}

#: The files and folders (trailing "/") each known export layout holds, to tell a user which
#: layout an unknown folder is closest to and what it lacks.
LAYOUTS: dict[str, tuple[str, ...]] = {
    "Stray Scanner export": ("rgb.mp4", "odometry.csv", "camera_matrix.csv", "depth/", "confidence/", "imu.csv"),
    "Spectacular AI recording": ("data.jsonl", "calibration.json", "data.mov", "frames2/", "metadata.json",
                                 "cameras_sai.jsonl"),
    "Spectacular AI SDK recording": ("data.jsonl", "calibration.json", "data.mp4", "vio_config.yaml", "frames2/",
                                     "cameras_sai.jsonl"),
    "Record3D export folder (unzipped .r3d)": ("metadata", "rgbd/"),
    "Record3D EXR + JPG export": ("metadata.json", "rgb/", "depth/"),
}

_DETECT = (("spectacular", is_spectacular), ("strayscanner", is_strayscanner), ("record3d", is_record3d))
_READ = {"strayscanner": read_strayscanner, "spectacular": read_spectacular, "record3d": read_record3d}
_SCAN = {"strayscanner": scan_strayscanner, "spectacular": scan_spectacular, "record3d": scan_record3d}


def detect_format(path: str | Path) -> str | None:
    """The capture format of ``path`` (``"strayscanner"``, ``"spectacular"``, ``"record3d"``) or None."""
    path = Path(path)
    for name, test in _DETECT:
        if test(path):
            return name
    return None


def _has(path: Path, item: str) -> bool:
    return (path / item[:-1]).is_dir() if item.endswith("/") else (path / item).is_file()


def closest_layout(path: str | Path) -> str:
    """For a folder of no known format: which known layout it is closest to and what it lacks,
    in words (e.g. "closest to a Stray Scanner export: has odometry.csv, depth/; lacks rgb.mp4, ...")."""
    path = Path(path)
    if path.is_file() and path.suffix.lower() == ".zip":
        return "a zip archive: unzip it (the Spectacular Rec app zips its recordings) and point to the folder"
    if not path.is_dir():
        return "not a folder, nor a .r3d file"
    # Share of each layout's items present; ties go to the layout with more items found.
    score = {name: (sum(_has(path, i) for i in items) / len(items), sum(_has(path, i) for i in items))
             for name, items in LAYOUTS.items()}
    name = max(score, key=lambda n: score[n])
    if score[name][1] == 0:
        return "holds none of the files of a known layout (" + "; ".join(
            f"{n}: {', '.join(items)}" for n, items in LAYOUTS.items()) + ")"
    has = [i for i in LAYOUTS[name] if _has(path, i)]
    lacks = [i for i in LAYOUTS[name] if not _has(path, i)]
    return f"closest to a {name}: has {', '.join(has)}; lacks {', '.join(lacks)}"


def _require_format(path: Path) -> str:
    fmt = detect_format(path)
    if fmt is None:
        what = "does not exist" if not path.exists() else f"is not a capture of a known format ({closest_layout(path)})"
        raise InputError(path, what, "point to the folder the phone app exported, with every file it wrote")
    return fmt


def open_capture(path: str | Path) -> Capture:
    """Read any supported capture (format detected from its files).

    Raises:
        InputError: the format is not recognised (the message lists what each format needs), or
            the reader found a problem.
    """
    path = Path(path)
    return _READ[_require_format(path)](path)


def scan_capture(path: str | Path, thorough: bool = True) -> CaptureScan:
    """Scan any supported capture, collecting every problem (for ``embodmocap inspect``)."""
    path = Path(path)
    return _SCAN[_require_format(path)](path, thorough=thorough)
