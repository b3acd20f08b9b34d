"""Signal handling shared by every process: SIGTERM behaves like Ctrl-C."""
from __future__ import annotations

import signal


def sigterm_as_interrupt() -> None:
    """Raise KeyboardInterrupt on SIGTERM and SIGINT so every process shuts down through one path.

    SIGINT is set explicitly: a process started in the background by a shell (or by a parent
    that was) inherits SIGINT ignored, and Python then leaves it ignored.
    """

    def _raise(signum, frame):
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, _raise)
    signal.signal(signal.SIGINT, signal.default_int_handler)
