"""The command line's conventions: --version, -q/-v, --log-file, --config FILE.toml (the command
line wins; unknown keys are one clear error), through the real ``embodmocap`` entry point."""

from __future__ import annotations

import logging
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from embodmocap import __version__
from embodmocap.cli import _parse, main
from embodmocap.cli_options import GlobalOptions, global_options

EXAMPLE = Path(__file__).resolve().parents[1] / "docs" / "config.example.toml"


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "embodmocap.cli", *args], capture_output=True, text=True)


def test_version_prints_the_package_version():
    out = run_cli("--version")
    assert out.returncode == 0 and out.stdout.strip() == f"embodmocap {__version__}"


def test_quiet_silences_info_lines_and_verbose_shows_debug(tmp_path):
    plain = run_cli("body", "make-test-model", str(tmp_path / "a.npz"))
    quiet = run_cli("-q", "body", "make-test-model", str(tmp_path / "b.npz"))
    verbose = run_cli("body", "make-test-model", str(tmp_path / "c.npz"), "--verbose")
    assert plain.returncode == quiet.returncode == verbose.returncode == 0
    assert " INFO embodmocap.body.testmodel: wrote test body model" in plain.stderr
    assert "INFO" not in quiet.stderr and quiet.stderr.strip() == ""
    assert (tmp_path / "b.npz").is_file()  # quiet, but the work is done
    assert " INFO embodmocap.body.testmodel: wrote test body model" in verbose.stderr
    # -v and -q are taken anywhere on the line; -v means DEBUG, --debug alone also DEBUG.
    assert global_options(["run", "-v", "S"]) == (["run", "S"], GlobalOptions(level=logging.DEBUG))
    assert global_options(["-q", "run"])[1].level == logging.WARNING
    assert global_options(["--debug", "run"])[1].level == logging.DEBUG


def test_log_file_keeps_the_lines_even_when_quiet(tmp_path):
    log = tmp_path / "logs" / "run.log"
    out = run_cli("-q", "--log-file", str(log), "body", "make-test-model", str(tmp_path / "a.npz"))
    assert out.returncode == 0 and out.stderr.strip() == ""
    text = log.read_text()
    assert "INFO embodmocap.body.testmodel: wrote test body model" in text and str(tmp_path / "a.npz") in text
    # A failure's one line goes to the log file too, with the same exit status as without it.
    bad = run_cli(f"--log-file={log}", "synth", str(tmp_path / "s"), "--width", "3000")
    assert bad.returncode == 2 and bad.stderr.startswith("error:") and "RGB size" in bad.stderr
    assert "ERROR embodmocap: error:" in log.read_text() and "RGB size" in log.read_text()


def test_config_file_fills_settings_and_the_command_line_wins(tmp_path):
    settings = tmp_path / "settings.toml"
    settings.write_text("seed = 3\n")
    assert main(["body", "make-test-model", str(tmp_path / "file.npz"), "--config", str(settings)]) == 0
    assert main(["body", "make-test-model", str(tmp_path / "flag.npz"), "--seed", "3"]) == 0
    assert main(["body", "make-test-model", str(tmp_path / "wins.npz"), "--config", str(settings), "--seed", "0"]) == 0
    assert main(["body", "make-test-model", str(tmp_path / "zero.npz")]) == 0
    file, flag, wins, zero = (np.load(tmp_path / f"{n}.npz") for n in ("file", "flag", "wins", "zero"))
    assert np.array_equal(file["v_template"], flag["v_template"])  # the file's seed reached the command
    assert not np.array_equal(file["v_template"], zero["v_template"])
    assert np.array_equal(wins["v_template"], zero["v_template"])  # the command line's seed won


def test_config_file_maps_onto_stage_settings(tmp_path):
    settings = tmp_path / "settings.toml"
    settings.write_text("include_failed = true\n[scene]\nvoxel_m_indoor = 0.03\n"
                        "[motion.smplify]\nphase1_iterations = 7\n[calibrate]\n")
    run = _parse(["run", "S"], settings)
    assert run.config.scene.voxel_m_indoor == 0.03 and run.config.include_failed
    assert run.config.motion.smplify.phase1_iterations == 7
    assert run.session == Path("S")
    wins = _parse(["run", "S", "--scene.voxel-m-indoor", "0.05"], settings)
    assert wins.config.scene.voxel_m_indoor == 0.05 and wins.config.motion.smplify.phase1_iterations == 7
    # The same file serves the stage commands: each reads its own table.
    assert _parse(["scene", "S"], settings).config.voxel_m_indoor == 0.03
    assert _parse(["motion", "S"], settings).config.smplify.phase1_iterations == 7
    # The defaults are untouched without a file.
    assert _parse(["run", "S"], None).config.scene.voxel_m_indoor != 0.03


def test_example_settings_file_is_valid_for_run_and_every_stage():
    for cmd in ("run", "scene", "sequence", "calibrate", "motion"):
        _parse([cmd, "S"], EXAMPLE)


@pytest.mark.parametrize("text, words", [
    ("[scene]\nvoxl_m_indoor = 0.02\n", ["unknown key 'scene.voxl_m_indoor'", "did you mean 'scene.voxel_m_indoor'"]),
    ("[motion.smplify]\nphase1_iteration = 3\n", ["'motion.smplify.phase1_iteration'", "'motion.smplify.phase1_iterations'"]),
    ("[scene]\nvoxel_m_indoor = 'big'\n", ["'scene.voxel_m_indoor'", "expected a number"]),
    ("[scene\n", ["not valid TOML"]),
])
def test_bad_settings_file_is_one_line_naming_file_and_key(tmp_path, capsys, text, words):
    settings = tmp_path / "bad.toml"
    settings.write_text(text)
    rc = main(["run", str(tmp_path / "S"), "--config", str(settings)])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith(f"error: {settings}:") and len(err.strip().splitlines()) == 1
    for w in words:
        assert w in err


def test_missing_settings_file_and_missing_value(tmp_path, capsys):
    assert main(["run", str(tmp_path), "--config", str(tmp_path / "nope.toml")]) == 2
    assert "nope.toml: settings file not found" in capsys.readouterr().err
    assert main(["run", str(tmp_path), "--config"]) == 2
    assert "--config needs a path" in capsys.readouterr().err
