"""The ``embodmocap`` command: one subcommand per job, generated from config dataclasses by tyro.

Every option's help text is the docstring of its dataclass field. Errors caused by input are shown
as one line (what, where, what to do); ``--debug`` anywhere on the command line shows the traceback.
"""

from __future__ import annotations

import logging
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Union

import tyro

from embodmocap.errors import EmbodMocapError
from embodmocap.scene.config import SceneConfig
from embodmocap.calibrate.stage import CalibrateConfig
from embodmocap.sequence.config import SequenceConfig
from embodmocap.synth.config import SynthConfig

log = logging.getLogger("embodmocap")


@dataclass(frozen=True)
class Synth:
    """Write a synthetic dual-iPhone session with ground truth (the built-in test studio)."""

    out: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="OUT")]
    """Session folder to create."""
    config: Annotated[SynthConfig, tyro.conf.arg(name="")] = SynthConfig()
    """Studio settings."""

    def run(self) -> int:
        from embodmocap.synth.studio import synthesize

        res = synthesize(self.config, self.out)
        print(f"synthetic session: {res.root} ({res.frames_rendered} frames in {res.seconds_taken:.1f} s)")
        return 0


@dataclass(frozen=True)
class Inspect:
    """Print what a capture or a session holds and list every problem found."""

    path: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="PATH")]
    """A capture folder (Stray Scanner, Spectacular AI, Record3D) or a session folder."""

    def run(self) -> int:
        from embodmocap.io.inspect import inspect_path

        text, problems = inspect_path(self.path)
        print(text)
        return 1 if problems else 0


@dataclass(frozen=True)
class Demo:
    """Run the built-in demo: synthesise a session, inspect it, and run the stages built so far (I, II, III)."""

    out: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="OUT")] = Path("demo_out")
    """Folder for the demo session (replaced if it holds an earlier demo)."""
    seconds: float = 6.0
    """Performance length of the demo sequence, seconds."""
    seed: int = 0
    """Random seed of the demo session."""

    def run(self) -> int:
        import shutil

        from embodmocap.io.inspect import inspect_path
        from embodmocap.synth.studio import synthesize

        if (self.out / "session.toml").exists() and (self.out / "ground_truth").exists():
            shutil.rmtree(self.out)  # an earlier demo's output: ours to replace
        elif self.out.exists() and any(self.out.iterdir()):
            raise EmbodMocapError(f"{self.out}: folder exists and is not a demo session (choose another OUT)")
        res = synthesize(SynthConfig(seed=self.seed, seconds=self.seconds, scene_seconds=15.0), self.out)
        text, problems = inspect_path(self.out)
        print(text)
        print(f"\ndemo session written to {res.root} in {res.seconds_taken:.1f} s")
        if problems:
            return 1
        from embodmocap.scene.stage import run as run_scene

        from embodmocap.sequence.stage import run as run_sequence

        scene = run_scene(SceneConfig(), self.out)
        print(f"\nStage I (scene): {scene.layout.root}")
        for k, v in scene.figures.items():
            print(f"  {k}: {v}")
        seq = run_sequence(SequenceConfig(), self.out)
        print(f"\nStage II (sequence {seq.name}): {seq.layout.root}")
        print(f"  sync contact sheets: {seq.layout.root / 'sync_v1.png'}, {seq.layout.root / 'sync_v2.png'}")
        for k, v in seq.figures.items():
            print(f"  {k}: {v}")
        from embodmocap.calibrate.stage import run as run_calibrate

        cal = run_calibrate(CalibrateConfig(), self.out)
        print(f"\nStage III (calibrate {cal.name}): {self.out / 'sequences' / cal.name / 'calibration.json'}")
        for v, view in cal.report["views"].items():
            print(f"  {v}: registered {100 * view['registered_fraction']:.0f}% of sampled frames; refinement moved "
                  f"the view {100 * view['refine_shift_m']:.1f} cm / {view['refine_yaw_deg']:.2f} deg")
        for w in cal.report.get("warnings", []):
            print(f"  warning: {w}")
        return 0


@dataclass(frozen=True)
class Scene:
    """Stage I: build the metric, Z-up scene mesh and sparse model of a session's scene capture."""

    session: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="SESSION")]
    """Session folder (holds session.toml)."""
    scene: str | None = None
    """Scene to process; needed only when the session has several."""
    force: bool = False
    """Redo every step even when its outputs are up to date."""
    config: Annotated[SceneConfig, tyro.conf.arg(name="")] = SceneConfig()
    """Stage settings."""

    def run(self) -> int:
        from embodmocap.scene.stage import run

        out = run(self.config, self.session, self.scene, force=self.force)
        print(f"scene {out.name}: {out.layout.root}")
        for k, v in out.figures.items():
            print(f"  {k}: {v}")
        return 0


@dataclass(frozen=True)
class Sequence:
    """Stage II: sync, slice and observe the performer in both views of a sequence."""

    session: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="SESSION")]
    """Session folder (holds session.toml)."""
    seq: str | None = None
    """Sequence to process; needed only when the session has several."""
    force: bool = False
    """Redo every step even when its outputs are up to date."""
    config: Annotated[SequenceConfig, tyro.conf.arg(name="")] = SequenceConfig()
    """Stage settings."""

    def run(self) -> int:
        from embodmocap.sequence.stage import run

        out = run(self.config, self.session, self.seq, force=self.force)
        print(f"sequence {out.name}: {out.layout.root}")
        for k, v in out.figures.items():
            print(f"  {k}: {v}")
        return 0


@dataclass(frozen=True)
class Calibrate:
    """Stage III: put both moving views in the scene's world (registration + joint refinement)."""

    session: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="SESSION")]
    """Session folder (holds session.toml)."""
    seq: str | None = None
    """Sequence to process; needed only when the session has several."""
    force: bool = False
    """Redo every step even when its outputs are up to date."""
    config: Annotated[CalibrateConfig, tyro.conf.arg(name="")] = CalibrateConfig()
    """Stage settings."""

    def run(self) -> int:
        from embodmocap.calibrate.stage import run

        out = run(self.config, self.session, self.seq, force=self.force)
        print(f"sequence {out.name}: calibration in {self.session / 'sequences' / out.name / 'calibration.json'}")
        for v, view in out.report["views"].items():
            print(f"  {v}: registered {100 * view['registered_fraction']:.0f}%, refinement moved it "
                  f"{100 * view['refine_shift_m']:.1f} cm / {view['refine_yaw_deg']:.2f} deg")
        for w in out.report.get("warnings", []):
            print(f"  warning: {w}")
        return 0


@dataclass(frozen=True)
class BodyMakeTestModel:
    """Generate the built-in body model (SMPL file layout; needs no licensed file)."""

    out: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="OUT")]
    """Output .npz path."""
    seed: int = 0
    """Random seed of the generated model (0 is the one the demo and tests use)."""

    def run(self) -> int:
        from embodmocap.body.testmodel import make_test_model_cli

        make_test_model_cli(self.out, seed=self.seed)
        print(f"wrote {self.out}")
        return 0


@dataclass(frozen=True)
class SessionImport:
    """Create session.toml from a CSV/XLSX sheet in the paper release's layout."""

    sheet: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="SHEET")]
    """The .csv or .xlsx sheet (columns scene_folder, seq_name, in_door, v1_start, v2_start, ...)."""
    session: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="SESSION")]
    """Session folder (relative scene folders are resolved against it)."""
    force: bool = False
    """Overwrite an existing session.toml."""
    capture_pattern: str = "{scene_folder}/{seq_name}/raw{index}"
    """Where each view's capture lives, relative to the session; placeholders {scene_folder},
    {scene}, {seq_name}, {view} (v1/v2) and {index} (1/2). The default is the release's layout."""
    contact_sheet: Path | None = None
    """For a CSV sheet: a second CSV with the `contact` table (columns scene, contacts)."""
    check: bool = True
    """Refuse to write a manifest whose capture folders are missing (--no-check writes it anyway)."""

    def run(self) -> int:
        from embodmocap.io.sheet_import import import_sheet_cli

        path = import_sheet_cli(
            self.sheet, self.session, capture_pattern=self.capture_pattern,
            contact_sheet=self.contact_sheet, force=self.force, check=self.check,
        )
        print(f"wrote {path}")
        return 0


#: The subcommands; tyro turns each dataclass (and its field docstrings) into options and help.
Commands = Union[
    Annotated[Demo, tyro.conf.subcommand("demo")],
    Annotated[Synth, tyro.conf.subcommand("synth")],
    Annotated[Inspect, tyro.conf.subcommand("inspect")],
    Annotated[Scene, tyro.conf.subcommand("scene")],
    Annotated[Sequence, tyro.conf.subcommand("sequence")],
    Annotated[Calibrate, tyro.conf.subcommand("calibrate")],
    Annotated[BodyMakeTestModel, tyro.conf.subcommand("body:make-test-model")],
    Annotated[SessionImport, tyro.conf.subcommand("session:import")],
]


def _setup_logging(debug: bool) -> None:
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s", "%H:%M:%S"))
    log.addHandler(handler)
    log.setLevel(logging.DEBUG if debug else logging.INFO)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv
    argv = [a for a in argv if a != "--debug"]
    # "body make-test-model" and "session import" read naturally as two words.
    if len(argv) >= 2 and argv[0] in ("body", "session"):
        argv = [f"{argv[0]}:{argv[1]}"] + argv[2:]
    _setup_logging(debug)
    try:
        cmd = tyro.cli(
            Commands, args=argv, prog="embodmocap",
            description="EmbodMocap: 4D human-scene capture from two handheld iPhones.",
        )
        return int(cmd.run())
    except EmbodMocapError as err:
        if debug:
            raise
        print(f"error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted: run the same command again to resume", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
