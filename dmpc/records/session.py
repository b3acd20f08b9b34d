"""Recording one run: the run folder plus a progress bar, closed properly on any exit."""
from __future__ import annotations

import time

from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from dmpc.console import stderr_console
from dmpc.plant.barrier import StepRecord
from dmpc.records.run_folder import RunFolder
from dmpc.runtime.setup import Prepared
from dmpc.scenario import dump_resolved


class RunRecorder:
    """Writes scenario.yaml and design.json at once, each step as it completes, and the
    arrays and summary at the end; an interrupted run still gets them for the completed steps.

    Parameters
    ----------
    out : path-like
        The run folder.
    prepared : Prepared
    show_progress : bool
    """

    def __init__(self, out, prepared: Prepared, show_progress: bool = True) -> None:
        self.prepared = prepared
        self.folder = RunFolder(out, prepared.system)
        self.folder.write_text("scenario.yaml", dump_resolved(prepared.scenario))
        self.folder.write_json("design.json", prepared.design_json())
        self._started = time.monotonic()
        self._progress = None
        self._task = None
        self.summary: dict | None = None
        if show_progress:
            self._progress = Progress(TextColumn("[bold]steps"), BarColumn(), MofNCompleteColumn(),
                                      TextColumn("J={task.fields[J]}"), TimeElapsedColumn(),
                                      console=stderr_console(), transient=True)
            self._task = self._progress.add_task("run", total=prepared.protocol.steps, J="-")

    def __enter__(self) -> "RunRecorder":
        if self._progress is not None:
            self._progress.start()
        return self

    def on_step(self, record: StepRecord) -> None:
        self.folder.append_step(record)
        if self._progress is not None:
            self._progress.update(self._task, advance=1, J=f"{record.J:.4g}")

    def complete(self, **extra) -> dict:
        """Write the arrays and the summary; returns the summary."""
        if self._progress is not None:
            self._progress.stop()
        info = {"scenario": self.prepared.name, "design_digest": self.prepared.digest, "method": self.prepared.method,
                "wall_time_s": time.monotonic() - self._started, "rejected": {}, "rejected_reasons": {},
                "duplicates": 0, "agents": {}}
        info.update({k: v for k, v in extra.items() if v is not None})
        self.summary = self.folder.finish(info)
        return self.summary

    def __exit__(self, exc_type, exc, tb) -> None:
        if self.summary is None:
            reason = "interrupted" if exc_type is KeyboardInterrupt else (
                f"failed: {exc_type.__name__}" if exc_type else "incomplete")
            self.complete(aborted=reason)
        self.folder.close()
