"""Recording one run: the run folder plus a progress bar, closed properly on any exit."""
from __future__ import annotations

import time
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from dmpc.core.quantities import named_labels
from dmpc.core.steps import StepRecord
from dmpc.prepared import Prepared
from dmpc.prepared.bundle import bundle_json
from dmpc.records.files import BUNDLE, DESIGN, DISTURBANCE, SCENARIO
from dmpc.records.run_folder import RecordWriteError, RunFolder
from dmpc.records.verdict import RunLimits
from dmpc.scenario import Scenario, dump_resolved
from dmpc.terminal.progress import ProgressBar


def seconds_per_step(prepared: Prepared) -> float | None:
    """The seconds one step of the ``prepared`` run stands for: the scenario's ``dt`` (the model's
    sampling period), else in ``realtime`` mode the period of the steps (``options.dt``); None when
    neither is known."""
    scenario = prepared.scenario
    if scenario is not None and scenario.dt is not None:
        return float(scenario.dt)
    return float(prepared.dt) if prepared.mode == "realtime" else None


def run_labels(scenario: Scenario) -> dict[str, dict[str, tuple[str, ...]]]:
    """The labels (``h1 [m]``) the ``scenario`` gives its quantities, for the verdict's messages and
    the setpoint segments: :func:`~dmpc.core.quantities.named_labels` and ``output``, every
    subsystem's outputs (its ``outputs``; the states' labels where C is omitted or the identity,
    else y1, y2, ...)."""
    labels = named_labels(scenario)
    labels["output"] = {sub.name: tuple(o.label for o in sub.output_labels()) for sub in scenario.resolved_subsystems()}
    return labels


def measurement_noise_scale(prepared: Prepared) -> float:
    """The largest standard deviation of the noise the ``prepared`` run's plant adds to its outputs
    (0 without)."""
    noise = prepared.plant.measurement_noise
    return 0.0 if noise is None else float(np.max(noise.std, initial=0.0))


class RunRecorder:
    """Writes scenario.yaml (run.json for a run started from a run bundle) and design.json at
    once, each step as it completes, and the arrays and summary at the end; an interrupted run
    still gets them for the completed steps.

    Parameters
    ----------
    out : path-like
        The run folder.
    prepared : Prepared
    show_progress : bool
    sources : iterable of path-like, optional
        The files the run was loaded from (scenario or run bundle, design). One that already is
        the run folder's own file is not written again: ``dmpc run`` writes them before it starts
        the plant on them.
    """

    def __init__(self, out, prepared: Prepared, show_progress: bool = True, sources: Iterable = ()) -> None:
        self.prepared = prepared
        self.folder = RunFolder(out, prepared.system)
        loaded = {Path(p).resolve() for p in sources}

        def needed(name: str) -> bool:
            return (self.folder.path / name).resolve() not in loaded

        if prepared.scenario is not None:
            if needed(SCENARIO):
                self.folder.write_text(SCENARIO, dump_resolved(prepared.scenario))
        elif needed(BUNDLE):  # started from a run bundle: the bundle describes the run instead
            self.folder.write_json(BUNDLE, bundle_json(prepared))
        if needed(DESIGN):
            self.folder.write_json(DESIGN, prepared.design_json())
        if prepared.plant.disturbance is not None:
            np.save(self.folder.path / DISTURBANCE, prepared.plant.disturbance)
        self._started = time.monotonic()
        self._progress = ProgressBar("steps", prepared.protocol.steps, fields={"J": "-"}) if show_progress else None
        self.summary: dict | None = None
        self._write_failed = False

    def __enter__(self) -> "RunRecorder":
        if self._progress is not None:
            self._progress.start()
        return self

    def on_step(self, record: StepRecord) -> None:
        """Record the completed step ``record``; after a failed write (RecordWriteError, raised once) the
        records are closed and later steps are not recorded."""
        if self._write_failed:
            return
        try:
            self.folder.append_step(record)
        except RecordWriteError:
            self._write_failed = True
            raise
        if self._progress is not None:
            self._progress.advance(J=f"{record.J:.4g}")

    def complete(self, **extra) -> dict:
        """Write the arrays and the summary; returns the summary (RecordWriteError if it cannot)."""
        if self._progress is not None:
            self._progress.stop()
        info = {"scenario": self.prepared.name, "design_digest": self.prepared.digest, "method": self.prepared.method,
                "wall_time_s": time.monotonic() - self._started,
                "horizon": self.prepared.design.horizon,
                "horizon_auto": (self.prepared.design.start or {}).get("horizon") == "auto", "rejected": {}, "rejected_reasons": {},
                "duplicates": 0, "inputs_refused": {}, "agents": {}, "plant": self.prepared.plant.describe()}
        info.update({k: v for k, v in extra.items() if v is not None})
        messages = extra.get("messages")
        if messages is not None:  # a solve is a plan message: the solves whose plans reached the coordinator
            per = {name: entry["plan_messages"] for name, entry in messages["per_agent"].items()}
            info["solves"], info["solves_per_agent"] = sum(per.values()), per
        p = self.prepared.protocol
        limits = RunLimits(steps=p.steps, initial_rounds=p.initial_rounds, rounds=p.rounds,
                           initial_tolerance=p.initial_tolerance, tolerance=p.tolerance,
                           stopped=str(info.get("failure") or info.get("aborted") or ""),
                           setpoint_margin=self.prepared.setpoint_margin,
                           measurement_noise=measurement_noise_scale(self.prepared))
        scenario = self.prepared.scenario
        self.summary = self.folder.finish(info, limits, run_labels(scenario) if scenario is not None else None,
                                          seconds_per_step(self.prepared))
        return self.summary

    @property
    def steps(self) -> int:
        """Steps recorded so far."""
        return self.folder.steps

    def complete_if_possible(self, **extra) -> dict | None:
        """:meth:`complete`, or None when the records cannot be written (the step log keeps the
        completed steps)."""
        try:
            return self.complete(**extra)
        except RecordWriteError:
            return None

    def __exit__(self, exc_type, exc, tb) -> None:
        if self.summary is None:
            reason = "interrupted" if exc_type is KeyboardInterrupt else (
                f"failed: {exc}" if isinstance(exc, RecordWriteError) else
                f"failed: {exc_type.__name__}" if exc_type else "incomplete")
            if exc_type is None and not self._write_failed:
                self.complete(aborted=reason)
            else:  # the exception on its way out says what went wrong; a second one must not hide it
                self.complete_if_possible(aborted=reason)
        self.folder.close()
