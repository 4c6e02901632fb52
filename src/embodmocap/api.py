"""The Python API for notebooks and scripts: ``embodmocap.run(session)`` and ``embodmocap.load(session)``.

    import embodmocap
    res = embodmocap.run("my_session")            # every stage, resumable (or embodmocap.load)
    seq = res.sequence()                          # the only sequence, or res.sequence("walk")
    seq.motion.params.body_pose, seq.motion.valid # (T, 69) world SMPL pose, (T,) bool
    v, f, c = res.scene(seq.scene).mesh           # scene mesh, Z up, metres

Everything is read through the typed readers the stages write with (:mod:`embodmocap.io`), so a
result holds exactly what the files hold; nothing is recomputed. Large things (the mesh, the motion,
the joints, the cameras) are read on first access and kept, so ``load`` of a big session is quick
and only what a notebook touches is read. A file that is missing or malformed raises the reader's
:class:`~embodmocap.errors.InputError` naming the file and the command that writes it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import EmbodMocapError, InputError
from embodmocap.io.layout import VIEWS, SceneLayout, SequenceLayout, SessionLayout
from embodmocap.types import SmplParams

#: The largest stage manifest or evaluation file read for figures (they are a few kB).
_MAX_JSON_BYTES = 64 * 2**20


class Mesh(NamedTuple):
    """A triangle mesh in the scene's world (Z up, metres)."""

    vertices: NDArray[np.float64]
    """(V, 3) positions."""
    faces: NDArray[np.int64]
    """(F, 3) vertex indices."""
    colours: NDArray
    """(V, 3) RGB, or an empty array when the file has none."""


@dataclass(frozen=True)
class SmplMotion:
    """The world SMPL motion of a sequence (``smpl_world.npz``)."""

    params: SmplParams
    """SMPL parameters per frame, world frame (Z up, metres): betas, global_orient, body_pose,
    transl, fps, gender."""
    frames: NDArray[np.int64]
    """(T,) sequence frame of each row."""
    valid: NDArray[np.bool_]
    """(T,) False where the body could not be placed from that frame's observations and was filled
    in from its neighbours (all True for files written before the flag existed)."""

    @property
    def fps(self) -> float:
        return float(self.params.fps)

    def __len__(self) -> int:
        return len(self.params)


@dataclass(frozen=True)
class SceneResult:
    """One scene's Stage I outputs."""

    name: str
    paths: SceneLayout
    """Every path of the scene's output folder (``paths.mesh_raw``, ``paths.manifest``, ...)."""

    @cached_property
    def mesh(self) -> Mesh:
        """The full-resolution scene mesh (``mesh_raw.ply``), read on first access."""
        from embodmocap.io.mesh_file import read_mesh_ply

        return Mesh(*read_mesh_ply(_need(self.paths.mesh_raw, "scene mesh", "embodmocap scene SESSION")))

    @cached_property
    def quality(self) -> dict[str, Any]:
        """Stage I's quality figures (its stage manifest's ``figures``); empty before it ran."""
        return _figures(self.paths.manifest)


@dataclass(frozen=True)
class SequenceResult:
    """One sequence's outputs: motion, joints, cameras per view, quality figures, paths."""

    name: str
    scene: str
    """Name of the scene the sequence was captured in (``result.scene(seq.scene)``)."""
    paths: SequenceLayout
    """Every path of the sequence's output folder (``paths.smpl_world``, ``paths.view("v1")``, ...)."""

    @property
    def done(self) -> bool:
        """Whether Stage IV has written the world motion."""
        return self.paths.smpl_world.is_file()

    @cached_property
    def motion(self) -> SmplMotion:
        """World SMPL motion with its ``valid`` flags, read on first access."""
        from embodmocap.io.smpl_file import read_smpl_npz, read_smpl_valid

        params, frames = read_smpl_npz(self.paths.smpl_world)
        return SmplMotion(params, frames, read_smpl_valid(self.paths.smpl_world))

    @cached_property
    def joints(self) -> NDArray[np.float64]:
        """(T, 24, 3) SMPL joints of the final body, world metres (``joints_world.npz``)."""
        from embodmocap.io.stage_files import read_world_joints

        return np.asarray(read_world_joints(self.paths.joints_world).joints, dtype=np.float64)

    @cached_property
    def cameras(self) -> dict[str, Any]:
        """View -> :class:`~embodmocap.io.stage_files.CameraFile` in the scene's world: Stage IV's
        ``cameras_final.npz`` (after the contact alignment), else Stage III's ``cameras_world.npz``.
        ``T_world_cam`` (N, 4, 4) camera-to-world, OpenCV axes; ``K`` (3, 3); ``raw_frames`` (N,)."""
        from embodmocap.io.stage_files import read_cameras

        out = {}
        for v in VIEWS:
            view = self.paths.view(v)
            path = view.cameras_final if view.cameras_final.is_file() else view.cameras_world
            out[v] = read_cameras(_need(path, f"cameras of view {v}", f"embodmocap calibrate SESSION --seq {self.name}"))
        return out

    @cached_property
    def quality(self) -> dict[str, dict[str, Any]]:
        """Stage -> quality figures of its stage manifest (``sequence``, ``calibrate``, ``motion``;
        a stage that has not run is absent)."""
        found = {stage: _figures(path) for stage, path in (("sequence", self.paths.manifest),
                                                           ("calibrate", self.paths.calibrate_manifest),
                                                           ("motion", self.paths.motion_manifest))}
        return {k: v for k, v in found.items() if v}


@dataclass(frozen=True)
class SessionResult:
    """A processed session: its scenes and sequences, the evaluation, and what ``run`` did."""

    root: Path
    paths: SessionLayout
    scenes: dict[str, SceneResult]
    sequences: dict[str, SequenceResult]
    pipeline: Any = field(default=None, repr=False)
    """The :class:`~embodmocap.pipeline.PipelineResult` (stage by stage) when made by :func:`run`."""

    def sequence(self, name: str | None = None) -> SequenceResult:
        """Sequence ``name``, or the session's only one."""
        if name is None:
            if len(self.sequences) != 1:
                raise InputError(self.paths.manifest, f"the session has {len(self.sequences)} sequences",
                                 f"name one: {', '.join(sorted(self.sequences))}")
            return next(iter(self.sequences.values()))
        if name not in self.sequences:
            raise InputError(self.paths.manifest, f"no sequence {name!r}", f"choose one of {', '.join(sorted(self.sequences))}")
        return self.sequences[name]

    def scene(self, name: str | None = None) -> SceneResult:
        """Scene ``name``, or the session's only one."""
        if name is None and len(self.scenes) == 1:
            return next(iter(self.scenes.values()))
        if name not in self.scenes:
            raise InputError(self.paths.manifest, f"no scene {name!r}", f"choose one of {', '.join(sorted(self.scenes))}")
        return self.scenes[name]

    @cached_property
    def evaluation(self) -> dict[str, Any] | None:
        """``evaluation.json`` (``embodmocap evaluate``), or None when it was not written."""
        from embodmocap.io.jsonfile import read_json

        if not self.paths.evaluation.is_file():
            return None
        return read_json(self.paths.evaluation, max_bytes=_MAX_JSON_BYTES, what="evaluation file")


def load(session: str | Path) -> SessionResult:
    """The outputs of a processed session (see the module docstring); nothing is computed.

    Raises:
        InputError: the folder has no readable ``session.toml``.
    """
    from embodmocap.io.manifest import load_manifest

    layout = SessionLayout(Path(session))
    manifest = load_manifest(layout.manifest)
    scenes = {n: SceneResult(n, layout.scene(n)) for n in manifest.scenes}
    sequences = {n: SequenceResult(n, e.scene, layout.sequence(n)) for n, e in manifest.sequences.items()}
    return SessionResult(layout.root, layout, scenes, sequences)


def run(session: str | Path, config: Any = None, *, force: bool = False) -> SessionResult:
    """Run every stage of ``session`` (resumable, like ``embodmocap run``) and :func:`load` it.

    Args:
        session: session folder (holds ``session.toml``).
        config: a :class:`~embodmocap.pipeline.PipelineConfig`, a path to a settings file in the
            ``--config`` format (docs/config.example.toml), or None for the defaults.
        force: redo every step even when its outputs are up to date.

    Raises:
        EmbodMocapError: a stage failed (the message lists each failure with its cause; fix it and
            call again to resume), or a bad settings file.
    """
    from embodmocap.pipeline import PipelineConfig, run_session

    if config is None:
        config = PipelineConfig()
    elif isinstance(config, (str, Path)):
        from embodmocap.cli import Run
        from embodmocap.cli_settings import command_default, read_settings

        config = command_default(Run, "run", read_settings(Path(config)), Path(config)).config
    res = run_session(config, session, force=force)
    if not res.ok:
        failed = "; ".join(f"{r.target} {r.stage}: {r.error}" for r in res.failed())
        raise EmbodMocapError(f"{session}: {len(res.failed())} stage(s) failed: {failed} "
                              "(fix the cause and call run again to resume)")
    return replace(load(session), pipeline=res)


def _need(path: Path, what: str, command: str) -> Path:
    if not path.is_file():
        raise InputError(path, f"{what} not found", f"run `{command}` first")
    return path


def _figures(manifest: Path) -> dict[str, Any]:
    """The ``figures`` of a stage manifest; empty when the stage has not run."""
    from embodmocap.io.jsonfile import read_json

    if not manifest.is_file():
        return {}
    data = read_json(manifest, max_bytes=_MAX_JSON_BYTES, what="stage manifest")
    figures = data.get("figures") if isinstance(data, dict) else None
    return dict(figures) if isinstance(figures, dict) else {}


__all__ = ["Mesh", "SceneResult", "SequenceResult", "SessionResult", "SmplMotion", "load", "run"]
