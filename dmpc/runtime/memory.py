"""Give memory freed during start-up back to the operating system."""
from __future__ import annotations

import ctypes
import gc


def settle_after_startup() -> None:
    """Collect start-up garbage, freeze what is left, and return free heap pages to the OS.

    Validating the scenario and building the design allocate many short-lived objects, and
    the imported libraries leave a large graph of long-lived ones. Freezing moves the survivors
    out of the garbage collector's reach, so the per-step collections no longer walk them
    (they cost more than the QP otherwise); trimming gives the freed pages back.
    """
    gc.collect()
    gc.freeze()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass
