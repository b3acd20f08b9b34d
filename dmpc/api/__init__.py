"""The Python entry points: load a scenario, design it, simulate or run it, read a run back.

Every function takes plain objects (a path, a mapping of numpy arrays, or a
:class:`~dmpc.scenario.Scenario`) and returns a frozen result indexed by subsystem name. The
command line is a layer on the same steps. Nothing is printed unless ``progress=True``.
"""
from __future__ import annotations

import contextlib
import re
import secrets
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

from dmpc.api.result import Result, load_run
from dmpc.api.scenarios import ScenarioLike, load_scenario
from dmpc.api.setpoints import LiveRun, SetpointError, SetpointRefused, SetpointUnanswered, StartHook, setpoint
from dmpc.bus import keys
from dmpc.core.errors import DmpcError
from dmpc.methods import method_spec
from dmpc.offline.record import Design
from dmpc.plant.models import PlantModelError
from dmpc.prepared import PlantFunction
from dmpc.records.files import LOGS, log_file
from dmpc.records.session import RunRecorder
from dmpc.runtime.hosting import check_per_process, group_agents
from dmpc.runtime.inprocess import record_run
from dmpc.runtime.launcher import default_topology, launch
from dmpc.setup import prepare
from dmpc.setup.plant import function_reference, load_plant_function, with_plant_function
from dmpc.terminal.exit_codes import EXIT_INTERRUPTED, EXIT_OK

__all__ = ["LiveRun", "RunError", "SetpointError", "SetpointRefused", "SetpointUnanswered", "design", "load_run",
           "load_scenario", "run", "setpoint", "simulate"]


class RunError(DmpcError, RuntimeError):
    """A run that could not complete (a process failed, the agents never became ready, ...).

    A run that completes with constraint violations is not an error: its ``Result.verdict`` is
    ``failed``.
    """


def _prepared(scenario: ScenarioLike, method: str | None = None, steps: int | None = None):
    extra: dict[str, object] = {}
    if method is not None:
        extra["options__method"] = method
    if steps is not None:
        extra["steps"] = steps
    return prepare(load_scenario(scenario, **extra))


def design(scenario: ScenarioLike) -> Design:
    """The offline design of a scenario: gains, terminal set, sigma, horizon and checks.

    The same as ``dmpc design --json`` (``Design.json`` is that JSON).

    Raises
    ------
    dmpc.design.DesignError
        The design cannot work (e.g. an infeasible start at the given horizon).
    """
    from dmpc.setup.coupling_check import design_with_coupling  # start-up time: only a design needs it

    prepared = _prepared(scenario)
    return Design.from_json(design_with_coupling(prepared), prepared.names)


@contextlib.contextmanager
def _run_folder(out: str | Path | None) -> Iterator[tuple[Path, bool]]:
    """``(folder, temporary)``: ``out``, or a temporary folder removed afterwards."""
    if out is not None:
        yield Path(out), False
        return
    with tempfile.TemporaryDirectory(prefix="dmpc-run-") as tmp:
        yield Path(tmp) / "run", True


def simulate(scenario: ScenarioLike, *, method: str | None = None, out: str | Path | None = None,
             plant: PlantFunction | None = None, progress: bool = False, steps: int | None = None) -> Result:
    """Run every agent, the coordinator and the plant in this process (as ``dmpc simulate``).

    Parameters
    ----------
    scenario : path, mapping or Scenario
    method : str, optional
        The control method (``tv-box``, ``tv-box-opt``, ``fixed-box``, ``ellipsoid``,
        ``ellipsoid-adaptive``, ``centralized``); None: the scenario's ``options.method``.
    out : path, optional
        Run folder to write; None: a temporary one (``Result.folder`` is then None).
    plant : callable (x, u, k) -> x_next, optional
        Your own plant in place of the linear one: x (n,) and u (m,) in the global order.
        An exception in it stops the run with :class:`PlantModelError`, whose cause is yours.
    progress : bool
        Show a progress bar (stderr).
    steps : int, optional
        Steps to run instead of the scenario's.

    Returns
    -------
    Result

    Raises
    ------
    RunError
        The run could not complete.
    """
    prepared = _prepared(scenario, method, steps)
    if plant is not None:
        prepared = with_plant_function(prepared, plant)
    with _run_folder(out) as (folder, temporary):
        with RunRecorder(folder, prepared, show_progress=progress) as recorder:
            _, failure = record_run(prepared, recorder)
        if failure:
            raise RunError(f"the run of '{prepared.name}' failed: {failure}")
        return load_run(folder, in_temporary_folder=temporary)


def run(scenario: ScenarioLike, *, out: str | Path | None = None, method: str | None = None,
        plant: PlantFunction | None = None, progress: bool = False, steps: int | None = None,
        startup_timeout: float = 60.0, topology: str | None = None, agents_per_process: int = 1,
        secure: bool = False, on_start: Callable[[LiveRun], object] | None = None) -> Result:
    """Run the plant and one process per agent over Zenoh on this machine (as ``dmpc run``).

    Every process is stopped when the run ends, fails, or is interrupted (Ctrl-C re-raises
    KeyboardInterrupt after the processes are gone; the completed steps stay in ``out``).

    Parameters
    ----------
    scenario, out, method, progress, steps
        As for :func:`simulate`.
    plant : callable (x, u, k) -> x_next, optional
        Your own plant, passed to the plant process as ``--model``: it must be importable by
        name, i.e. defined at the top level of a module (not in a notebook or ``__main__``).
    startup_timeout : float
        Seconds the processes wait for each other.
    topology : {"mesh", "star"}, optional
        How the processes connect; the default depends on the number of agent processes.
    agents_per_process : int
        Agents served by each agent process (``dmpc run --agents-per-process``); 1 by default.
    secure : bool
        Every link over TLS with certificates and access control made for this run in the run
        folder's ``tls/`` (as ``dmpc run --secure``).
    on_start : callable LiveRun -> None, optional
        Called in a daemon thread once the run's processes are being started, with the run's
        endpoint, id, certificate directory and folder, and methods to change a setpoint
        (:meth:`LiveRun.setpoint`) and to wait for a step (:meth:`LiveRun.wait_for_step`). What
        it raises is raised again once the run is over and its processes are stopped.

    Returns
    -------
    Result

    Raises
    ------
    RunError
        A process failed.
    PlantModelError
        The plant function failed in the plant process (the message holds its traceback).
    ValueError
        ``plant`` cannot be imported by another process, or ``agents_per_process`` is below 1.
    """
    check_per_process(agents_per_process)
    prepared = _prepared(scenario, method, steps)
    reference = None
    if plant is not None:
        reference = function_reference(plant)
        function, _ = load_plant_function(reference)
        prepared = with_plant_function(prepared, function, reference)
    if not method_spec(prepared.method).distributed:  # one QP in one process: no agents to start
        if secure or on_start is not None:
            raise ValueError(f"secure and on_start apply to a run over Zenoh; method '{prepared.method}' runs no "
                             "agents, in this process (dmpc.simulate)")
        return simulate(prepared.scenario, out=out, plant=plant, progress=progress)
    if secure and agents_per_process > 1:
        raise ValueError("secure=True needs agents_per_process=1: a certificate belongs to one agent")
    run_id = re.sub(r"[^A-Za-z0-9_.-]", "-", prepared.name)[:55] + "-" + secrets.token_hex(4)
    hook = StartHook(on_start, prepared.scenario) if on_start is not None else None
    with _run_folder(out) as (folder, temporary):
        outcome = launch(prepared, folder, run_id, startup_timeout=startup_timeout, show_progress=progress,
                         topology=topology or default_topology(len(group_agents(prepared.names, agents_per_process))),
                         plant_model=reference, agents_per_process=agents_per_process, secure=secure, on_ready=hook)
        if outcome.code == EXIT_INTERRUPTED:
            raise KeyboardInterrupt
        if outcome.code != EXIT_OK:
            _raise_failure(folder, outcome.message, plant is not None)
        if hook is not None:
            hook.finish()
        return load_run(folder, in_temporary_folder=temporary)


def _raise_failure(folder: Path, message: str, has_function: bool) -> None:
    log_path = folder / LOGS / log_file(keys.PLANT_ROLE)
    log = log_path.read_text(errors="replace") if log_path.is_file() else ""
    if has_function and ("PlantModelError" in log or "the plant function" in log):
        tail = "\n".join(log.strip().splitlines()[-40:])
        raise PlantModelError(f"the plant function failed in the plant process; its log:\n{tail}")
    raise RunError(message)
