"""Terminal output helpers: solver noise off the terminal, errors as one line, summaries."""
from __future__ import annotations

import os
import sys

from rich.console import Console

_silenced = False
errors_printed = 0
"""How many ``error:`` lines this process has printed (a command that said why it stopped
is not followed by a generic line)."""


def silence_c_stdout() -> None:
    """Send C-level writes to fd 1 (OSQP's "Polishing not needed") to /dev/null.

    Python's ``sys.stdout`` is moved to a duplicate of the original fd 1, so everything the
    program prints still reaches the terminal or pipe; only native libraries lose fd 1.
    """
    global _silenced
    if _silenced:
        return
    try:
        sys.stdout.flush()
        saved = os.dup(1)
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 1)
        os.close(devnull)
        os.set_inheritable(saved, False)
        sys.stdout = os.fdopen(saved, "w", buffering=1, encoding=getattr(sys.stdout, "encoding", None) or "utf-8")
        _silenced = True
    except OSError:
        pass  # no fd 1 to redirect (embedded use): leave it as it is


PIPE_WIDTH = 160
"""Columns of tables written to a pipe or file (a terminal gives its own width)."""


def stdout_console() -> Console:
    width = None if sys.stdout.isatty() else PIPE_WIDTH
    return Console(file=sys.stdout, highlight=False, soft_wrap=True, width=width)


def stderr_console() -> Console:
    return Console(file=sys.stderr, highlight=False, soft_wrap=True)


def error_line(message: str) -> None:
    """Print ``error: message`` on stderr as a single line."""
    global errors_printed
    text = " ".join(str(message).split())
    print(f"error: {text}", file=sys.stderr, flush=True)
    errors_printed += 1
