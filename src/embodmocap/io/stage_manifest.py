"""Resumable stages: each step's outputs are recorded with a fingerprint of what produced them.

A stage is a list of steps. Before a step runs, the stage computes its fingerprint from the
step's config, the fingerprints of its input files and those of the steps it depends on. The step
is skipped when the manifest holds the same fingerprint and every output it recorded still exists
with the content it was written with; otherwise it runs and the manifest is rewritten (atomically)
right after it, so a run interrupted between steps resumes at the first step that is not done.

Fingerprints depend on content, never on modification times or absolute paths, so a session
folder that is moved, copied (``cp -a``, ``rsync -a``, even ``cp -r``) or reached through a
relative path or a symlink redoes nothing (policy in :func:`file_digest`). Paths in the manifest
are relative to the manifest's folder.

A stage run also records its status (``running`` while it works, then ``ok``, ``failed`` or
``interrupted``) and the fingerprints of the inputs it read. A downstream stage refuses to start on
an upstream stage that failed, did not finish, whose outputs changed or whose inputs changed since
it ran (:func:`require_upstream`), naming the stage to rerun.

The manifest (``manifest.json`` next to the stage's outputs) also carries what users want to see:
the resolved config, the package version, timings and the quality figures of each step.
"""

from __future__ import annotations

import contextvars
import functools
import hashlib
import json
import logging
import os
import stat
import time
from dataclasses import asdict, dataclass, is_dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence, TypeVar

from embodmocap import __version__
from embodmocap.errors import InputError, interrupted
from embodmocap.io.atomic import remove_stale_temps, write_json

log = logging.getLogger(__name__)

#: 2: content fingerprints, per-output fingerprints, status and inputs (1: sizes + mtimes).
MANIFEST_VERSION = 2

#: Files up to this size are hashed whole; larger ones are sampled (see :func:`file_digest`).
SMALL_FILE_BYTES = 8 << 20
#: Bytes hashed at each end of a large file.
EDGE_BYTES = 1 << 20
#: Blocks hashed evenly spread between the ends of a large file, and their size.
SAMPLE_BLOCKS = 16
SAMPLE_BYTES = 64 << 10

#: Stage manifests are small; anything bigger is not one of ours.
MAX_MANIFEST_BYTES = 64 << 20

# Digests of files already hashed in this process, keyed by what changes when a file is rewritten
# (device, inode, size, mtime): stages fingerprint the same capture several times per run.
_DIGESTS: dict[tuple, str] = {}


def known_digests() -> dict[tuple, str]:
    """The file digests this process has computed (a copy), for :func:`remember_digests` in
    another process on the same files: ``embodmocap run``'s workers share them (a fresh worker
    would otherwise hash a capture's thousands of frame files again to check its upstream)."""
    return dict(_DIGESTS)


def remember_digests(digests: dict[tuple, str]) -> None:
    """Take digests another process computed (:func:`known_digests`). Safe between processes on
    one machine: a key holds the file's device, inode, size and modification time, so a rewritten
    file misses it as it would in the process that hashed it."""
    _DIGESTS.update(digests)


def file_digest(path: str | Path) -> str:
    """A content fingerprint of one file (hex, 32 characters).

    Files up to :data:`SMALL_FILE_BYTES` (8 MiB: keypoint JSON, PNG frames, CSV, npz outputs) are
    hashed whole with SHA-256. Larger files (videos, depth stacks, COLMAP databases) hash their size,
    the first and the last MiB and 16 evenly spread 64 KiB blocks: about 3 MiB read whatever the
    size, and any rewrite that changes the size, either end or one of the blocks is seen. Never the
    modification time, so faithful copies fingerprint the same. SQLite files (COLMAP's database)
    leave out the header's change counters, which every open bumps.
    """
    p = os.path.abspath(path)
    return _digest(p, os.stat(p))


def _digest(p: str, st: os.stat_result) -> str:
    """:func:`file_digest` of the file at absolute path ``p`` whose ``os.stat`` is ``st``."""
    key = (p, st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)
    hit = _DIGESTS.get(key)
    if hit is not None:
        return hit
    h = hashlib.sha256()
    size = st.st_size
    with open(p, "rb") as f:
        if size <= SMALL_FILE_BYTES:
            h.update(_without_sqlite_counters(f.read(1 << 20)))
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
        else:
            h.update(f"sampled {size}".encode())
            spans = [(0, EDGE_BYTES), (size - EDGE_BYTES, EDGE_BYTES)]
            step = (size - 2 * EDGE_BYTES - SAMPLE_BYTES) / (SAMPLE_BLOCKS + 1)
            spans += [(EDGE_BYTES + int(step * (k + 1)), SAMPLE_BYTES) for k in range(SAMPLE_BLOCKS)]
            for off, n in spans:
                f.seek(off)
                block = f.read(n)
                h.update(_without_sqlite_counters(block) if off == 0 else block)
    digest = h.hexdigest()[:32]
    _DIGESTS[key] = digest
    return digest


_SQLITE_MAGIC = b"SQLite format 3\x00"


def _without_sqlite_counters(head: bytes) -> bytes:
    """The start of a file, with an SQLite database's change counters (header bytes 24-27 and
    92-95) zeroed: SQLite bumps them whenever the file is opened for writing, even to read (COLMAP
    opens its database so), and they say nothing about the content."""
    if not head.startswith(_SQLITE_MAGIC) or len(head) < 100:
        return head
    b = bytearray(head)
    b[24:28] = bytes(4)
    b[92:96] = bytes(4)
    return bytes(b)


def path_fingerprint(path: str | Path) -> list:
    """A content fingerprint of a file or folder (see :func:`file_digest`), free of absolute paths.

    A file gives ``[name, size, digest]``; a folder the sorted ``[relative path, size, digest]`` of
    every file below it (hidden files and folders, e.g. temporary ones, left out); a missing path
    ``[name, None]``.
    """
    p = Path(path)
    if p.is_file():
        return [p.name, p.stat().st_size, file_digest(p)]
    if p.is_dir():
        out: list = []
        _folder_fingerprint(os.path.abspath(p), "", out)
        out.sort()
        return out
    return [p.name, None]


def _folder_fingerprint(folder: str, rel: str, out: list) -> None:
    """Append ``[relative path, size, digest]`` of every file below ``folder`` (absolute; ``rel``:
    its path below the fingerprinted folder, ``""`` or ending in ``/``) to ``out``, as
    :func:`path_fingerprint` lists them: hidden names left out, links to files followed, links to
    folders not entered (as ``os.walk`` does). One ``stat`` per file (``os.scandir``): a capture's
    thousands of frame files are checked at every stage's start (issue 30)."""
    with os.scandir(folder) as it:
        entries = list(it)
    for e in entries:
        if e.name.startswith("."):
            continue
        try:
            if e.is_dir(follow_symlinks=False):
                _folder_fingerprint(e.path, f"{rel}{e.name}/", out)
                continue
            st = e.stat()  # follows a link, as Path.is_file does
        except OSError:  # vanished, or a dangling link: not a file
            continue
        if stat.S_ISREG(st.st_mode):
            out.append([f"{rel}{e.name}", st.st_size, _digest(e.path, st)])


def fingerprint(*parts: Any) -> str:
    """SHA-256 of a JSON rendering of ``parts`` (dataclasses, paths, numbers, lists, dicts)."""
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=_plain).encode()).hexdigest()[:16]


def _plain(o: Any) -> Any:
    if is_dataclass(o):
        return asdict(o)
    if isinstance(o, Path):
        return str(o)
    if hasattr(o, "tolist"):
        return o.tolist()
    raise TypeError(f"cannot fingerprint {type(o).__name__}")


def _abspath(p: str | Path) -> str:
    """Absolute and ``..``-free, symlinks kept (a session reached through a link stays there)."""
    return os.path.abspath(p)


#: Called with (stage, step) each time a step is recorded or found up to date, in the process that
#: runs it: ``embodmocap run``'s workers tell the scheduler so (:mod:`embodmocap.schedule`).
STEP_LISTENERS: list[Callable[[str, str], None]] = []

# The manifests opened by the stage call in progress (see :func:`tracked_stage`).
_ACTIVE: contextvars.ContextVar[list | None] = contextvars.ContextVar("embodmocap_stage_manifests", default=None)


@dataclass(frozen=True)
class Upstream:
    """A stage whose outputs this stage reads: its manifest, its name and the command that reruns it."""

    manifest: Path
    stage: str
    command: str


class StageManifest:
    """The manifest of one stage's run: steps done, their fingerprints, status, timings and figures.

    Args:
        path: the manifest file.
        stage: the stage's name (``scene``, ``sequence``, ``calibrate``, ``motion``).
        config: the stage's config (recorded as given).
        inputs: files and folders the stage reads; their fingerprints are recorded when the stage
            finishes, so a downstream stage can tell that this one is out of date.
        upstream: stages whose outputs this one reads; checked first (:func:`require_upstream`).
        root: the session folder. Paths inside it are stored relative to the manifest's folder (so
            the session can move), paths outside it absolute. Default: the manifest's folder.
    """

    def __init__(self, path: str | Path, stage: str, config: Any, *, inputs: Iterable[str | Path | None] = (),
                 upstream: Sequence[Upstream] = (), root: str | Path | None = None) -> None:
        for up in upstream:
            require_upstream(up)
        self.path = Path(_abspath(path))
        self.stage = stage
        self.root = _abspath(root if root is not None else self.path.parent)
        self.inputs = [Path(p) for p in inputs if p is not None]
        #: Steps found up to date by :meth:`step` in this run, in order.
        self.skipped: list[str] = []
        #: This run does only some of the stage's steps by design (e.g. Stage III's registration
        #: while Stage I is unfinished): it ends ``partial``, which no downstream stage accepts.
        self.partial = False
        self.data: dict[str, Any] = {
            "version": MANIFEST_VERSION, "stage": stage, "package_version": __version__,
            "config": json.loads(json.dumps(config, default=_plain)), "status": "running",
            "steps": {}, "figures": {}, "inputs": {},
        }
        old = self._load()
        if old is not None:
            self.data["steps"] = old.get("steps", {})
            self.data["figures"] = old.get("figures", {})
        # Temporary files of an earlier run that was killed (kill -9, power loss) go first.
        remove_stale_temps(self.path.parent)
        active = _ACTIVE.get()
        if active is not None:
            active.append(self)
        # Recorded at once: a run killed from here on leaves "running", which downstream stages
        # read as "did not finish".
        self.save()

    def _load(self) -> dict | None:
        if not self.path.is_file():
            return None
        try:
            if self.path.stat().st_size > MAX_MANIFEST_BYTES:
                raise ValueError("too large")
            old = json.loads(self.path.read_text())
        except (OSError, ValueError, RecursionError):
            log.warning("%s: unreadable stage manifest, redoing every step", self.path)
            return None
        if not isinstance(old, dict) or old.get("version") != MANIFEST_VERSION or old.get("stage") != self.stage:
            return None  # another format (an older version) or another stage: redo every step
        if not isinstance(old.get("steps"), dict) or not isinstance(old.get("figures"), dict):
            return None
        return old

    # -- paths --------------------------------------------------------------------------------

    def _store(self, p: str | Path) -> str:
        """How a path is written to the manifest: relative to its folder inside the session."""
        a = _abspath(p)
        if a == self.root or a.startswith(self.root.rstrip(os.sep) + os.sep):
            return Path(os.path.relpath(a, self.path.parent)).as_posix()
        return a

    def resolve(self, stored: str) -> Path:
        """A path as written in the manifest, as a path from here (whatever the current directory)."""
        return _resolve(self.path, stored)

    # -- steps --------------------------------------------------------------------------------

    def is_current(self, step: str, fp: str) -> bool:
        """True when ``step`` was done with fingerprint ``fp`` and its outputs are as it wrote them."""
        rec = self.data["steps"].get(step)
        if not isinstance(rec, dict) or rec.get("fingerprint") != fp:
            return False
        return not _changed_outputs(self.path, rec)

    def record(self, step: str, fp: str, outputs: Iterable[str | Path], seconds: float,
               figures: dict[str, Any] | None = None) -> None:
        """Mark ``step`` done (with its outputs' fingerprints) and rewrite the manifest atomically."""
        outs = [Path(o) for o in outputs]
        self.data["steps"][step] = {
            "fingerprint": fp, "outputs": [self._store(o) for o in outs],
            "output_fingerprints": {self._store(o): fingerprint(path_fingerprint(o)) for o in outs},
            "seconds": round(float(seconds), 3), "finished": time.strftime("%Y-%m-%dT%H:%M:%S"),
        }
        if figures:
            self.data["figures"].update(figures)
        self.save()

    def figures(self) -> dict[str, Any]:
        return dict(self.data["figures"])

    def step(self, name: str, fp: str, *, force: bool = False, label: str = "") -> "StepRun":
        """One step, for ``with``: ``step.run`` says whether it must run (forced, or its fingerprint
        or outputs changed); the body calls ``step.record(outputs, figures)`` when it ran. Timing
        starts at ``with``; a skipped step is added to :attr:`skipped`; each step logs one line."""
        return StepRun(self, name, fp, force, label or self.stage)

    def finish(self, status: str, error: BaseException | str | None = None) -> None:
        """Record how the stage's run ended: ``ok`` (with its inputs' fingerprints), ``partial`` (the
        steps it was asked for done, see :attr:`partial`), ``failed`` or ``interrupted`` (with the
        error's first line)."""
        self.data["status"] = status
        self.data["ended"] = time.strftime("%Y-%m-%dT%H:%M:%S")
        if status == "ok":
            self.data.pop("error", None)
            self.data["inputs"] = {self._store(p): fingerprint(path_fingerprint(p)) for p in self.inputs}
        elif status == "partial":
            self.data.pop("error", None)
            self.data["inputs"] = {}
        else:
            msg = str(error) if error is not None else ""
            self.data["error"] = (msg.splitlines() or [type(error).__name__ if error else ""])[0][:300]
        self.save()

    def save(self) -> None:
        write_json(self.path, self.data)


class StepRun:
    """A step of a stage run (see :meth:`StageManifest.step`)."""

    def __init__(self, manifest: StageManifest, name: str, fp: str, force: bool, label: str) -> None:
        self.manifest, self.name, self.fp, self.label = manifest, name, fp, label
        self.run = force or not manifest.is_current(name, fp)
        self.recorded = False
        self.postponed = False
        self._t0 = time.perf_counter()

    def __enter__(self) -> "StepRun":
        self._t0 = time.perf_counter()
        return self

    def record(self, outputs: Iterable[str | Path], figures: dict[str, Any] | None = None) -> None:
        """Mark the step done with its outputs and figures; logs its one summary line."""
        seconds = time.perf_counter() - self._t0
        self.manifest.record(self.name, self.fp, outputs, seconds, figures)
        self.recorded = True
        log.info("%s: %s done in %.1f s%s", self.label, self.name, seconds, _brief(figures))
        _tell_listeners(self.manifest.stage, self.name)

    def postpone(self) -> "StepRun":
        """Leave the ``with`` without recording: the step is finished later (its outputs depend on
        other steps, e.g. a view placed through the other view) by :meth:`record`, timed from the
        start of the ``with``. Returns the step."""
        self.postponed = True
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if not self.run:
            self.manifest.skipped.append(self.name)
            if exc_type is None:
                _tell_listeners(self.manifest.stage, self.name)
        elif exc_type is None and not self.recorded and not self.postponed:
            raise RuntimeError(f"step {self.name} of {self.manifest.stage} ran but recorded nothing")
        return False


def _tell_listeners(stage: str, step: str) -> None:
    for fn in STEP_LISTENERS:
        fn(stage, step)


def _brief(figures: dict[str, Any] | None, limit: int = 6) -> str:
    """``: a=1, b=0.5, ...`` of a step's scalar figures, at most ``limit`` (the manifest has them all)."""
    items = [(k, v) for k, v in (figures or {}).items() if isinstance(v, (int, float, str, bool)) or v is None]
    if not items:
        return ""
    text = ", ".join(f"{k}={v}" for k, v in items[:limit])
    return f": {text}" + (f" (+{len(items) - limit} more in the manifest)" if len(items) > limit else "")


def _resolve(manifest: Path, stored: str) -> Path:
    p = Path(stored)
    return p if p.is_absolute() else Path(os.path.normpath(Path(manifest).parent / p))


def _changed_outputs(manifest: Path, rec: dict) -> list[str]:
    """Outputs of a step record that are missing or no longer hold what was written."""
    bad = []
    fps = rec.get("output_fingerprints") or {}
    for o in rec.get("outputs", []):
        q = _resolve(manifest, o)
        if not q.exists():
            bad.append(f"{o} is missing")
        elif o in fps and fingerprint(path_fingerprint(q)) != fps[o]:
            bad.append(f"{o} changed since it was written")
    return bad


def require_upstream(up: Upstream) -> None:
    """Refuse to go on when an upstream stage failed, did not finish, or is out of date.

    A manifest that does not exist or was written by an older version of the package says nothing
    about the run (outputs made by hand, or by an earlier version): the stage's own checks for
    missing outputs apply. Raises :class:`InputError` naming the upstream manifest, what is wrong
    and the command to rerun.
    """
    path = Path(up.manifest)
    fix = f"run `{up.command}` first"
    if not path.is_file():
        return
    try:
        if path.stat().st_size > MAX_MANIFEST_BYTES:
            raise ValueError("too large")
        data = json.loads(path.read_text())
    except (OSError, ValueError, RecursionError):
        raise InputError(path, f"the {up.stage} stage's manifest is unreadable", fix) from None
    if not isinstance(data, dict) or data.get("version") != MANIFEST_VERSION:
        return
    status = data.get("status")
    if status == "failed":
        raise InputError(path, f"the {up.stage} stage failed in its last run ({data.get('error', '')})", fix)
    if status != "ok":
        raise InputError(path, f"the {up.stage} stage did not finish its last run ({status})", fix)
    for step, rec in (data.get("steps") or {}).items():
        bad = _changed_outputs(path, rec) if isinstance(rec, dict) else []
        if bad:
            raise InputError(path, f"the {up.stage} stage's output {bad[0]} (step {step})", fix)
    for stored, fp in (data.get("inputs") or {}).items():
        q = _resolve(path, stored)
        if fingerprint(path_fingerprint(q)) != fp:
            raise InputError(path, f"the {up.stage} stage is out of date: its input {q} changed since it ran", fix)


F = TypeVar("F", bound=Callable[..., Any])


def tracked_stage(fn: F) -> F:
    """Decorate a stage's ``run``: every :class:`StageManifest` it opens records how the run ended
    (``ok``, ``failed`` with the error, or ``interrupted`` on Ctrl-C)."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        opened: list[StageManifest] = []
        token = _ACTIVE.set(opened)
        try:
            result = fn(*args, **kwargs)
        except BaseException as err:
            status = "interrupted" if interrupted(err) else "failed"
            for sm in opened:
                try:
                    sm.finish(status, err)
                except OSError as save_err:  # e.g. the disk is full: the original error matters
                    log.debug("could not record %s in %s: %s", status, sm.path, save_err)
            raise
        finally:
            _ACTIVE.reset(token)
        for sm in opened:
            sm.finish("partial" if sm.partial else "ok")
        return result

    return wrapper  # type: ignore[return-value]


def require_step(up: Upstream, step: str) -> None:
    """Refuse to go on unless ``step`` of the upstream stage is recorded with its outputs as written
    (the stage itself may still be running: the caller knows that step was done in this run, as
    ``embodmocap run``'s scheduler does). Raises :class:`InputError` naming the manifest."""
    path = Path(up.manifest)
    try:
        rec = (json.loads(path.read_text()).get("steps") or {}).get(step)
    except (OSError, ValueError, AttributeError, RecursionError):
        rec = None
    bad = _changed_outputs(path, rec) if isinstance(rec, dict) else [f"its {step} step is not done"]
    if bad:
        raise InputError(path, f"the {up.stage} stage: {bad[0]}", f"run `{up.command}` first")


def require_sequence_stages(lay: Any, entry: Any) -> None:
    """Refuse a sequence whose outputs cannot be trusted: any of its stages (its scene's Stage I,
    then Stages II-IV) failed, did not finish, or is out of date (:func:`require_upstream`).

    Args:
        lay: the session's :class:`embodmocap.io.layout.SessionLayout`.
        entry: the sequence's entry of ``session.toml`` (``name``, ``scene``).
    """
    sl = lay.sequence(entry.name)
    for path, stage, target in ((lay.scene(entry.scene).manifest, "scene", f"--scene {entry.scene}"),
                                (sl.manifest, "sequence", f"--seq {entry.name}"),
                                (sl.calibrate_manifest, "calibrate", f"--seq {entry.name}"),
                                (sl.motion_manifest, "motion", f"--seq {entry.name}")):
        require_upstream(Upstream(path, stage, f"embodmocap {stage} {lay.root} {target}"))
