"""A child's output once the launcher that reads it is gone.

``dmpc run`` reads its children's stdout and stderr through pipes (:mod:`dmpc.runtime.logpump`).
If the launcher is killed, those pipes lose their reader, and the next line a child writes fails
with EPIPE: an agent would die before writing its report, the plant before merging the agents'
reports into ``summary.json``. A child started so guards its output: at the first write that finds
the pipe broken, that stream's file descriptor is pointed at its log file (appended to;
``/dev/null`` if that cannot be opened) and the write is done again there, so the process
finishes its work and its last lines still reach the log.
"""
from __future__ import annotations

import errno
import os
import sys
from typing import TextIO, cast

LOG_ENV = "DMPC_LOG_FILE"
"""The environment variable by which the launcher tells a child its log file."""


def _redirect(fd: int, log_path: str) -> None:
    """Point the file descriptor ``fd`` at ``log_path`` (appended to), or at /dev/null."""
    try:
        target = os.open(log_path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    except OSError:
        target = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(target, fd)
    finally:
        os.close(target)


def _broken(exc: OSError) -> bool:
    return isinstance(exc, BrokenPipeError) or exc.errno == errno.EPIPE


class _Guarded:
    """A text stream whose writes survive the loss of its pipe's reader (see the module's text)."""

    def __init__(self, stream: TextIO, log_path: str) -> None:
        self._stream = stream
        self._log_path = log_path

    def write(self, text: str) -> int:
        """Write ``text``; where the pipe is broken, again into the log file."""
        try:
            return self._stream.write(text)
        except OSError as exc:
            if not _broken(exc):
                raise
            _redirect(self._stream.fileno(), self._log_path)
            return self._stream.write(text)

    def flush(self) -> None:
        """Flush; a broken pipe moves the output to the log file first."""
        try:
            self._stream.flush()
        except OSError as exc:
            if not _broken(exc):
                raise
            _redirect(self._stream.fileno(), self._log_path)
            self._stream.flush()

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


def guard_output(log_path: str | None = None) -> None:
    """Guard ``sys.stdout`` and ``sys.stderr`` of this process against the loss of their reader.

    Parameters
    ----------
    log_path : str, optional
        Where the output goes once the pipe is broken; by default the environment's
        ``DMPC_LOG_FILE`` (set by the launcher for the children it starts). Without either, nothing
        is done: a process started by hand writes to its terminal or wherever its caller said.
    """
    path = log_path or os.environ.get(LOG_ENV)
    if not path or isinstance(sys.stdout, _Guarded):
        return
    sys.stdout = cast(TextIO, _Guarded(sys.stdout, path))
    sys.stderr = cast(TextIO, _Guarded(sys.stderr, path))
