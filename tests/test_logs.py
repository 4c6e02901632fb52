"""Readable logs: repeated lines folded by the command line's handler; the body model announced
once per process; one summary line per Stage II step."""

from __future__ import annotations

import io
import logging

from embodmocap import logs


def test_repeated_lines_are_folded_into_one_count():
    stream = io.StringIO()
    logger = logging.getLogger("embodmocap.test_logs_fold")
    logger.propagate = False
    handler = logs.setup(logger, debug=False, stream=stream)
    try:
        for _ in range(12):
            logger.info("%d gaps left unfilled", 3)
        logger.warning("%d gaps left unfilled", 3)  # another level: a new line
        logger.info("done")
        logger.info("done")
        handler.flush_repeats()
    finally:
        logger.removeHandler(handler)
    lines = stream.getvalue().splitlines()
    assert [ln.split(": ", 1)[1] for ln in lines if ": " in ln] == [
        "3 gaps left unfilled", "3 gaps left unfilled", "done"]
    assert lines[1] == "(the line above repeated 11 more times)"
    assert lines[-1] == "(the line above repeated 1 more times)" and len(lines) == 5


def test_body_model_is_announced_once_per_file(tmp_path, caplog):
    from embodmocap.body.model import load_body_model
    from embodmocap.body.testmodel import write_test_model

    path = write_test_model(tmp_path / "body.npz")
    with caplog.at_level(logging.DEBUG, logger="embodmocap.body.model"):
        for _ in range(3):
            load_body_model(path)
    loaded = [r for r in caplog.records if r.getMessage().startswith("loaded body model")]
    assert [r.levelno for r in loaded] == [logging.INFO, logging.DEBUG, logging.DEBUG]
