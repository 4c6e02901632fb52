"""The perception registry: ``make(role, name, view, config)`` builds the backend Stage II uses for
one role of one view, whatever it is (precomputed files, a ``transformers`` model, MediaPipe).

Every backend returned follows its role's protocol in :mod:`embodmocap.perception.roles`:

============= ==================================== =============================================
role          protocol                             names
============= ==================================== =============================================
detector      :class:`~.roles.PersonDetector`      precomputed, rtdetr, mediapipe
keypoints     :class:`~.roles.KeypointEstimator`   precomputed, vitpose, mediapipe
masks         :class:`~.roles.MaskSegmenter`       precomputed, sam2, mediapipe
depth         :class:`~.roles.DepthEstimator`      precomputed, promptda
body_prior    :class:`~.roles.BodyPriorEstimator`  precomputed
============= ==================================== =============================================

Precomputed backends read the view's files named in ``session.toml``; a view that names none is
one :class:`~embodmocap.errors.InputError` saying which key to add or which backend to pick.
Model backends import their libraries only when built; their weights come from the config's
``*_model`` (a local folder or a hub id; empty = the role's default id of
:data:`embodmocap.perception.hub.DEFAULT_MODELS`), downloaded into the Hugging Face cache unless
``offline``. ``shared`` lets one call site reuse one
instance for several roles (MediaPipe detects and estimates keypoints in one model).
"""

from __future__ import annotations

from typing import Any, Callable

from embodmocap.errors import InputError
from embodmocap.perception import roles

#: Role -> the protocol its backends follow.
PROTOCOLS: dict[str, type] = {
    "detector": roles.PersonDetector,
    "keypoints": roles.KeypointEstimator,
    "masks": roles.MaskSegmenter,
    "depth": roles.DepthEstimator,
    "body_prior": roles.BodyPriorEstimator,
}

#: For each role, the manifest key a precomputed backend reads, and the advice when it is missing.
_PRECOMPUTED_KEY = {
    "detector": ("keypoints", "detector = precomputed needs the view's keypoint folder",
                 "add `keypoints = \"...\"` for the view in session.toml, or pick detector = rtdetr or mediapipe"),
    "keypoints": ("keypoints", "keypoints = precomputed but the view names no keypoint folder",
                  "add `keypoints = \"...\"` for the view in session.toml, or pick a model backend"),
    "masks": ("masks", "masks = precomputed but the view names no mask folder",
              "add `masks = \"...\"` for the view in session.toml, or use --masks none"),
    "depth": ("depth", "depth = precomputed but the view names no depth folder",
              "add `depth = \"...\"` for the view in session.toml, or use --depth lidar"),
    "body_prior": ("body_prior", "body_prior = precomputed but the view names no body prior file",
                   "add `body_prior = \"...\"` for the view in session.toml, or use --body-prior none"),
}


def _view_path(role: str, view) -> Any:
    key, problem, fix = _PRECOMPUTED_KEY[role]
    path = getattr(view, key, None) if view is not None else None
    if path is None:
        raise InputError(getattr(view, "capture", None), problem, fix)
    return path


class RefinedDepth:
    """A :class:`~.roles.DepthEstimator` over a :class:`~.depth_refine.DepthRefiner` (RGB + sensor depth in)."""

    def __init__(self, refiner) -> None:
        self.refiner = refiner
        self.name = refiner.name

    def depth_maps(self, frames, frame_ids, sensor_depth):
        if sensor_depth is None:
            raise ValueError(f"depth backend {self.name!r} refines the sensor depth: pass it")
        return self.refiner.refine(frames, sensor_depth)


def _mediapipe(shared: dict) -> Any:
    if "mediapipe" not in shared:
        from embodmocap.perception.mediapipe_backend import MediaPipePose

        shared["mediapipe"] = MediaPipePose()
    return shared["mediapipe"]


def _hf(role: str, name: str, model: str, cfg) -> Any:
    from embodmocap.perception.hf_backends import make_backend

    return make_backend(role, name, model=model, device=cfg.device, offline=cfg.offline)


def _precomputed_keypoints(view, role: str):
    from embodmocap.perception.precomputed import PrecomputedKeypoints

    return PrecomputedKeypoints(_view_path(role, view))


def _precomputed(cls_name: str, role: str) -> Callable:
    def build(view, cfg, shared):
        from embodmocap.perception import precomputed

        return getattr(precomputed, cls_name)(_view_path(role, view))
    return build


def _promptda(view, cfg, shared):
    from embodmocap.perception.depth_refine import make_depth_refiner

    return RefinedDepth(make_depth_refiner("promptda", model=cfg.depth_model, device=cfg.device, output="rgb",
                                           offline=cfg.offline))


def _precomputed_detector(view, cfg, shared):
    from embodmocap.perception.precomputed import PrecomputedDetector

    return PrecomputedDetector(_precomputed_keypoints(view, "detector"))


#: (role, name) -> builder(view, config, shared).
BACKENDS: dict[tuple[str, str], Callable[[Any, Any, dict], Any]] = {
    ("detector", "precomputed"): _precomputed_detector,
    ("detector", "rtdetr"): lambda view, cfg, shared: _hf("detector", "rtdetr", cfg.detector_model, cfg),
    ("detector", "mediapipe"): lambda view, cfg, shared: _mediapipe(shared),
    ("keypoints", "precomputed"): lambda view, cfg, shared: _precomputed_keypoints(view, "keypoints"),
    ("keypoints", "vitpose"): lambda view, cfg, shared: _hf("keypoints", "vitpose", cfg.keypoints_model, cfg),
    ("keypoints", "mediapipe"): lambda view, cfg, shared: _mediapipe(shared),
    ("masks", "precomputed"): _precomputed("PrecomputedMasks", "masks"),
    ("masks", "sam2"): lambda view, cfg, shared: _hf("masks", "sam2", cfg.masks_model, cfg),
    ("masks", "mediapipe"): lambda view, cfg, shared: _mediapipe(shared),
    ("depth", "precomputed"): _precomputed("PrecomputedDepth", "depth"),
    ("depth", "promptda"): _promptda,
    ("body_prior", "precomputed"): _precomputed("PrecomputedBodyPrior", "body_prior"),
}


def names(role: str) -> tuple[str, ...]:
    """The backend names registered for ``role``."""
    return tuple(n for r, n in BACKENDS if r == role)


def make(role: str, name: str, view=None, config=None, shared: dict | None = None):
    """The backend ``name`` for ``role``, for one view.

    Args:
        role: one of :data:`PROTOCOLS`.
        name: a backend name of that role (:func:`names`).
        view: the view's manifest entry (:class:`~embodmocap.io.manifest.ViewEntry`): where the
            precomputed files are; None for model backends.
        config: the model folders or hub ids, device, offline: Stage II's settings
            (:class:`~embodmocap.sequence.config.SequenceConfig`) or any object with the fields of
            :class:`~embodmocap.perception.config.ModelSources`; None = the defaults.
        shared: instances to reuse across roles (one dict per view and call site).

    Raises:
        ValueError: unknown role or name. InputError: a precomputed backend without its files.
    """
    if role not in PROTOCOLS:
        raise ValueError(f"unknown perception role {role!r}; roles: {', '.join(PROTOCOLS)}")
    build = BACKENDS.get((role, name))
    if build is None:
        raise ValueError(f"no {role} backend named {name!r}; {role} backends: {', '.join(names(role))}")
    if config is None:
        from embodmocap.perception.config import ModelSources

        config = ModelSources()
    backend = build(view, config, {} if shared is None else shared)
    assert isinstance(backend, PROTOCOLS[role]), f"{type(backend).__name__} does not follow {PROTOCOLS[role].__name__}"
    return backend

