"""Interactive 3D web viewer of a finished sequence (``embodmocap view``), built on viser.

What the page shows (Z up, metres, the scene's world):

- the Stage I scene mesh (simplified or full) and a 0.5 m floor grid;
- the fitted SMPL body, animated by a timeline (play/pause, frame slider, step buttons, speed);
- both views' camera frusta following their paths, each with the frame that camera saw (scaled
  down to ``max_image_side``);
- the triangulated COCO-17 keypoints of the current frame (gap-filled ones in orange);
- the performer's pelvis path as a line;
- the skill clips (``embodmocap skills``): each clip's object box and target, and a clip list that
  moves the timeline to a clip;
- one checkbox per layer.

Body vertices are posed a chunk of frames at a time in float32 (:class:`embodmocap.viz.BodyFrames`)
and only the current frame is sent to the browser, so long sequences cost neither memory nor start
time. :func:`serve` returns at once with a :class:`ViewerHandle`; :func:`view_cli` blocks until
Ctrl-C.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import require
from embodmocap.geometry.rotations import matrix_to_quat, xyzw_to_wxyz
from embodmocap.io.layout import SessionLayout
from embodmocap.viz.config import ViewerConfig
from embodmocap.viz import BodyFrames, SequenceData, load_sequence

log = logging.getLogger(__name__)

#: Frustum colours per view (v1 red, v2 green, as the paper's release draws them).
VIEW_COLOURS: dict[str, tuple[int, int, int]] = {"v1": (220, 60, 60), "v2": (60, 180, 80)}

#: Scene node names the viewer creates (also the layer names of the checkboxes).
LAYERS: tuple[str, ...] = ("scene", "body", "cameras", "keypoints", "path", "robot", "skills")


class ViewerHandle:
    """A running viewer: the viser server, its scene nodes and the timeline.

    Attributes:
        server: the ``viser.ViserServer``.
        nodes: layer name -> scene handle(s): ``scene`` (mesh, or None), ``body`` (mesh),
            ``cameras`` (view -> frustum), ``keypoints`` (point cloud, or None), ``path`` (lines).
        data: the sequence shown.
        url: address of the page.
    """

    def __init__(self, server, data: SequenceData, body: BodyFrames, frames: dict[str, Any], cfg: ViewerConfig) -> None:
        self.server = server
        self.data = data
        self.nodes: dict[str, Any] = {}
        self.url = f"http://{cfg.host}:{server.get_port()}"
        self.scene_bounds: NDArray | None = None  # (2, 3) min/max corner of the scene mesh
        self._body = body
        self._sources = frames  # view -> FrameSource (or None: no images)
        self._cfg = cfg
        self._lock = threading.Lock()
        self._frame = -1
        self._stop = threading.Event()
        self._gui: dict[str, Any] = {}
        self._thread: threading.Thread | None = None

    @property
    def num_frames(self) -> int:
        return len(self.data.frames)

    @property
    def frame(self) -> int:
        """The row of the motion shown now."""
        return self._frame

    def set_frame(self, row: int) -> None:
        """Show motion row ``row`` (clipped to the sequence): body, frusta, images, keypoints."""
        row = int(np.clip(row, 0, self.num_frames - 1))
        with self._lock:
            if row == self._frame:
                return
            self._frame = row
            self._show(row)
        slider = self._gui.get("frame")
        if slider is not None and slider.value != row:
            slider.value = row

    def playing(self) -> bool:
        box = self._gui.get("playing")
        return bool(box is not None and box.value)

    def stop(self) -> None:
        """Stop the playback thread and the server."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self.server.stop()

    # ------------------------------------------------------------------ per frame

    def _show(self, row: int) -> None:
        data, t = self.data, int(self.data.frames[row])
        with self.server.atomic():
            self.nodes["body"].vertices = self._body.vertices(row)
            for v, frustum in self.nodes["cameras"].items():
                T = data.views[v].T_world_cam[t]
                frustum.position = T[:3, 3]
                frustum.wxyz = _wxyz(T[:3, :3])
                image = self._image(v, t)
                if image is not None:
                    frustum.image = image
            kp = self.nodes.get("keypoints")
            if kp is not None:
                pts, cols = _keypoint_cloud(data, t)
                kp.points, kp.colors = pts, cols
            robot = getattr(self, "robot", None)
            if robot is not None and row < len(robot.pos):
                for i, node in enumerate(self.nodes["robot"].values()):
                    node.position = robot.pos[row, i] + np.asarray(self._cfg.robot_offset_m)
                    node.wxyz = robot.wxyz[row, i]

    def _image(self, view: str, t: int) -> NDArray[np.uint8] | None:
        src = self._sources.get(view)
        if src is None:
            return None
        raw = int(self.data.views[view].raw_frames[t])
        try:
            rgb = src.rgb(raw)
        except (IndexError, OSError, ValueError) as err:  # a capture shorter than the cameras say
            log.warning("%s: cannot read raw frame %d (%s); frustum image left as it was", view, raw, err)
            return None
        return _downscaled(rgb, self._cfg.max_image_side)

    def _play(self) -> None:
        """Playback loop (daemon thread): advance while the play box is ticked."""
        while not self._stop.is_set():
            fps = self._cfg.playback_fps or self.data.params.fps or 30.0
            speed = float(self._gui["speed"].value) if "speed" in self._gui else 1.0
            step = 1.0 / max(fps * speed, 1e-3)
            if self.playing() and self.num_frames > 1:
                t0 = time.perf_counter()
                self.set_frame((self._frame + 1) % self.num_frames)
                self._stop.wait(max(0.0, step - (time.perf_counter() - t0)))
            else:
                self._stop.wait(0.05)


def _wxyz(R: NDArray) -> NDArray[np.float64]:
    """Rotation matrix -> viser's (w, x, y, z) quaternion (the package stores (x, y, z, w))."""
    return xyzw_to_wxyz(matrix_to_quat(R))


def _downscaled(rgb: NDArray[np.uint8], max_side: int) -> NDArray[np.uint8]:
    import cv2

    s = max_side / max(rgb.shape[:2])
    if s >= 1.0:
        return rgb
    size = (max(1, round(rgb.shape[1] * s)), max(1, round(rgb.shape[0] * s)))
    return cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)


def _keypoint_cloud(data: SequenceData, t: int) -> tuple[NDArray[np.float32], NDArray[np.uint8]]:
    """(n, 3) finite keypoints of sequence frame ``t`` and their colours (orange where gap-filled)."""
    kp = data.keypoints3d
    if kp is None or not 0 <= t < len(kp.points):
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
    ok = np.isfinite(kp.points[t]).all(axis=1)
    cols = np.where(kp.filled[t][ok, None], [[255, 150, 30]], [[250, 230, 40]]).astype(np.uint8)
    return kp.points[t][ok].astype(np.float32), cols


def _frame_sources(session: Path, data: SequenceData, cfg: ViewerConfig) -> dict[str, Any]:
    """view -> the capture's FrameSource, or nothing for views whose capture cannot be opened."""
    if cfg.max_image_side <= 0:
        return {}
    from embodmocap.errors import InputError
    from embodmocap.io.captures import open_capture
    from embodmocap.io.manifest import load_manifest

    lay = SessionLayout(session)
    entry = load_manifest(lay.manifest).sequences[data.name]
    sources = {}
    for v in data.views:
        path = entry.views[v].capture if v in entry.views else lay.view_capture(data.name, v)
        try:
            sources[v] = open_capture(path).frames
        except InputError as err:
            log.warning("no images in the %s frustum: %s", v, err)
    return sources


def _add_scene(server, session: Path, data: SequenceData, cfg: ViewerConfig):
    """Scene mesh (+ floor grid); returns the mesh handle and its (2, 3) bounds, or (None, None)."""
    if cfg.mesh == "none":
        return None, None
    from embodmocap.io.mesh_file import read_mesh_ply

    scene = SessionLayout(session).scene(data.scene)
    path = scene.mesh_simplified if cfg.mesh == "simplified" else scene.mesh_raw
    if not path.is_file():
        log.warning("%s not found: the viewer shows no scene mesh", path)
        return None, None
    v, f, c = read_mesh_ply(path)
    lo, hi = v.min(0), v.max(0)
    node = _scene_mesh_node(server, v, f, c)
    server.scene.add_grid("/grid", width=float(hi[0] - lo[0]) + 1.0, height=float(hi[1] - lo[1]) + 1.0,
                          cell_size=0.5, position=((lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]))
    return node, np.stack([lo, hi])


def _scene_mesh_node(server, v: NDArray, f: NDArray, c: NDArray):
    """The scene mesh node: vertex colours when the file has them, else plain grey."""
    if len(c) == len(v):
        import trimesh

        mesh = trimesh.Trimesh(v, f, vertex_colors=np.round(np.clip(c, 0, 1) * 255).astype(np.uint8), process=False)
        return server.scene.add_mesh_trimesh("/scene", mesh)
    return server.scene.add_mesh_simple("/scene", v.astype(np.float32), f.astype(np.uint32),
                                        color=(200, 200, 200), side="double")


def _start_viewpoint(data: SequenceData, bounds: NDArray | None) -> NDArray[np.float64]:
    """Where the browser's camera starts: behind and above the first view's first camera, kept
    inside the scene's bounds (a point behind a camera near a wall would be outside the room)."""
    T = next(iter(data.views.values())).T_world_cam[int(data.frames[0])]
    back = T[:3, 2] * np.array([1.0, 1.0, 0.0])
    back /= max(np.linalg.norm(back), 1e-9)
    pos = T[:3, 3] - 0.8 * back + np.array([0.0, 0.0, 0.5])
    if bounds is not None:
        pos = np.clip(pos, bounds[0] + 0.4, bounds[1] - 0.4)
    return pos


def _add_nodes(handle: ViewerHandle, session: Path, cfg: ViewerConfig) -> None:
    server, data = handle.server, handle.data
    nodes = handle.nodes
    nodes["scene"], handle.scene_bounds = _add_scene(server, session, data, cfg)
    nodes["body"] = server.scene.add_mesh_simple(
        "/body", handle._body.vertices(0), handle._body.faces.astype(np.uint32), color=cfg.body_rgb,
        opacity=cfg.body_opacity if cfg.body_opacity < 1 else None, side="double")
    t0 = int(data.frames[0])
    nodes["cameras"] = {}
    for v, cams in data.views.items():
        K = cams.intrinsics
        nodes["cameras"][v] = server.scene.add_camera_frustum(
            f"/cameras/{v}", fov=float(2 * np.arctan2(K.height / 2, K.fy)), aspect=K.width / K.height,
            scale=cfg.frustum_scale, color=VIEW_COLOURS.get(v, (200, 200, 200)), image=handle._image(v, t0),
            jpeg_quality=cfg.jpeg_quality, format="jpeg",
            position=cams.T_world_cam[t0, :3, 3], wxyz=_wxyz(cams.T_world_cam[t0, :3, :3]))
    if data.keypoints3d is not None:
        pts, cols = _keypoint_cloud(data, t0)
        nodes["keypoints"] = server.scene.add_point_cloud("/keypoints", pts, cols, point_size=cfg.point_size,
                                                          point_shape="circle")
    else:
        nodes["keypoints"] = None
    path = data.pelvis
    segments = np.stack([path[:-1], path[1:]], axis=1) if len(path) > 1 else np.zeros((0, 2, 3))
    nodes["path"] = server.scene.add_line_segments("/path", segments.astype(np.float32), (255, 120, 200),
                                                   thickness=3.0, thickness_units="screen")
    _add_robot(handle, session, cfg)
    _add_skills(handle, session)


def _add_skills(handle: ViewerHandle, session: Path) -> None:
    """The skill layer (clip boxes and targets, ``embodmocap skills``), if the sequence has clips."""
    from embodmocap.viz.skills_layer import add_skills

    add_skills(handle, session)


def _add_robot(handle: ViewerHandle, session: Path, cfg: ViewerConfig) -> None:
    """The robot layer: one node per visual mesh of the retargeted robot, if there is one."""
    from embodmocap.viz.robot_layer import RobotFrames, find_robot

    handle.robot = None
    folder = find_robot(session, handle.data.name, cfg.robot)
    if folder is None:
        return
    handle.robot = RobotFrames.load(folder)
    handle.nodes["robot"] = {
        f"/robot/{i}": handle.server.scene.add_mesh_simple(f"/robot/{i}", v, f, color=(200, 200, 205), side="double")
        for i, (v, f) in enumerate(handle.robot.meshes)}


def _add_gui(handle: ViewerHandle, cfg: ViewerConfig) -> None:
    gui, g, n = handle.server.gui, handle._gui, handle.num_frames
    with gui.add_folder("Timeline"):
        g["playing"] = gui.add_checkbox("Playing", initial_value=cfg.start_playing)
        g["frame"] = gui.add_slider("Frame", min=0, max=max(n - 1, 1), step=1, initial_value=0, disabled=n < 2)
        prev, nxt = gui.add_button("Previous frame"), gui.add_button("Next frame")
        g["speed"] = gui.add_slider("Speed", min=0.1, max=4.0, step=0.1, initial_value=1.0)
    g["frame"].on_update(lambda _: handle.set_frame(int(g["frame"].value)))
    prev.on_click(lambda _: handle.set_frame((handle.frame - 1) % n))
    nxt.on_click(lambda _: handle.set_frame((handle.frame + 1) % n))
    with gui.add_folder("Layers"):
        for layer in LAYERS:
            node = handle.nodes.get(layer)
            targets = list(node.values()) if isinstance(node, dict) else [node] if node is not None else []
            if layer == "scene" and targets:
                grid = handle.server.scene.get_handle_by_name("/grid")
                targets += [grid] if grid is not None else []
            box = gui.add_checkbox(layer.capitalize(), initial_value=True, disabled=not targets)
            box.on_update(lambda ev, ts=targets: [setattr(h, "visible", ev.target.value) for h in ts])
            g[f"layer_{layer}"] = box
    from embodmocap.viz.skills_layer import add_clip_list

    add_clip_list(handle)


def serve(session: str | Path, seq: str, cfg: ViewerConfig = ViewerConfig()) -> ViewerHandle:
    """Start the viewer of one sequence and return at once (the server runs in its own threads).

    Raises:
        MissingExtraError: viser is not installed (``pip install 'embodmocap[viewer]'``).
        InputError: Stage IV outputs are missing or malformed.
    """
    viser = require("viser", "viewer")
    from embodmocap.body.model import load_body_model

    session = Path(session)
    data = load_sequence(session, seq)
    body = BodyFrames(load_body_model(data.body_model), data.params, chunk=cfg.chunk_frames)
    sources = _frame_sources(session, data, cfg)
    server = viser.ViserServer(host=cfg.host, port=cfg.port, verbose=False)
    try:
        server.scene.set_up_direction("+z")
        handle = ViewerHandle(server, data, body, sources, cfg)
        _add_nodes(handle, session, cfg)
        _add_gui(handle, cfg)
        server.initial_camera.position = tuple(_start_viewpoint(data, handle.scene_bounds))
        server.initial_camera.look_at = tuple(data.pelvis[0])
        server.initial_camera.up = (0.0, 0.0, 1.0)
        handle.set_frame(0)
        handle._thread = threading.Thread(target=handle._play, name="embodmocap-viewer-playback", daemon=True)
        handle._thread.start()
    except BaseException:
        server.stop()
        raise
    log.info("viewer of %s/%s at %s", session, seq, handle.url)
    return handle


def view_cli(session: Path, seq: str, cfg: ViewerConfig = ViewerConfig()) -> None:
    """Serve the viewer and block until Ctrl-C."""
    handle = serve(session, seq, cfg)
    log.warning("viewer running at %s (Ctrl-C to stop)", handle.url)
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        log.info("stopping the viewer")
    finally:
        handle.stop()
