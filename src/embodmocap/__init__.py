"""embodmocap: metric, gravity-aligned 4D human-scene capture from two handheld iPhones."""

import logging

__version__ = "0.1.0"

#: The package logger; modules use ``logging.getLogger(__name__)`` under it, never the root logger.
logger = logging.getLogger("embodmocap")
logger.addHandler(logging.NullHandler())
