"""Stage III's steps, declared once (:mod:`embodmocap.io.steps`): their fingerprints, the coverage
test of :class:`~embodmocap.calibrate.config.CalibrateConfig` and the architecture doc's table come from here."""

from __future__ import annotations

from embodmocap.calibrate.config import CalibrateConfig
from embodmocap.calibrate.solve import REGISTER_VERSION
from embodmocap.io.steps import StageSteps, Step
from embodmocap.sequence.geosync import GEOSYNC_VERSION

_DIR = "sequences/<seq>/"
_UPSTREAM = ("scenes/<scene>/sfm/sparse", "scenes/<scene>/mesh_raw.ply", "<view>/cameras.npz")

STEPS = StageSteps("calibrate", CalibrateConfig, (
    # The registration's own VIO check uses the yaw offset's settings, and a view placed through
    # the performer uses the cross-view track and the mesh sampled for the Chamfer term: those
    # settings are the registration's, and the refinement, which comes after it, sees them too.
    # A registration reads the sparse model, not the mesh (so `embodmocap run` can start it while
    # Stage I fuses the mesh): the mesh is a read of a view placed through the performer only.
    Step("register", reads=(*_UPSTREAM, "<view>/masks.npy"), version=REGISTER_VERSION,
         settings=("register", "offset", "vio_max_disagreement_m", "vio_max_disagreement_deg", "retry_below_fraction",
                   "retry_candidates_factor", "min_registered_fraction", "min_consistent_fraction",
                   "min_registered_frames", "place_by_performer", "performer_min_on_mesh", "performer_on_mesh_m",
                   "track_frames", "scene_points"),
         writes=(_DIR + "<view>/registration.npz",), doc="frames registered into the sparse model (per view: register_<view>)"),
    # With `presync`, the refinement's track term pairs the views at the sub-frame sync measured on
    # the registration cameras: Stage II's sync record, the keypoints, the session.toml keys and the
    # geosync settings (declared by the geosync step; given here as context) are then its inputs too.
    Step("refine", after=("register",), reads=(*_UPSTREAM, "<view>/registration.npz", "sync.json", "<view>/keypoints2d.npz"),
         context=("use_tracks", "presync_geosync", "subframe_sync", "sync_force"),
         settings=("refine", "refine_views", "chamfer_frames", "chamfer_points_per_frame", "max_refine_shift_m",
                   "max_refine_yaw_deg", "presync", "presync_max_frames"),
         writes=(_DIR + "calibration.json",), doc="yaw + translation of each view refined jointly"),
    Step("geosync", reads=("sync.json", "calibration.json", "<view>/keypoints2d.npz", "<view>/cameras.npz"),
         context=("subframe_sync", "sync_force"), settings=("geosync", "sync_cameras"), version=GEOSYNC_VERSION,
         writes=(_DIR + "final_sync.json", _DIR + "<view>/cameras_world.npz"),
         doc="the time offset where the views' keypoint rays meet; the world cameras"),
))
