"""Progress on stderr: one bar over the steps of a run (``dmpc simulate``, ``dmpc run``), or over many
closed-loop runs with the time they will take (``dmpc roa``).

A bar is drawn only where someone sees it: on a terminal or in a notebook. In a file or a pipe
it would show nothing and leave a blank line, so it stays off there; :class:`RunProgress` says
what it does in lines of text instead, which show everywhere.
"""
from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from dmpc.terminal.console import stderr_console

ESTIMATE_AFTER = 10
"""Runs after which :class:`RunProgress` prints how long the rest will take."""


class ProgressBar:
    """A transient bar over ``total`` items, labelled ``label``.

    Parameters
    ----------
    label : str
        The bar's title: ``steps``, or the command (``roa``).
    total : int
    console : rich.console.Console, optional
        stderr's by default.
    fields : mapping of str -> str, optional
        Values shown after the count as ``name=value`` (the cost ``J`` of the last step), with
        their first text; :meth:`advance` and :meth:`update` change them.
    time_left : bool
        Show the time left at the pace so far.
    """

    def __init__(self, label: str, total: int, console: Console | None = None, fields: dict[str, str] | None = None,
                 time_left: bool = False) -> None:
        console = console if console is not None else stderr_console()
        self.shown = console.is_terminal or console.is_jupyter
        self._fields: dict[str, Any] = dict(fields or {})
        columns = [TextColumn(f"[bold]{label}"), BarColumn(), MofNCompleteColumn()]
        columns += [TextColumn(f"{name}={{task.fields[{name}]}}") for name in self._fields]
        columns += [TimeElapsedColumn()] + ([TextColumn("left"), TimeRemainingColumn()] if time_left else [])
        self._bar = Progress(*columns, console=console, transient=True) if self.shown else None
        self._task = self._bar.add_task(label, total=total, **self._fields) if self._bar is not None else None

    def start(self) -> None:
        if self._bar is not None:
            self._bar.start()

    def advance(self, **fields: Any) -> None:
        """One more item is done; ``fields`` (text) are the new values shown."""
        if self._bar is not None and self._task is not None:
            self._bar.update(self._task, advance=1, **fields)

    def update(self, completed: int, **fields: Any) -> None:
        """``completed`` items are done (a count read from elsewhere, such as a step log)."""
        if self._bar is not None and self._task is not None:
            self._bar.update(self._task, completed=completed, **fields)

    def stop(self) -> None:
        if self._bar is not None:
            self._bar.stop()

    def __enter__(self) -> "ProgressBar":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def duration_text(seconds: float) -> str:
    """``seconds`` as ``0.4 s``, ``42 s``, ``3 min 5 s`` or ``2 h 7 min``."""
    if seconds < 9.95:
        return f"{max(0.0, seconds):.1f} s"
    seconds = round(seconds)
    if seconds < 60:
        return f"{seconds} s"
    minutes, s = divmod(seconds, 60)
    if minutes < 60:
        return f"{minutes} min {s} s"
    hours, m = divmod(minutes, 60)
    return f"{hours} h {m} min"


class RunProgress:
    """Progress over ``total`` closed-loop runs: a line that announces them, a :class:`ProgressBar`,
    and after ``estimate_after`` runs a line with the time left.

    The bar alone says nothing until its rate settles, and nothing at all when stderr is not a
    terminal; the two lines do, in both cases.

    Parameters
    ----------
    label : str
        The command, e.g. ``roa``: the bar's title and the lines' prefix.
    total : int
        Runs to do.
    plan : str
        What the runs are, e.g. ``2 methods x 4 horizons x 500 samples``.
    console : rich.console.Console
    clock : callable () -> float
        Seconds (monotonic by default).
    estimate_after : int
        Runs after which the estimate is printed.
    """

    def __init__(self, label: str, total: int, plan: str, console: Console,
                 clock: Callable[[], float] = time.monotonic, estimate_after: int = ESTIMATE_AFTER) -> None:
        self.label, self.total, self.plan, self.console = label, total, plan, console
        self.clock = clock
        self.estimate_after = min(estimate_after, total)
        self.done = 0
        self._started = 0.0
        self._bar = ProgressBar(label, total, console, time_left=True)

    def start(self) -> None:
        self.console.print(f"{self.label}: {self.total} closed-loop runs ({self.plan}); "
                           f"an estimate of the time follows after the first {self.estimate_after}")
        self._started = self.clock()
        self._bar.start()

    def advance(self) -> None:
        """One run is done."""
        self.done += 1
        self._bar.advance()
        if self.done == self.estimate_after:
            self.console.print(self.estimate())

    def estimate(self) -> str:
        """The line printed after the first runs: their pace, and the time left at that pace."""
        elapsed = self.clock() - self._started
        left = elapsed / self.done * (self.total - self.done)
        return (f"{self.label}: {self.done} of {self.total} runs in {duration_text(elapsed)}; "
                f"about {duration_text(left)} left at that pace")

    def stop(self) -> None:
        self._bar.stop()
