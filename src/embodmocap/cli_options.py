"""The options ``embodmocap`` takes anywhere on its command line, before tyro parses the rest:
``--version``, ``-q``/``--quiet``, ``-v``/``--verbose``, ``--debug``, ``--log-file PATH`` and
``--config FILE.toml`` (:mod:`embodmocap.cli_settings`)."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from embodmocap.errors import EmbodMocapError


@dataclass
class GlobalOptions:
    """Options taken anywhere on the command line, before tyro sees it (see :func:`main`)."""

    debug: bool = False
    """--debug: show the traceback of a failure."""
    level: int = logging.INFO
    """-q: WARNING (warnings and errors only); -v: DEBUG; default INFO."""
    log_file: Path | None = None
    """--log-file PATH: the log also appended there."""
    config: Path | None = None
    """--config FILE.toml: the command's settings (cli_settings); the command line wins."""
    version: bool = False
    """--version: print the version and stop."""


def global_options(argv: list[str]) -> tuple[list[str], GlobalOptions]:
    """Take the global options out of ``argv``; an option missing its value is one clear error."""
    opts, rest, i = GlobalOptions(), [], 0
    while i < len(argv):
        a = argv[i]
        if a == "--":  # everything after is the command's
            rest += argv[i:]
            break
        name, eq, value = a.partition("=")
        if a == "--debug":
            opts.debug = True
        elif a in ("-q", "--quiet"):
            opts.level = logging.WARNING
        elif a in ("-v", "--verbose"):
            opts.level = logging.DEBUG
        elif a == "--version":
            opts.version = True
        elif name in ("--log-file", "--config"):
            if not eq:
                if i + 1 >= len(argv) or argv[i + 1].startswith("-"):
                    raise EmbodMocapError(f"{name} needs a path (e.g. {name} "
                                          f"{'run.log' if name == '--log-file' else 'settings.toml'})")
                i += 1
                value = argv[i]
            setattr(opts, name[2:].replace("-", "_"), Path(value))
        else:
            rest.append(a)
        i += 1
    if opts.debug and opts.level == logging.INFO:
        opts.level = logging.DEBUG
    return rest, opts
