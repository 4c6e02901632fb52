"""The command line: generated help, one-line errors, the body and inspect commands."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from embodmocap.cli import main


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "embodmocap.cli", *args], capture_output=True, text=True)


def test_help_documents_every_synth_option():
    from dataclasses import fields

    from embodmocap.synth.config import SynthConfig

    out = run_cli("synth", "--help")
    assert out.returncode == 0
    for f in fields(SynthConfig):
        assert "--" + f.name.replace("_", "-") in out.stdout, f.name


def test_inspect_missing_path_is_one_clear_line(tmp_path):
    out = run_cli("inspect", str(tmp_path / "nope"))
    assert out.returncode == 1
    assert "does not exist" in out.stdout
    assert "Traceback" not in out.stdout + out.stderr


def test_inspect_unknown_folder_names_the_formats(tmp_path):
    (tmp_path / "x.txt").write_text("hello")
    out = run_cli("inspect", str(tmp_path))
    assert out.returncode == 1
    assert "Stray Scanner" in out.stdout and str(tmp_path) in out.stdout


def test_bad_synth_option_is_one_line_error(tmp_path, capsys):
    rc = main(["synth", str(tmp_path / "s"), "--width", "3000"])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.startswith("error:") and "RGB size" in err and len(err.strip().splitlines()) == 1


def test_body_make_test_model_two_word_command(tmp_path):
    out = tmp_path / "body.npz"
    assert main(["body", "make-test-model", str(out)]) == 0
    data = np.load(out)
    for key in ("v_template", "f", "J_regressor", "weights", "kintree_table", "shapedirs", "posedirs"):
        assert key in data.files
    assert data["J_regressor"].shape[0] == 24


@pytest.mark.parametrize("argv", [["--help"], ["inspect", "--help"], ["body", "make-test-model", "--help"]])
def test_help_exits_zero(argv):
    out = run_cli(*argv)
    assert out.returncode == 0, out.stderr
