"""The ``embodmocap`` command: one subcommand per job, generated from config dataclasses by tyro.

Every option's help text is the docstring of its dataclass field. Every failure is shown as one line
(what, where, what to do): input errors, file system errors (disk full, permission denied) and,
as a last resort, unexpected ones; ``--debug`` anywhere on the command line shows the traceback.
Commands that write into a session check that they can before any work starts.
"""

from __future__ import annotations

import logging
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal, Union

import tyro

from embodmocap.cli_options import global_options
from embodmocap.errors import EmbodMocapError, interrupted, os_error_line, stop_watching_interrupts, watch_interrupts
from embodmocap.scene.config import SceneConfig
from embodmocap.batch.commands import Batch, Catalog
from embodmocap.calibrate.config import CalibrateConfig
from embodmocap.cli_tools import BodyMakeTestModel, SessionImport
from embodmocap.device import Device
from embodmocap.check.config import CheckConfig
from embodmocap.evaluate.benchmark import BenchmarkConfig
from embodmocap.evaluate.report import ReportConfig
from embodmocap.evaluate.session import EvaluateConfig
from embodmocap.export.config import ExportConfig
from embodmocap.motion.config import MotionConfig
from embodmocap.mono.commands import Mono
from embodmocap.pipeline import PipelineConfig
from embodmocap.robot.commands import RobotRetarget
from embodmocap.sequence.config import SequenceConfig
from embodmocap.skills.commands import Skills
from embodmocap.sim.commands import SimCheck, SimEval, SimTrain
from embodmocap.synth.config import SynthConfig
from embodmocap.viz.config import RenderConfig, ViewerConfig

log = logging.getLogger("embodmocap")


@dataclass(frozen=True)
class Synth:
    """Write a synthetic dual-iPhone session (one iPhone with ``--views 1``) with ground truth (the built-in test studio)."""

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
        from embodmocap.check.inspect import inspect_path

        text, problems = inspect_path(self.path)
        print(text)
        return 1 if problems else 0


@dataclass(frozen=True)
class Check:
    """Is each take usable? Sync, performer in both views, angle between the views, registration to
    the scene and tracking jumps on a sample of frames; verdict usable / usable with warnings /
    reshoot (exit status 0 / 1 / 2; 2 also for an input error)."""

    session: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="SESSION")]
    """Session folder (holds session.toml); the scene's Stage I outputs are needed for the
    registration, view-angle and geometric-sync checks."""
    seq: str | None = None
    """Check only this sequence (default: every sequence of the session)."""
    json: bool = False
    """Print the result as JSON (for machines) instead of text."""
    config: Annotated[CheckConfig, tyro.conf.arg(name="")] = CheckConfig()
    """Check settings."""

    def run(self) -> int:
        import json as _json

        from embodmocap.check.core import check_session, exit_status, format_text

        results = check_session(self.config, self.session, self.seq)
        if self.json:
            print(_json.dumps({"session": str(self.session), "exit_status": exit_status(results),
                               "sequences": [r.to_json() for r in results]}, indent=2))
        else:
            print(format_text(results))
        return exit_status(results)


@dataclass(frozen=True)
class Demo:
    """Run the built-in demo: synthesise a session, inspect it, run every stage, evaluate it against
    its ground truth and write the report."""

    out: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="OUT")] = Path("demo_out")
    """Folder for the demo session (replaced if it holds an earlier demo)."""
    seconds: float = 6.0
    """Performance length of the demo sequence, seconds."""
    seed: int = 0
    """Random seed of the demo session."""

    def run(self) -> int:
        import shutil

        from embodmocap.check.inspect import inspect_path
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
        status = Run(self.out).run()
        if status != 0:
            return status
        status = Evaluate(self.out).run()
        if status == 0:
            status = Report(self.out).run()
        return status


@dataclass(frozen=True)
class Run:
    """Run every stage for the scene(s) and every sequence of a session, in order (resumable)."""

    session: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="SESSION")]
    """Session folder (holds session.toml)."""
    force: bool = False
    """Redo every step even when its outputs are up to date."""
    workers: int = 0
    """Stages run at once, each in a worker process (Stage II beside Stage I, Stage III's registration
    beside Stage I's mesh, the rest of Stage III beside Stage I's last steps); 0 = the usable cores, at most 2; 1 = one after the other in this process.
    The outputs are the same; the memory in use is the sum of the processes."""
    config: Annotated[PipelineConfig, tyro.conf.arg(name="")] = PipelineConfig()
    """Settings of every stage."""

    def run(self) -> int:
        from embodmocap.pipeline import run_session
        from embodmocap.progress import is_quiet

        quiet = is_quiet()  # -q: nothing on stdout; a failure's lines still on stderr
        res = run_session(self.config, self.session, force=self.force, workers=self.workers,
                          on_progress=None if quiet else lambda m: print(m, flush=True))
        if not quiet:
            print()
        for r in res.runs:
            line = f"  {r.target:<24} {r.stage:<10} {r.status:<7} {r.seconds:7.1f} s"
            if not quiet or r.error:
                print(line + (f"  {r.error}" if r.error else ""), file=sys.stderr if quiet else sys.stdout)
        if not res.ok:
            print(f"{len(res.failed())} stage(s) failed; fix the cause and run the same command again to resume",
                  file=sys.stderr if quiet else sys.stdout)
            return 1
        if not quiet:
            print(f"all stages done: {res.session}")
        return 0


@dataclass(frozen=True)
class Evaluate:
    """Quality metrics of every fitted sequence (and errors against ground truth when the session has
    it), written to SESSION/evaluation.json."""

    session: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="SESSION")]
    """Session folder (holds session.toml)."""
    config: Annotated[EvaluateConfig, tyro.conf.arg(name="")] = EvaluateConfig()
    """What to compute."""

    def run(self) -> int:
        from embodmocap.evaluate.session import evaluate_session
        from embodmocap.io.layout import SessionLayout

        result = evaluate_session(self.session, self.config)
        for name, m in result["scene"].items():
            print(f"scene {name}: " + ", ".join(f"{k} {v}" for k, v in m.items()))
        for name, m in result["sequences"].items():
            print(f"sequence {name}:")
            for k, v in m.items():
                print(f"  {k}: {v}")
        print(f"evaluation: {SessionLayout(self.session).evaluation}")
        return 0


@dataclass(frozen=True)
class Report:
    """Write SESSION/report.html (self-contained) and report.md: metrics, floor plan, errors over time,
    stage residuals and timings, sync contact sheets, the fitted body over frames of each view."""

    session: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="SESSION")]
    """Session folder (holds session.toml)."""
    config: Annotated[ReportConfig, tyro.conf.arg(name="")] = ReportConfig()
    """What the report shows."""

    def run(self) -> int:
        from embodmocap.evaluate.report import write_report

        html_path, md_path = write_report(self.session, self.config)
        print(f"report: {html_path} (Markdown: {md_path})")
        return 0


@dataclass(frozen=True)
class View:
    """Open the interactive 3D viewer (viser, in the browser): scene, animated body, camera frusta
    with their images, keypoints, the performer's path; Z up."""

    session: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="SESSION")]
    """Session folder (holds session.toml)."""
    seq: str | None = None
    """Sequence to show; needed only when the session has several."""
    config: Annotated[ViewerConfig, tyro.conf.arg(name="")] = ViewerConfig()
    """Viewer settings."""

    def run(self) -> int:
        from embodmocap.viz.viewer import view_cli

        view_cli(self.session, _sequence_name(self.session, self.seq), self.config)
        return 0


@dataclass(frozen=True)
class Render:
    """Render MP4 videos of the fitted body drawn over each view's RGB frames, and both views side by side."""

    session: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="SESSION")]
    """Session folder (holds session.toml)."""
    seq: str | None = None
    """Sequence to render; needed only when the session has several."""
    config: Annotated[RenderConfig, tyro.conf.arg(name="")] = RenderConfig()
    """Render settings."""

    def run(self) -> int:
        from embodmocap.viz.render import render_sequence

        for path in render_sequence(self.session, _sequence_name(self.session, self.seq), self.config):
            print(f"wrote {path}")
        return 0


@dataclass(frozen=True)
class Benchmark:
    """Synthesise N sessions and reproduce the paper's two tables on them (capture methods: monocular,
    single view v1 / v2, dual; loss ablation), written to OUT/benchmark.json and OUT/benchmark.md."""

    out: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="OUT")]
    """Folder for the synthetic sessions and the tables (sessions already there are reused)."""
    config: Annotated[BenchmarkConfig, tyro.conf.arg(name="")] = BenchmarkConfig()
    """What to synthesise and compare."""

    def run(self) -> int:
        from embodmocap.evaluate.benchmark import run_benchmark, summary

        result = run_benchmark(self.out, self.config)
        print(summary(result))
        print(f"tables: {self.out / 'benchmark.md'}; every row: {self.out / 'benchmark.json'}")
        return 0 if all("error" not in r for r in result["rows"]) else 1


@dataclass(frozen=True)
class Export:
    """Export a fitted sequence for other tools (AMASS npz, BVH, GLB, MimicKit, CSV, MuJoCo MJCF,
    OpenSim TRC, SMPL-X npz)."""

    session: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="SESSION")]
    """Session folder (holds session.toml)."""
    to: Literal["amass", "bvh", "glb", "mimickit", "csv", "robot", "mjcf", "training", "trc", "smplx"]
    """Format to write (training: every sequence unless --seq; docs/training.md)."""
    seq: str | None = None
    """Sequence to export; needed only when the session has several."""
    out: Path | None = None
    """Output file (folder for mimickit, mjcf and training); default SESSION/sequences/SEQ/export/
    (training: SESSION/training/)."""
    config: Annotated[ExportConfig, tyro.conf.arg(name="")] = ExportConfig()
    """Export settings."""

    def run(self) -> int:
        from embodmocap.export import export_sequence

        seq = self.seq if self.to == "training" else _sequence_name(self.session, self.seq)
        path = export_sequence(self.session, seq, self.to, self.out, config=self.config)
        print(f"wrote {path}")
        return 0


def _sequence_name(session: Path, seq: str | None) -> str:
    """The sequence to work on: ``seq``, or the session's only one."""
    from embodmocap.io.layout import SessionLayout
    from embodmocap.io.manifest import load_manifest

    return load_manifest(SessionLayout(session).manifest).sequence(seq).name


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
        from embodmocap.io.layout import SessionLayout

        out = run(self.config, self.session, self.seq, force=self.force)
        print(f"sequence {out.name}: calibration in {SessionLayout(self.session).sequence(out.name).calibration}")
        for v, view in out.report["views"].items():
            print(f"  {v}: registered {100 * view['registered_fraction']:.0f}%, refinement moved it "
                  f"{100 * view['refine_shift_m']:.1f} cm / {view['refine_yaw_deg']:.2f} deg")
        for w in out.report.get("warnings", []):
            print(f"  warning: {w}")
        return 0


@dataclass(frozen=True)
class Motion:
    """Stage IV: triangulate, fit world-space SMPL motion (two-phase SMPLify) and align it to contact markers."""

    session: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="SESSION")]
    """Session folder (holds session.toml)."""
    seq: str | None = None
    """Sequence to process; needed only when the session has several."""
    force: bool = False
    """Redo every step even when its outputs are up to date."""
    device: Device | None = None
    """Where the fit runs: ``auto``, ``cpu`` or ``cuda`` (replaces ``--smplify.device`` when given;
    ``cuda`` without a CUDA device is an error)."""
    config: Annotated[MotionConfig, tyro.conf.arg(name="")] = MotionConfig()
    """Stage settings."""

    def run(self) -> int:
        from embodmocap.device import motion_on_device
        from embodmocap.motion.stage import run

        out = run(motion_on_device(self.config, self.device), self.session, self.seq, force=self.force)
        print(f"sequence {out.name}: motion in {out.layout.smpl_world}")
        for k, v in out.figures.items():
            print(f"  {k}: {v}")
        return 0


#: The subcommands; tyro turns each dataclass (and its field docstrings) into options and help.
Commands = Union[
    Annotated[Demo, tyro.conf.subcommand("demo")],
    Annotated[Synth, tyro.conf.subcommand("synth")],
    Annotated[Inspect, tyro.conf.subcommand("inspect")],
    Annotated[Check, tyro.conf.subcommand("check")],
    Annotated[Scene, tyro.conf.subcommand("scene")],
    Annotated[Sequence, tyro.conf.subcommand("sequence")],
    Annotated[Calibrate, tyro.conf.subcommand("calibrate")],
    Annotated[Motion, tyro.conf.subcommand("motion")],
    Annotated[Mono, tyro.conf.subcommand("mono")],
    Annotated[Run, tyro.conf.subcommand("run")],
    Annotated[Batch, tyro.conf.subcommand("batch")],
    Annotated[Catalog, tyro.conf.subcommand("catalog")],
    Annotated[Evaluate, tyro.conf.subcommand("evaluate")],
    Annotated[Report, tyro.conf.subcommand("report")],
    Annotated[Benchmark, tyro.conf.subcommand("benchmark")],
    Annotated[Export, tyro.conf.subcommand("export")],
    Annotated[View, tyro.conf.subcommand("view")],
    Annotated[Render, tyro.conf.subcommand("render")],
    Annotated[BodyMakeTestModel, tyro.conf.subcommand("body:make-test-model")],
    Annotated[SessionImport, tyro.conf.subcommand("session:import")],
    Annotated[RobotRetarget, tyro.conf.subcommand("robot:retarget")],
    Annotated[SimCheck, tyro.conf.subcommand("sim:check")],
    Annotated[SimTrain, tyro.conf.subcommand("sim:train")],
    Annotated[SimEval, tyro.conf.subcommand("sim:eval")],
    Annotated[Skills, tyro.conf.subcommand("skills")],
]


def _preflight(cmd) -> None:
    """Before a command that writes into a session: writable folders, stale temporary files gone."""
    from embodmocap.io.preflight import check_writable, prepare_session

    device = cmd.device if isinstance(cmd, Motion) else cmd.config.device if isinstance(cmd, Run) else None
    if device is not None:  # `--device cuda` without CUDA: one clear error before anything else
        from embodmocap.device import resolve_device

        resolve_device(device)
    if isinstance(cmd, (Scene, Sequence, Calibrate, Motion, Run, Evaluate, Report, Export, Render, RobotRetarget, SimCheck)):
        prepare_session(cmd.session)
    if isinstance(cmd, Mono):
        prepare_session(cmd.session)
    if isinstance(cmd, Skills):
        prepare_session(cmd.session)
    from embodmocap.io.layout import SessionLayout

    # The training export checks each sequence it exports itself (all of them without --seq).
    if isinstance(cmd, (Export, Render, RobotRetarget)) and SessionLayout(cmd.session).manifest.is_file() \
            and not (isinstance(cmd, Export) and cmd.to == "training"):
        _require_stages_done(cmd.session, cmd.seq)
    if isinstance(cmd, Export) and cmd.out is not None:
        folder = cmd.out if cmd.to in ("mimickit", "robot", "mjcf", "training") else cmd.out.parent
        while not folder.exists() and folder != folder.parent:
            folder = folder.parent  # the export creates the missing folders
        check_writable(folder, "export folder")


def _require_stages_done(session: Path, seq: str | None) -> None:
    """Export and render read every stage's outputs of a sequence: none may have failed or be stale."""
    from embodmocap.io.layout import SessionLayout
    from embodmocap.io.manifest import load_manifest
    from embodmocap.io.stage_manifest import require_sequence_stages

    lay = SessionLayout(session)
    require_sequence_stages(lay, load_manifest(lay.manifest).sequence(seq))


def main(argv: list[str] | None = None) -> int:
    """The ``embodmocap`` command. Exit status: 0 done, 1 the command's own failure (a failed stage,
    problems found), 2 bad input or a file system error, 3 an unexpected error, 130 interrupted."""
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        argv, opts = global_options(argv)
    except EmbodMocapError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    if opts.version:
        from embodmocap import __version__

        print(f"embodmocap {__version__}")
        return 0
    # "body make-test-model" and "session import" read naturally as two words.
    if len(argv) >= 2 and argv[0] in ("body", "session", "robot", "sim"):
        argv = [f"{argv[0]}:{argv[1]}"] + argv[2:]
    from embodmocap import logs

    try:  # a --log-file that cannot be written is refused before any work
        if opts.log_file is not None:
            opts.log_file.parent.mkdir(parents=True, exist_ok=True)
            open(opts.log_file, "a").close()
    except OSError as err:
        print(f"error: --log-file: {os_error_line(err)}", file=sys.stderr)
        return 2
    previous = watch_interrupts()
    from embodmocap.progress import set_quiet

    was_quiet = set_quiet(opts.level > logging.INFO)  # -q: no progress bars or lines, no routine output
    try:
        with logs.command_logging(log, opts.level, opts.log_file):
            return _run(argv, opts)
    finally:
        set_quiet(was_quiet)
        stop_watching_interrupts(previous)


def _fail(line: str) -> None:
    from embodmocap.logs import say_error

    say_error(log, line)


def _parse(argv: list[str], settings: Path | None):
    """The command object: tyro on ``argv``, with the settings file's values as defaults."""
    kwargs = {}
    if settings is not None:
        from embodmocap.cli_settings import command_default, read_settings, subcommands

        data = read_settings(settings)
        names = subcommands(Commands)
        name = next((a for a in argv if not a.startswith("-")), None)
        if name not in names:
            raise EmbodMocapError(f"--config {settings}: name the command too (e.g. embodmocap run SESSION "
                                  f"--config {settings})")
        kwargs["default"] = command_default(names[name], name, data, settings)
    return tyro.cli(Commands, args=argv, prog="embodmocap",
                    description="EmbodMocap: 4D human-scene capture from two handheld iPhones.", **kwargs)


def _run(argv: list[str], opts) -> int:
    debug = opts.debug
    try:
        cmd = _parse(argv, opts.config)
        _preflight(cmd)
        return int(cmd.run())
    except EmbodMocapError as err:
        if interrupted(err):  # e.g. a missing-extra error made by an import that Ctrl-C cut short
            _fail("interrupted: run the same command again to resume")
            return 130
        if debug:
            raise
        _fail(f"error: {err}")
        return 2
    except KeyboardInterrupt:
        _fail("interrupted: run the same command again to resume")
        return 130
    except OSError as err:  # disk full, permission denied, read-only file system, ...
        if debug:
            raise
        _fail(f"error: {os_error_line(err)}")
        return 2
    except Exception as err:  # noqa: BLE001 - a bug or an unforeseen input: still one line
        if interrupted(err):  # Ctrl-C during an import of a compiled module (see errors.watch_interrupts)
            _fail("interrupted: run the same command again to resume")
            return 130
        if debug:
            raise
        first = (str(err).splitlines() or [""])[0][:300]
        _fail(f"error: unexpected {type(err).__name__}: {first} (run the same command with --debug for the "
              "traceback, and report it)")
        return 3


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
