"""Ctrl-C that lands inside the import of a compiled module surfaces as an ImportError; once the
CLI watches SIGINT, such an error still counts as an interruption (manifest "interrupted")."""

from __future__ import annotations

import json
import os
import signal
import time

import pytest

from embodmocap import errors
from embodmocap.io.stage_manifest import StageManifest, tracked_stage


@pytest.fixture(autouse=True)
def default_sigint():
    """Python's own SIGINT handler for each test: a test run started in the background (``cmd &``,
    ``nohup``) inherits SIGINT ignored, and the CLI rightly leaves an ignored SIGINT ignored."""
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, before)


def _stage_interrupted_inside_an_import(path):
    @tracked_stage
    def stage():
        StageManifest(path, "demo", {})
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5)  # the signal is handled before this returns
        except KeyboardInterrupt:
            raise ImportError("initialization failed") from None  # what an interrupted extension init raises
    return stage


def test_an_error_caused_by_sigint_counts_as_interrupted(tmp_path):
    previous = errors.watch_interrupts()
    assert previous is not None, "the test runs in the main thread with the default handler"
    try:
        with pytest.raises(ImportError):
            _stage_interrupted_inside_an_import(tmp_path / "m.json")()
        assert errors.interrupted(ImportError("x"))
        assert json.loads((tmp_path / "m.json").read_text())["status"] == "interrupted"
    finally:
        errors.stop_watching_interrupts(previous)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_without_a_sigint_an_error_is_a_failure(tmp_path):
    previous = errors.watch_interrupts()
    try:
        @tracked_stage
        def stage():
            StageManifest(tmp_path / "m.json", "demo", {})
            raise ImportError("a real import problem")

        with pytest.raises(ImportError):
            stage()
        assert not errors.interrupted(ImportError("x")) and errors.interrupted(KeyboardInterrupt())
        assert json.loads((tmp_path / "m.json").read_text())["status"] == "failed"
    finally:
        errors.stop_watching_interrupts(previous)
