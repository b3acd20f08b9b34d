"""Signal handling shared by every process: SIGTERM behaves like Ctrl-C."""
from __future__ import annotations

import signal


def sigterm_as_interrupt() -> None:
    """Raise KeyboardInterrupt on SIGTERM so every process shuts down through one path."""

    def _raise(signum, frame):
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, _raise)
