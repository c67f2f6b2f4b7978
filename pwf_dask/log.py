"""The package's messages: one ``logging`` logger, ``pwf_dask``, configured by the CLI.

The library never prints. Stage messages (what is computed, what was repaired) are INFO
records of ``pwf_dask.*`` loggers, and progress lines are shown only where INFO is enabled.
A Python user sees them after ``pwf_dask.log.configure()`` (or their own logging set-up);
the CLI calls it with ``-v`` (DEBUG) or ``-q`` (warnings and errors only).
"""

from __future__ import annotations

import logging
import sys

logger = logging.getLogger("pwf_dask")
logger.addHandler(logging.NullHandler())


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is at the time of the record (test captures, redirects)."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:  # StreamHandler sets it once; the property always follows sys.stderr
        pass


def configure(verbosity: int = 0) -> None:
    """Messages of the ``pwf_dask`` loggers on stderr, as plain lines: ``verbosity`` -1 warnings
    only (no progress), 0 INFO (stage messages and progress), 1 DEBUG."""
    for handler in [h for h in logger.handlers if isinstance(h, _StderrHandler)]:
        logger.removeHandler(handler)
    handler = _StderrHandler()
    handler.setFormatter(logging.Formatter("%(message)s"))
    logger.addHandler(handler)
    logger.setLevel({-1: logging.WARNING, 0: logging.INFO}.get(verbosity, logging.DEBUG))
    logger.propagate = False


def progress_enabled() -> bool:
    return logger.isEnabledFor(logging.INFO)
