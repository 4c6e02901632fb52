"""Record3D exports (iOS app): an export folder or a ``.r3d`` file (a zip of the same files).

Layout (see docs/formats.md)::

    metadata        JSON: K (9 floats, column-major 3x3 at w x h), w, h (RGB size), fps, poses
                    ([qx, qy, qz, qw, px, py, pz] per frame); newer apps add dw, dh (depth size)
                    and frameTimestamps (s); older apps add initPose instead (below)
    rgbd/N.jpg      RGB frame N (N = 0, 1, ...; not zero-padded)
    rgbd/N.depth    LZFSE-compressed float32 depth in metres, dh x dw
    rgbd/N.conf     LZFSE-compressed uint8 confidence 0/1/2, dh x dw (optional)

Poses are ARKit camera-to-world: Y-up world, ARKit/OpenGL camera axes (x right, y up, z backward),
as Nerfstudio's Record3D importer also uses them. Converted once here:
``T_world_cam = gl_to_cv_cam(T_zup_yup @ T_yup_glcam)``. LZFSE needs the ``record3d`` extra.

Older app versions (2022-2023) write poses relative to the first camera (``poses[0]`` is the
identity) and the first camera in ARKit's gravity-aligned world as ``initPose`` (same 7 numbers):
the world pose of frame i is ``initPose * poses[i]``. Without that the world is tilted, so an
export whose first pose is the identity and that has no ``initPose`` is refused. Their metadata
also lacks ``dw``/``dh`` (the depth size is then found from the first depth frame) and
``frameTimestamps`` (times are then ``i / fps``).

The "EXR + JPG" export (``metadata.json``, ``rgb/N.jpg``, ``depth/N.exr``) shares the metadata and
is read by :mod:`embodmocap.io.captures.record3d_exr`.
"""

from __future__ import annotations

import io
import json
import logging
import re
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError, require
from embodmocap.geometry.transforms import T_zup_from_yup, gl_to_cv_cam, invert_T, make_T, matrix_to_quat, quat_to_matrix
from embodmocap.io.atomic import atomic_path
from embodmocap.io.captures.common import CaptureScan, LazyFrames, Problem, capture_from_scan, intrinsics_problems, pose_problems
from embodmocap.types import Capture, CameraTrajectory, Intrinsics

log = logging.getLogger(__name__)

FORMAT = "record3d"
_RGB_NAME = re.compile(r"^rgbd/(\d+)\.jpg$")
#: A first pose within this of the identity (rotation angle in radians, translation in metres)
#: marks poses relative to the first camera (older app versions).
IDENTITY_TOL = 1e-6
#: Depth sizes (width, height) the app writes, tried when the metadata does not give one.
LIDAR_SIZES = ((256, 192), (192, 256), (320, 240), (240, 320), (640, 480), (480, 640))


class _Store:
    """Read-only access to the export's files, in a folder or inside a .r3d zip."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._zip: zipfile.ZipFile | None = None
        if path.is_file():
            try:
                self._zip = zipfile.ZipFile(path)
            except zipfile.BadZipFile as err:
                raise InputError(path, f"not a valid .r3d (zip) file ({err})", "export the recording again") from err
            self._names = set(self._zip.namelist())
        else:
            self._names = {p.relative_to(path).as_posix() for p in path.rglob("*") if p.is_file()}

    def where(self, name: str) -> Path:
        """A path naming the member, for messages (inside the zip: archive path / member)."""
        return self.path / name

    def exists(self, name: str) -> bool:
        return name in self._names

    def names(self) -> set[str]:
        return self._names

    def read(self, name: str) -> bytes:
        if name not in self._names:
            raise InputError(self.where(name), "file missing from the export", "export the recording again")
        try:
            if self._zip is not None:
                return self._zip.read(name)
            return (self.path / name).read_bytes()
        except (OSError, zipfile.BadZipFile, EOFError) as err:
            raise InputError(self.where(name), f"unreadable ({err})", "export the recording again") from err


def is_record3d(path: Path) -> bool:
    """True if ``path`` is a ``.r3d`` file, a folder with ``metadata`` and ``rgbd/`` (unzipped .r3d)
    or a folder with ``metadata.json`` and ``rgb/`` (the EXR + JPG export)."""
    if path.is_file():
        return path.suffix.lower() == ".r3d"
    if not path.is_dir():
        return False
    has_meta = (path / "metadata").is_file() or (path / "metadata.json").is_file()
    return has_meta and ((path / "rgbd").is_dir() or (path / "rgb").is_dir())


def read_record3d(path: str | Path) -> Capture:
    """Read a Record3D export folder or ``.r3d`` file into a :class:`Capture`.

    Raises:
        InputError: on the first problem found, naming the file and what to do.
    """
    return capture_from_scan(scan_record3d(path))


def _decompress(data: bytes, where: Path) -> bytes:
    lzfse = require("lzfse", "record3d")
    try:
        return lzfse.decompress(data)
    except Exception as err:  # noqa: BLE001 - the binding raises its own error type
        raise InputError(where, f"LZFSE data is corrupt ({err})", "export the recording again") from err


def _decode_lzfse(data: bytes, dtype, shape: tuple[int, int], where: Path) -> NDArray:
    raw = _decompress(data, where)
    arr = np.frombuffer(raw, dtype=dtype)
    if arr.size != shape[0] * shape[1]:
        raise InputError(where, f"holds {arr.size} values, expected {shape[1]}x{shape[0]} = {shape[0] * shape[1]}",
                         "dw/dh in metadata do not match the depth frames")
    return arr.reshape(shape)


def _decode_jpeg(data: bytes, where: Path) -> NDArray[np.uint8]:
    import cv2

    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if bgr is None:
        raise InputError(where, "unreadable JPEG", "export the recording again")
    return np.ascontiguousarray(bgr[..., ::-1])


@dataclass(frozen=True)
class Record3dMetadata:
    """The export's ``metadata`` / ``metadata.json``, in every app version's form.

    Attributes:
        w, h: RGB size the intrinsics are for.
        K3: (3, 3) intrinsics at w x h.
        fps: frame rate.
        poses: (N, 7) [qx, qy, qz, qw, px, py, pz] ARKit camera-to-world (or relative to the first
            camera, see ``init_pose``).
        depth_size: (dw, dh), or None when the metadata does not say (older apps).
        frame_timestamps: (N,) seconds, or None (older apps).
        init_pose: (7,) the first camera in ARKit's world when present (older apps), else None.
    """

    w: int
    h: int
    K3: NDArray[np.float64]
    fps: float
    poses: NDArray[np.float64]
    depth_size: tuple[int, int] | None
    frame_timestamps: NDArray[np.float64] | None
    init_pose: NDArray[np.float64] | None


def parse_metadata(data: bytes, where: Path) -> Record3dMetadata:
    """Parse the metadata JSON; raises one :class:`InputError` naming what is malformed."""
    try:
        meta = json.loads(data)
        w, h = int(meta["w"]), int(meta["h"])
        fps = float(meta.get("fps", 0) or 0)
        K3 = np.asarray(meta["K"], dtype=np.float64).reshape(3, 3).T  # stored column-major
        poses = np.asarray(meta.get("poses", []), dtype=np.float64).reshape(-1, 7)
        dsize = (int(meta["dw"]), int(meta["dh"])) if "dw" in meta and "dh" in meta else None
        stamps = np.asarray(meta["frameTimestamps"], dtype=np.float64).reshape(-1) if "frameTimestamps" in meta else None
        init = np.asarray(meta["initPose"], dtype=np.float64).reshape(7) if meta.get("initPose") is not None else None
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, ValueError) as err:
        raise InputError(where, f"malformed metadata ({err.__class__.__name__}: {err})",
                         "expected JSON with K, w, h, fps and poses (Record3D writes it with every export)") from err
    if fps <= 0 and stamps is None:
        raise InputError(where, "metadata has neither fps nor frameTimestamps", "export the recording again")
    if fps <= 0:  # only frame times: the rate is their median step
        steps = np.diff(stamps) if stamps is not None else np.zeros(0)
        steps = steps[steps > 0]
        if not len(steps):
            raise InputError(where, "metadata has no fps and its frameTimestamps do not increase",
                             "export the recording again")
        fps = 1.0 / float(np.median(steps))
    return Record3dMetadata(w, h, K3, fps, poses, dsize, stamps, init)


def world_poses(meta: Record3dMetadata, where: Path) -> tuple[NDArray[np.float64], str, list[Problem]]:
    """(T_world_cam (N, 4, 4) in the package convention, a note on the pose form, problems).

    Poses relative to the first camera (``poses[0]`` the identity) are put in ARKit's world with
    ``initPose``; without one they are refused, since their world is not gravity-aligned.
    """
    T_pose = make_T(quat_to_matrix(meta.poses[:, :4], invalid="nan"), meta.poses[:, 4:])
    problems: list[Problem] = []
    note = "poses in ARKit's world"
    if len(T_pose) and _is_identity(T_pose[0]):
        if meta.init_pose is not None:
            T_init = make_T(quat_to_matrix(meta.init_pose[:4], invalid="nan"), meta.init_pose[4:])
            T_pose = T_init @ T_pose
            note = "poses relative to the first camera, put in ARKit's world with initPose"
        else:
            note = "poses relative to the first camera, no initPose"
            problems.append(Problem(where, "poses are relative to the first camera (poses[0] is the identity) and "
                                           "there is no initPose: the world would not be gravity-aligned",
                                    "export again with the app's metadata intact (older Record3D versions write "
                                    "initPose beside poses)"))
    return gl_to_cv_cam(T_zup_from_yup() @ T_pose), note, problems


def _is_identity(T: NDArray) -> bool:
    return bool(np.all(np.isfinite(T)) and np.abs(T[:3, :3] - np.eye(3)).max() < IDENTITY_TOL
                and np.abs(T[:3, 3]).max() < IDENTITY_TOL)


def depth_size_from_values(n: int, rgb_size: tuple[int, int], where: Path) -> tuple[int, int]:
    """(dw, dh) of a depth frame holding ``n`` values, when the metadata gives no size: the size
    with the RGB frames' aspect, else one of :data:`LIDAR_SIZES` with ``n`` pixels."""
    w, h = rgb_size
    dw = int(round(np.sqrt(n * w / h)))
    if dw > 0 and n % dw == 0 and abs(dw / (n // dw) - w / h) < 0.02:
        return dw, n // dw
    for size in LIDAR_SIZES:
        if size[0] * size[1] == n and (size[0] > size[1]) == (w > h):
            return size
    raise InputError(where, f"holds {n} depth values, which fit no depth size of the {w}x{h} frames' aspect",
                     "the metadata has no dw/dh; export the recording again")


def scan_record3d(path: str | Path, thorough: bool = False) -> CaptureScan:
    """Read everything but the frames, collecting every problem instead of stopping."""
    root = Path(path)
    if not root.exists():
        return CaptureScan(root, FORMAT, problems=(Problem(root, "Record3D export not found"),))
    if root.is_dir() and not (root / "rgbd").is_dir() and (root / "rgb").is_dir():
        from embodmocap.io.captures.record3d_exr import scan_record3d_exr

        return scan_record3d_exr(root, thorough)
    try:
        store = _Store(root)
    except InputError as err:
        return CaptureScan(root, FORMAT, problems=(Problem(root, err.problem, err.fix),))
    kind = "Record3D .r3d file" if root.is_file() else "Record3D export folder (unzipped .r3d)"
    problems: list[Problem] = []
    meta_name = "metadata" if store.exists("metadata") else "metadata.json"
    meta_path = store.where(meta_name)
    try:
        meta = parse_metadata(store.read(meta_name), meta_path)
    except InputError as err:
        return CaptureScan(root, FORMAT, variant=kind, problems=(Problem(err.path, err.problem, err.fix),))
    w, h, fps = meta.w, meta.h, meta.fps

    numbers = sorted(int(m.group(1)) for n in store.names() if (m := _RGB_NAME.match(n)))
    num_frames = len(numbers)
    if num_frames == 0:
        problems.append(Problem(store.where("rgbd"), "no RGB frames (the app writes rgbd/N.jpg, N = 0, 1, ...)",
                                "export the recording again"))
    elif numbers != list(range(num_frames)):
        gap = next(i for i, n in enumerate(numbers) if n != i)
        problems.append(Problem(store.where(f"rgbd/{gap}.jpg"), "missing frame (the app numbers frames 0..N-1)",
                                "export the recording again"))
        num_frames = gap

    rgb_size = (w, h)
    if num_frames:
        try:
            first = _decode_jpeg(store.read("rgbd/0.jpg"), store.where("rgbd/0.jpg"))
            rgb_size = (first.shape[1], first.shape[0])
        except InputError as err:
            problems.append(Problem(err.path, err.problem, err.fix))
    K = Intrinsics.from_K(meta.K3, w, h)
    if rgb_size != (w, h):
        log.info("%s: JPEG frames are %dx%d, metadata says %dx%d; scaling K", root, *rgb_size, w, h)
        K = K.scaled(*rgb_size)
    problems += intrinsics_problems(meta_path, K)

    missing = [i for i in range(num_frames) if not store.exists(f"rgbd/{i}.depth")]
    if missing:
        problems.append(Problem(store.where(f"rgbd/{missing[0]}.depth"),
                                f"missing ({len(missing)} of {num_frames} depth frames missing; the app writes "
                                "rgbd/N.depth beside every rgbd/N.jpg)", "export the recording again with depth"))
    depth_size = meta.depth_size
    present = [i for i in range(num_frames) if i not in set(missing)]
    if depth_size is None and present:
        name = f"rgbd/{present[0]}.depth"
        try:
            raw = _decompress(store.read(name), store.where(name))
            depth_size = depth_size_from_values(len(raw) // 4, rgb_size, store.where(name))
        except InputError as err:
            problems.append(Problem(err.path, err.problem, err.fix))
    if depth_size is not None:
        dw, dh = depth_size
        for i in present[: None if thorough else 1]:
            try:
                _decode_lzfse(store.read(f"rgbd/{i}.depth"), np.float32, (dh, dw), store.where(f"rgbd/{i}.depth"))
            except InputError as err:
                problems.append(Problem(err.path, err.problem, err.fix))

    T, pose_note, pose_probs = world_poses(meta, meta_path)
    problems += pose_probs + pose_problems(meta_path, T, fps, num_frames)
    n_pose = min(len(T), num_frames)
    stamps = meta.frame_timestamps
    if stamps is not None and len(stamps) >= num_frames:
        timestamps, times_note = stamps[:num_frames], "frameTimestamps"
    else:
        timestamps, times_note = np.arange(num_frames) / fps, "times from fps"
    trajectory = CameraTrajectory(timestamps[:n_pose], np.arange(n_pose), T[:n_pose])
    has_conf = num_frames > 0 and store.exists("rgbd/0.conf")
    size_note = "depth size from dw/dh" if meta.depth_size is not None else "depth size from the depth data"
    variant = f"{kind}, {'newer' if meta.depth_size is not None else 'older'} metadata ({pose_note}; " \
              f"{size_note}; {times_note})"

    def make_frames() -> LazyFrames:
        assert depth_size is not None
        dw, dh = depth_size

        def depth(i: int) -> NDArray[np.float32]:
            d = _decode_lzfse(store.read(f"rgbd/{i}.depth"), np.float32, (dh, dw), store.where(f"rgbd/{i}.depth")).copy()
            d[~np.isfinite(d) | (d < 0)] = 0.0
            return d

        def conf(i: int) -> NDArray[np.uint8] | None:
            name = f"rgbd/{i}.conf"
            return _decode_lzfse(store.read(name), np.uint8, (dh, dw), store.where(name)).copy() if store.exists(name) else None

        return LazyFrames(num_frames, lambda i: _decode_jpeg(store.read(f"rgbd/{i}.jpg"), store.where(f"rgbd/{i}.jpg")),
                          lambda i: store.where(f"rgbd/{i}.depth"), None, (dw, dh),
                          read_depth=depth, read_conf=conf if has_conf else None)

    return CaptureScan(
        path=root, format=FORMAT, variant=variant, num_frames=num_frames, fps=fps, rgb_intrinsics=K,
        depth_size=depth_size, timestamps_s=timestamps, trajectory=trajectory, make_frames=make_frames,
        problems=tuple(problems),
    )


def write_record3d(out: str | Path, rgb: Iterable[NDArray[np.uint8]], depth_m: Iterable[NDArray[np.float32]],
                   T_world_cam: NDArray, intrinsics: Intrinsics, fps: float,
                   confidence: Iterable[NDArray[np.uint8]] | None = None,
                   timestamps_s: NDArray | None = None, jpeg_quality: int = 95) -> Path:
    """Write a Record3D export (folder, or a zip when ``out`` ends in ``.r3d``), atomically.

    ``rgb`` (H, W, 3) uint8 frames, ``depth_m`` (h, w) float32 metres, ``T_world_cam`` (N, 4, 4)
    in the package convention (converted back to ARKit's), ``intrinsics`` at the RGB size.
    Mainly a test fixture: the app is the real producer of this format.
    """
    import cv2

    lzfse = require("lzfse", "record3d")
    out = Path(out)
    T = np.asarray(T_world_cam, dtype=np.float64).reshape(-1, 4, 4)
    T_yup_gl = invert_T(T_zup_from_yup()) @ gl_to_cv_cam(T)
    poses = np.concatenate([matrix_to_quat(T_yup_gl[:, :3, :3]), T_yup_gl[:, :3, 3]], axis=1)
    files: dict[str, bytes] = {}
    dsize = None
    confs = iter(confidence) if confidence is not None else None
    for i, (im, d) in enumerate(zip(rgb, depth_m)):
        ok, jpg = cv2.imencode(".jpg", np.ascontiguousarray(np.asarray(im)[..., ::-1]),
                               [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
        assert ok
        files[f"rgbd/{i}.jpg"] = jpg.tobytes()
        d = np.ascontiguousarray(d, dtype=np.float32)
        dsize = (d.shape[1], d.shape[0])
        files[f"rgbd/{i}.depth"] = lzfse.compress(d.tobytes())
        if confs is not None:
            files[f"rgbd/{i}.conf"] = lzfse.compress(np.ascontiguousarray(next(confs), dtype=np.uint8).tobytes())
    meta = {
        "w": intrinsics.width, "h": intrinsics.height, "dw": dsize[0] if dsize else 0, "dh": dsize[1] if dsize else 0,
        "fps": fps, "K": intrinsics.K.T.reshape(-1).tolist(), "poses": poses.tolist(),
    }
    if timestamps_s is not None:
        meta["frameTimestamps"] = np.asarray(timestamps_s, dtype=np.float64).tolist()
    files["metadata"] = json.dumps(meta).encode()
    if out.suffix.lower() == ".r3d":
        with atomic_path(out) as tmp:
            buf = io.BytesIO()
            with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as z:
                for name, data in files.items():
                    z.writestr(name, data)
            tmp.write_bytes(buf.getvalue())
    else:
        from embodmocap.io.atomic import atomic_dir

        with atomic_dir(out) as tmp:
            (tmp / "rgbd").mkdir()
            for name, data in files.items():
                (tmp / name).write_bytes(data)
    return out
