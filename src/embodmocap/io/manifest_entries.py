"""The typed entries of the session manifest (``session.toml``): :class:`SessionManifest` and its
scenes, sequences, views and contact markers, with every path made absolute at construction.
Reading, checking and writing the file: :mod:`embodmocap.io.manifest` (which re-exports these)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

from embodmocap.errors import InputError
from embodmocap.io.layout import VIEWS

#: The manifest format version this module reads and writes.
MANIFEST_VERSION = 1
#: Body model genders the manifest accepts.
GENDERS: tuple[str, ...] = ("neutral", "male", "female")
#: File name of the manifest inside a session folder.
MANIFEST_NAME = "session.toml"

Xyz = tuple[float, float, float]


def xyz_tuple(v) -> Xyz:
    """A point as a tuple of 3 floats, so equality does not depend on list vs tuple input."""
    x, y, z = (float(c) for c in v)
    return (x, y, z)


class ManifestError(InputError):
    """A manifest with one or more problems; ``problems`` holds one line per problem."""

    def __init__(self, path: str | Path | None, problems: list[str]) -> None:
        self.problems = list(problems)
        count = f"{len(problems)} problem{'s' if len(problems) != 1 else ''}"
        lines = "".join(f"\n  - {p}" for p in problems)
        super().__init__(path, f"invalid session manifest, {count} (fix them and run again):{lines}")


@dataclass(frozen=True)
class SceneEntry:
    """One static-scene capture (stage I input)."""

    name: str
    """Scene name: the key under ``[scenes]``; also the folder name of its outputs."""
    capture: Path
    """Folder of the raw scene capture (absolute in memory; relative to the session in the file)."""
    indoor: bool = True
    """Whether the scene is indoors (indoor scenes get ceiling removal and tighter depth limits)."""
    markers: dict[str, Xyz] = field(default_factory=dict)
    """Named contact markers: name -> (x, y, z) in the scene frame, metres (Z up)."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "capture", Path(self.capture))
        object.__setattr__(self, "markers", {str(k): xyz_tuple(v) for k, v in self.markers.items()})


@dataclass(frozen=True)
class ContactMarker:
    """A known point the person's pelvis passes over at one frame (the paper's contact list)."""

    frame: int
    """Frame index of the sequence after synchronisation and slicing (0-based)."""
    xyz: Xyz
    """Contact point (x, y, z) in the scene frame, metres (Z up)."""
    marker: str | None = None
    """Name of the scene marker ``xyz`` came from, or None when ``xyz`` was given directly."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "frame", int(self.frame))
        object.__setattr__(self, "xyz", xyz_tuple(self.xyz))


@dataclass(frozen=True)
class ViewEntry:
    """One handheld view of a sequence (stage II input)."""

    capture: Path
    """Folder of the view's raw capture."""
    sync_frame: int | None = None
    """Raw frame index where the laser dot disappears; None = detect it automatically."""
    keypoints: Path | None = None
    """Folder of precomputed per-frame keypoint JSON (OpenPose or COCO style), or None."""
    masks: Path | None = None
    """Folder of precomputed person mask PNGs (255 = person), or None."""
    depth: Path | None = None
    """Folder of precomputed (refined) depth PNGs, or None to use the capture's depth."""
    body_prior: Path | None = None
    """File of the precomputed camera-space body prior (``.npz``), or None."""


@dataclass(frozen=True)
class SequenceEntry:
    """One performance seen by two handheld views inside one scene."""

    name: str
    """Sequence name: the key under ``[sequences]``; also the folder name of its outputs."""
    scene: str
    """Name of the scene (a key of ``SessionManifest.scenes``) the sequence was captured in."""
    views: dict[str, ViewEntry]
    """The views by name: ``v1`` and ``v2`` (two phones), or ``v1`` alone (one phone: no
    cross-view sync and no triangulation; see :attr:`view_names`)."""
    contacts: tuple[ContactMarker, ...] = ()
    """Contact markers used by the optional contact alignment of stage IV."""
    optim_scale: bool = False
    """Whether stage III also optimises a global scale of each view's trajectory."""
    note: str = ""
    """Free text carried along (e.g. why the sequence failed)."""
    failed: bool = False
    """Marked as failed: ``run`` skips it unless forced."""
    subframe_sync: bool = True
    """With manual ``sync_frame`` values: Stage III still measures the sub-frame part of the offset
    (geometric sync) and applies it when it agrees with the manual frames within a frame; False =
    the manual frames are applied as given (integer frames)."""
    sync_force: bool = False
    """Keep the manual ``sync_frame`` values even when the geometric sync contradicts them by more
    than ``geosync.manual_error_frames`` with high confidence (otherwise that is an error)."""

    @property
    def view_names(self) -> tuple[str, ...]:
        """The sequence's views in :data:`~embodmocap.io.layout.VIEWS` order: ``("v1", "v2")``, or
        ``("v1",)`` for a one-phone sequence. Every stage iterates over these."""
        return tuple(v for v in VIEWS if v in self.views)

    @property
    def one_view(self) -> bool:
        """Filmed by one phone: its outputs are flagged ``one_view``."""
        return len(self.view_names) == 1


@dataclass(frozen=True)
class SessionManifest:
    """The whole manifest. Relative paths are resolved against ``root`` at construction."""

    root: Path
    """The session folder (the folder holding ``session.toml``); not stored in the file."""
    scenes: dict[str, SceneEntry] = field(default_factory=dict)
    """Scenes by name."""
    sequences: dict[str, SequenceEntry] = field(default_factory=dict)
    """Sequences by name."""
    body_model: Path | None = None
    """Body model file (SMPL layout ``.npz``/``.pkl``); None = the generated test model."""
    gender: str = "neutral"
    """Body model gender: ``neutral``, ``male`` or ``female``."""
    version: int = MANIFEST_VERSION
    """Manifest format version."""

    def __post_init__(self) -> None:
        root = absolute_path(Path(self.root))
        object.__setattr__(self, "root", root)

        def fix(p: Path | str | None) -> Path | None:
            return None if p is None else absolute_path(root / p)

        object.__setattr__(self, "body_model", fix(self.body_model))
        object.__setattr__(
            self, "scenes", {k: replace(s, capture=fix(s.capture)) for k, s in self.scenes.items()}
        )
        object.__setattr__(
            self, "sequences", {k: _resolve_sequence(s, fix) for k, s in self.sequences.items()}
        )

    def active_sequences(self, force: bool = False) -> list[SequenceEntry]:
        """Sequences to run, in file order: all with ``force``, else those not marked failed."""
        return [s for s in self.sequences.values() if force or not s.failed]

    def sequence(self, name: str | None = None) -> SequenceEntry:
        """The sequence called ``name``, or the only one when None (InputError naming the file,
        with the sequences there, when there is no such sequence or more than one)."""
        return self.sequences[self._pick("sequence", list(self.sequences), name, "--seq")]

    def scene(self, name: str | None = None) -> SceneEntry:
        """The scene called ``name``, or the only one when None (InputError as :meth:`sequence`)."""
        return self.scenes[self._pick("scene", list(self.scenes), name, "--scene")]

    def _pick(self, kind: str, names: list[str], name: str | None, option: str) -> str:
        where = self.root / MANIFEST_NAME
        if name is None:
            if len(names) != 1:
                raise InputError(where, f"{len(names)} {kind}s in the session", f"name one with {option}")
            return names[0]
        if name not in names:
            raise InputError(where, f"no {kind} named '{name}'", f"{kind}s in this session: {', '.join(names) or 'none'}")
        return name


def absolute_path(path: Path) -> Path:
    """Absolute, ``..``-free path without resolving symlinks (the user's folder names stay)."""
    return Path(os.path.abspath(path))


def _resolve_sequence(seq: SequenceEntry, fix: Callable[[Path | None], Path | None]) -> SequenceEntry:
    views = {
        name: replace(
            v,
            capture=fix(v.capture),
            keypoints=fix(v.keypoints),
            masks=fix(v.masks),
            depth=fix(v.depth),
            body_prior=fix(v.body_prior),
        )
        for name, v in seq.views.items()
    }
    return replace(seq, views=views, contacts=tuple(seq.contacts))
