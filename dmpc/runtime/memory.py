"""Give memory freed during start-up back to the operating system."""
from __future__ import annotations

import ctypes
import gc


def trim_heap() -> None:
    """Collect garbage and ask glibc to return free heap pages (no-op elsewhere).

    Validating the scenario and building the design allocate a lot of short-lived objects;
    without this, a long-running agent keeps those pages resident for its whole life.
    """
    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass
