"""Logging for the commands: the library logs to ``trianflow_vo``; this shows it on stderr."""

from __future__ import annotations

import logging
import sys


class _Format(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        msg = record.getMessage()
        if record.levelno >= logging.ERROR:
            return f"error: {msg}"
        if record.levelno >= logging.WARNING:
            return f"warning: {msg}"
        return msg


class _LineHandler(logging.StreamHandler):
    """Writes to the current ``sys.stderr``; clears a progress line first on a terminal."""

    def __init__(self):
        super().__init__(sys.stderr)

    def emit(self, record: logging.LogRecord) -> None:
        self.stream = sys.stderr
        if self.stream.isatty():
            self.stream.write("\r\x1b[K")
        super().emit(record)


def setup_logging(verbosity: int) -> None:
    """``-1`` errors only (``-q``), ``0`` warnings, ``1`` information (``-v``), ``2`` debugging (``-vv``)."""
    level = {-1: logging.ERROR, 0: logging.WARNING, 1: logging.INFO}.get(verbosity, logging.DEBUG)
    logger = logging.getLogger("trianflow_vo")
    for h in list(logger.handlers):
        if isinstance(h, _LineHandler):
            logger.removeHandler(h)
    handler = _LineHandler()
    handler.setFormatter(_Format())
    logger.addHandler(handler)
    logger.setLevel(level)
