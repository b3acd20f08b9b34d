"""``dmpc coordinator`` (and ``dmpc plant``, which hosts the simulated plant with it): the step barrier as a
process on the Zenoh bus."""
from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import psutil

from dmpc.bus.interface import Bus
from dmpc.coordinator.barrier import Coordinator
from dmpc.coordinator.estimation import Estimation
from dmpc.coordinator.node import CoordinatorNode, RunObserver
from dmpc.coordinator.target_worker import TargetWorker
from dmpc.core.steps import StepRecord
from dmpc.estimation.targets import OffsetFreeTargets
from dmpc.methods import method_spec, terminal_policy
from dmpc.methods.policy import BoxPolicy
from dmpc.plant.dynamics import Plant
from dmpc.plant.models import make_plant
from dmpc.prepared import Prepared
from dmpc.records.agent_reports import merge_agent_reports, report_path
from dmpc.records.files import LOGS, PROCESSES, STEP_LOG
from dmpc.records.run_folder import RecordWriteError
from dmpc.records.session import RunRecorder
from dmpc.terminal.exit_codes import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK, EXIT_VERDICT
from dmpc.terminal.signals import interrupts_held
from dmpc.tracking.tracker import Tracker

LINGER = 2.0
REPORT_WAIT = 30.0
"""The most seconds to wait for the agents' reports once they have left: a guard against a hang, not
a measure; the wait ends as soon as every report is in or no other process of the run is alive."""
STOP_REPEAT = 0.2


@dataclass(frozen=True)
class CoordinatorOutcome:
    code: int
    message: str
    summary: dict | None


def coordinator_node(prepared: Prepared, bus: Bus, run_id: str, on_step: Callable[[StepRecord], None],
                     plant: Plant | None, telemetry: RunObserver | None = None,
                     plant_timeout: float | None = None) -> CoordinatorNode:
    """The coordinator of a prepared run, as a node on ``bus`` (not announced yet), timed by the
    bus's clock; ``plant`` is the simulated plant it steps, None for a plant outside.

    The one place that builds the coordinator from a prepared run: ``dmpc coordinator``,
    ``dmpc plant`` and ``dmpc simulate`` (:mod:`dmpc.runtime.inprocess`) all do it here.

    Parameters
    ----------
    prepared : Prepared
        The prepared run: its system, design, method, protocol options, setpoints and timing.
    bus : Bus
        The bus the node runs on; its clock times the coordinator.
    run_id : str
        The run id every message of the run carries.
    on_step : callable StepRecord -> None
        Called for every completed step (the run folder appends it).
    plant : Plant or None
        The simulated plant the coordinator steps; None for a plant outside.
    telemetry : RunObserver, optional
        Gets every completed step and the end, for observers.
    plant_timeout : float, optional
        With a plant outside: the most seconds to wait for each step's state; None with the
        simulated plant.
    """
    policy = terminal_policy(prepared.method, prepared.system, prepared.design)
    estimator = prepared.estimator
    tracker = None
    if prepared.tracks:
        assert isinstance(policy, BoxPolicy)
        outputs = None if estimator is None else OffsetFreeTargets(estimator.model, prepared.setpoint_margin)
        tracker = Tracker(prepared.system, prepared.design.terminal, policy.closed_loop,
                          prepared.design.gains.K_global(), prepared.setpoints, prepared.setpoint_margin, outputs)
    estimation = None if estimator is None else Estimation(estimator, prepared.plant.measurement_noise)
    coordinator = Coordinator(prepared.system, prepared.design, plant, prepared.protocol, run_id, policy=policy,
                              clock=bus.now, tracker=tracker, triggered=prepared.trigger.event,
                              cooperative=method_spec(prepared.method).cooperative,
                              cooperative_step=prepared.protocol.cooperative_step, estimation=estimation)
    # a live request's targets are computed beside the run where a thread can hand them back (not on
    # the in-memory bus, whose time is simulated: there a request is taken as it arrives)
    targets = TargetWorker(tracker.space, bus) if tracker is not None and bus.call_later_threadsafe else None
    return CoordinatorNode(bus, coordinator, prepared.digest, on_step, mode=prepared.mode, dt=prepared.dt,
                           deadline=prepared.deadline, scenario=prepared.name, telemetry=telemetry,
                           plant_timeout=plant_timeout, targets=targets)


def run_coordinator(prepared: Prepared, recorder: RunRecorder, bus: Bus, run_id: str, startup_timeout: float,
                    runtime: str = "multi-process", external_plant: bool = False,
                    plant_timeout: float = 10.0, telemetry: RunObserver | None = None) -> CoordinatorOutcome:
    """Wait for every agent, step the run to the end, write the records.

    ``external_plant``: the plant is outside this process (docs/protocol.md); x(0) is awaited with
    the agents, and each step's state for at most ``plant_timeout`` seconds. ``telemetry`` (the live
    view's, :func:`dmpc.watch.telemetry.open_telemetry`) sees every completed step and the end.
    Ctrl-C (or SIGTERM) stops the agents and keeps every completed step in the run folder.

    Parameters
    ----------
    prepared : Prepared
        The prepared run.
    recorder : RunRecorder
        The run folder's writer: it gets every completed step, then the summary.
    bus : Bus
        The bus the coordinator runs on (its session, until the agents have left).
    run_id : str
        The run id every message of the run carries.
    startup_timeout : float
        Seconds to wait for every agent's ``Ready`` (and a plant outside's x(0)); past them the
        run fails with what was missing.
    runtime : str
        How the run is hosted, the summary's ``runtime`` (``"multi-process"`` for ``dmpc run``).
    external_plant : bool
        The plant is outside this process.
    plant_timeout : float
        See above (used only with ``external_plant``).
    telemetry : RunObserver, optional
        See above.

    Returns
    -------
    CoordinatorOutcome
        The exit code, the line that says how the run ended, and the summary written (None if
        none could be).
    """
    outside = {"plant": {"model": "outside"}} if external_plant else {}  # what the summary says of the plant
    node = coordinator_node(prepared, bus, run_id, recorder.on_step, None if external_plant else make_plant(prepared),
                            telemetry=telemetry, plant_timeout=plant_timeout if external_plant else None)
    coordinator = node.coordinator
    node.announce()
    try:
        if not bus.run(until=lambda: node.started or node.finished, timeout=startup_timeout):
            reason = node.startup_failure(startup_timeout)
            node.fail(reason)
            summary = recorder.complete(**outside, runtime=runtime, failure=reason, **node.counts())
            finish(bus, node, summary, telemetry, recorder)
            return CoordinatorOutcome(EXIT_FAILED, reason, summary)
        bus.run(until=lambda: node.finished)
    except RecordWriteError as exc:
        reason = f"{node.who}: {exc}; the run stopped after {recorder.steps} steps, which are kept in {STEP_LOG}"
        node.fail(reason)
        kept = recorder.complete_if_possible(**outside, runtime=runtime, failure=reason, **node.counts())
        finish(bus, node, kept, telemetry, recorder)
        return CoordinatorOutcome(EXIT_FAILED, reason, kept)
    except KeyboardInterrupt:
        # the records of an interrupted run are written whole: a second signal (the launcher's death
        # reaches a process more than once, an impatient Ctrl-C) must not cut them short; bounded by
        # finish()'s own waits
        with interrupts_held():
            node.abort("aborted")
            summary = recorder.complete(**outside, runtime=runtime, aborted="interrupted", **node.counts())
            finish(bus, node, summary, telemetry, recorder)
        return CoordinatorOutcome(EXIT_INTERRUPTED, f"{node.who}: interrupted after {coordinator.k} steps", summary)
    summary = recorder.complete(**outside, runtime=runtime, failure=node.failure or None, **node.counts())
    finish(bus, node, summary, telemetry, recorder)
    if node.failure:
        return CoordinatorOutcome(EXIT_FAILED, f"{node.who}: {node.failure}", summary)
    if summary.get("verdict") == "failed":
        kinds = ", ".join(dict.fromkeys(f["kind"] for f in summary["failures"]))
        return CoordinatorOutcome(EXIT_VERDICT, f"{node.who}: finished {coordinator.k} steps; verdict failed ({kinds})", summary)
    return CoordinatorOutcome(EXIT_OK, f"{node.who}: finished {coordinator.k} steps", summary)


def finish(bus: Bus, node: CoordinatorNode, summary: dict | None, telemetry: RunObserver | None,
           recorder: RunRecorder | None = None) -> None:
    """Tell observers how the run ended, wait for the agents to leave, then stop the telemetry.

    In a run folder made by ``dmpc run`` (it has ``logs/``), the agents' reports are merged into
    the summary once they have left, so the summary has them even if the launcher is gone.

    Parameters
    ----------
    bus : Bus
        The coordinator's bus, run until the agents have left (:func:`linger`).
    node : CoordinatorNode
        The coordinator node, whose run is over (its ``Stop`` sent).
    summary : dict or None
        The summary written (``summary.json``'s content), for ``telemetry``; None if none was.
    telemetry : RunObserver or None
        Told of the summary, then closed.
    recorder : RunRecorder, optional
        The run folder's writer, whose folder gets the agents' reports merged into its summary.
    """
    with interrupts_held():  # bounded by LINGER: a second signal must not cut the agents' goodbye short
        if telemetry is not None and summary is not None:
            telemetry.summary(summary)
        try:
            linger(bus, node)
        finally:
            if telemetry is not None:
                telemetry.close()
    if summary is not None and recorder is not None and (recorder.folder.path / LOGS).is_dir():
        out = recorder.folder.path
        deadline = time.monotonic() + REPORT_WAIT  # an agent writes its report just after leaving
        try:
            while time.monotonic() < deadline and not _reports_settled(out, node.names):
                time.sleep(0.02)
        except KeyboardInterrupt:
            pass  # asked again to stop: merge what is there (the launcher merges again if it lives)
        with interrupts_held():
            merge_agent_reports(out, node.names)


def _reports_settled(out: Path, names: list[str]) -> bool:
    """Whether the agents' reports in the run folder ``out`` are all there, or no other process of the
    run (``processes.json``) is alive, so none will come; an agent that was killed writes none."""
    if all(report_path(out, n).exists() for n in names):
        return True
    try:
        pids = [int(pid) for pid in json.loads((out / PROCESSES).read_text()).values()]
    except (OSError, ValueError, TypeError, AttributeError):
        return False  # no list of processes: wait for the reports (to the deadline)
    return not any(_alive(pid) for pid in pids if pid != os.getpid())


def _alive(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie does not)."""
    try:
        return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.Error:
        return False


def linger(bus: Bus, node: CoordinatorNode, timeout: float = LINGER) -> None:
    """Keep the session open until the agents (and a plant outside), told to stop, have left (at most ``timeout`` s).

    Closing at once could withdraw the coordinator's liveliness token before the Stop message has
    reached every agent (through a router they travel different paths), and an agent would
    then report a lost coordinator instead of a finished run. Stop is repeated every
    ``STOP_REPEAT`` s meanwhile, in case a copy was lost (injected loss drops it too).

    Parameters
    ----------
    bus : Bus
        The coordinator's bus, run meanwhile.
    node : CoordinatorNode
        The coordinator node whose run is over: it says who is still present and repeats the ``Stop``.
    timeout : float
        The most seconds to wait (bus clock).
    """
    end = bus.now() + timeout
    try:
        while node.present() and bus.now() < end:
            if not bus.run(until=lambda: not node.present(), timeout=min(STOP_REPEAT, end - bus.now())):
                node.repeat_stop()
    except KeyboardInterrupt:
        pass
