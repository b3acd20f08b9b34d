"""Progress over many closed-loop runs: how many there are up front, how long once a few are done.

The bar alone says nothing until its rate settles, and nothing at all when stderr is not a
terminal; the two lines do, in both cases.
"""
from __future__ import annotations

import time
from collections.abc import Callable

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

ESTIMATE_AFTER = 10


def duration_text(seconds: float) -> str:
    """``0.4 s``, ``42 s``, ``3 min 5 s`` or ``2 h 7 min``."""
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
    """A bar over ``total`` runs that announces them and, after ``estimate_after``, the time left.

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
        self._bar = Progress(TextColumn(f"[bold]{label}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                             TextColumn("left"), TimeRemainingColumn(), console=console, transient=True)
        self._task = self._bar.add_task(label, total=total)

    def start(self) -> None:
        self.console.print(f"{self.label}: {self.total} closed-loop runs ({self.plan}); "
                           f"an estimate of the time follows after the first {self.estimate_after}")
        self._started = self.clock()
        self._bar.start()

    def advance(self) -> None:
        """One run is done."""
        self.done += 1
        self._bar.advance(self._task)
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
