"""Signal handling shared by every process: SIGTERM behaves like Ctrl-C."""
from __future__ import annotations

import contextlib
import signal
import sys
import threading
from collections.abc import Callable
from types import FrameType


class _Interrupts:
    received = 0
    """Signals handled by :func:`sigterm_as_interrupt`'s handler since it was set."""
    deferred = 0
    """Depth of :func:`interrupts_deferred` blocks: while above 0 the handler only counts."""
    unraisable_hook: Callable[[sys.UnraisableHookArgs], object] = sys.__unraisablehook__
    """The hook :func:`_quiet_about_interrupts` passes the other dropped exceptions on to."""


def _interrupt(signum: int, frame: FrameType | None) -> None:
    _Interrupts.received += 1
    if not _Interrupts.deferred:
        raise KeyboardInterrupt


def sigterm_as_interrupt() -> None:
    """Raise KeyboardInterrupt on SIGTERM and SIGINT so every process shuts down through one path.

    SIGINT is set explicitly: a process started in the background by a shell (or by a parent
    that was) inherits SIGINT ignored, and Python then leaves it ignored.
    """
    if not handles_interrupts():  # counted from the first call on
        _Interrupts.received = 0
    signal.signal(signal.SIGTERM, _interrupt)
    signal.signal(signal.SIGINT, _interrupt)
    if sys.unraisablehook is not _quiet_about_interrupts:
        _Interrupts.unraisable_hook = sys.unraisablehook
        sys.unraisablehook = _quiet_about_interrupts


def _quiet_about_interrupts(unraisable: sys.UnraisableHookArgs) -> None:
    """Python's hook for exceptions it drops, without its traceback for a KeyboardInterrupt of
    :func:`_interrupt` (:func:`raise_if_interrupted` acts on it)."""
    if isinstance(unraisable.exc_value, KeyboardInterrupt) and _Interrupts.received:
        return
    _Interrupts.unraisable_hook(unraisable)


def raise_if_interrupted() -> None:
    """Raise KeyboardInterrupt if a SIGINT or SIGTERM has come (with :func:`sigterm_as_interrupt`'s
    handler in place).

    The handler raises where the program happens to be, and Python drops an exception raised in
    a weakref callback, a finaliser or a fork hook ("Exception ignored in ..."): the program would
    go on as if no signal had come. Called at the points where a long start-up or wait checks
    in, the interrupt takes effect there.
    """
    if _Interrupts.received and handles_interrupts():
        raise KeyboardInterrupt


def handles_interrupts() -> bool:
    """True if :func:`sigterm_as_interrupt`'s handler is in place (this process is a dmpc command,
    not a program that imported dmpc)."""
    return signal.getsignal(signal.SIGINT) is _interrupt


@contextlib.contextmanager
def interrupts_deferred():
    """Start a child process without losing an interrupt: a SIGINT or SIGTERM that arrives meanwhile
    raises KeyboardInterrupt at the end of the block, once the child is recorded.

    ``subprocess.Popen`` with a ``preexec_fn`` runs Python's fork hooks, and a KeyboardInterrupt
    raised inside one is printed and dropped ("Exception ignored in ... _releaseLock"): the run
    would go on as if no signal had come. Raised after the fork but before ``Popen`` returns, it
    would leave a child nobody knows of. (Only with :func:`sigterm_as_interrupt`'s handler.)
    """
    before = _Interrupts.received
    _Interrupts.deferred += 1
    try:
        yield
    finally:
        _Interrupts.deferred -= 1
    if _Interrupts.received != before:
        raise KeyboardInterrupt


def ignore_further_interrupts() -> None:
    """Ignore SIGINT and SIGTERM from now on: the process, interrupted once, is shutting down (a
    bounded shutdown: its records written, its report, its session closed), and a second signal
    would cut its records short. The death of ``dmpc run``'s launcher can reach a process more than
    once. Only a dmpc command's main thread does so (with :func:`sigterm_as_interrupt`'s handler
    in place): a program that imported dmpc keeps its own handlers."""
    if handles_interrupts() and threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, signal.SIG_IGN)


@contextlib.contextmanager
def interrupts_held():
    """Ignore SIGINT and SIGTERM for the duration (a bounded shutdown that a second Ctrl-C must not
    cut short, leaving processes behind); the handlers are restored afterwards.

    Only the main thread can set handlers: elsewhere this does nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.signal(sig, signal.SIG_IGN) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler if handler is not None else signal.SIG_DFL)
