"""Setpoints changed while a run goes on, from Python: :func:`setpoint`, and the :class:`LiveRun`
that ``dmpc.run(on_start=...)`` hands to its callable."""
from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Optional, Union

from dmpc.api.scenarios import load_scenario
from dmpc.bus.messages import SetpointAnswer
from dmpc.bus.session import BusError
from dmpc.core.errors import DmpcError
from dmpc.records.files import STEP_LOG, SUMMARY
from dmpc.runtime.setpoints import DEFAULT_TIMEOUT, components, scenario_subsystem, send_setpoint, unanswered_text

Components = Union[None, Sequence[Optional[float]], Mapping[str, Optional[float]]]
"""Requested components: None (all free), one value per component (None: free), or a map by name."""

__all__ = ["LiveRun", "SetpointError", "SetpointRefused", "SetpointUnanswered", "setpoint"]


class SetpointError(DmpcError):
    """A setpoint request that did not take effect (``message`` says why); ``answer`` is the
    coordinator's (None if none came)."""

    def __init__(self, message: str, answer: SetpointAnswer | None = None) -> None:
        super().__init__(message)
        self.answer = answer


class SetpointRefused(SetpointError, ValueError):
    """The coordinator refused the request; the message (and ``answer.reason``) says why."""


class SetpointUnanswered(SetpointError, TimeoutError):
    """No answer: not authorised or no run listening. The coordinator was not reached, or the request
    did not reach it (another run id, a run already over, or a certificate other than the operator's,
    whose request the access control ends unanswered)."""


def setpoint(connect: str | Sequence[str], run_id: str, subsystem: str, x: Components = None, u: Components = None,
             tls: str | Path | None = None, timeout: float = DEFAULT_TIMEOUT, sender: str = "python", *,
             scenario=None) -> SetpointAnswer:
    """Change subsystem ``subsystem``'s setpoint in a running run (as ``dmpc setpoint``).

    The request is taken at a step boundary: from the first step whose target the coordinator has
    not decided yet (usually the next one). The tracking, with its reference governor, then moves
    the system there as fast as the guarantees allow.

    Parameters
    ----------
    connect : str or sequence of str
        The coordinator's endpoint, e.g. ``tcp/127.0.0.1:7447`` (``dmpc run --port``).
    run_id : str
        The run's id.
    subsystem : str
        The subsystem's name in the scenario.
    x, u : sequence or mapping, optional
        The requested states (n_i values) and inputs (m_i values), None for a free one; or a
        mapping by the names of the subsystem's ``states``/``inputs`` (needs ``scenario``).
        Omitted: every component free (a request with both omitted withdraws the subsystem's
        setpoint).
    tls : path, optional
        A certificate directory holding the ``operator`` certificate (``dmpc certs``, or a
        ``dmpc run --secure`` folder's ``tls/``).
    timeout : float
        Seconds to wait for the answer, connecting included.
    sender : str
        This program's name on the bus (the answer's key ends in it).
    scenario : path, mapping or Scenario, optional
        The run's scenario: names in ``x`` and ``u``, and the subsystem and the sizes checked
        before sending.

    Returns
    -------
    dmpc.bus.messages.SetpointAnswer
        Accepted: ``k`` is the first step the request holds at, ``id`` the request's id.

    Raises
    ------
    SetpointRefused
        The coordinator refused it (a value outside X_i or U_i, an unknown subsystem, a method
        that does not track setpoints, a run that is over, ...).
    SetpointUnanswered
        No answer within ``timeout``: not authorised or no run listening (another endpoint or run
        id, a run that is over, or a certificate other than the operator's); or the endpoint
        could not be reached.
    ValueError
        A value, name, endpoint or certificate directory that cannot be used (a
        ``dmpc.DmpcError`` too).
    """
    spec = None
    if scenario is not None:
        spec = scenario_subsystem(load_scenario(scenario), subsystem)
    x_values = components(x, "x", "x", subsystem, spec)
    u_values = components(u, "u", "u", subsystem, spec)
    try:
        answer = send_setpoint(connect, run_id, subsystem, x_values, u_values, sender=sender, tls_dir=tls,
                               timeout=timeout)
    except BusError as exc:
        raise SetpointUnanswered(f"no answer from the coordinator of run {run_id}: {exc}") from None
    if answer is None:
        raise SetpointUnanswered(unanswered_text(run_id, connect, timeout))
    if not answer.accepted:
        raise SetpointRefused(f"refused: {answer.reason}", answer)
    return answer


class LiveRun:
    """A run of ``dmpc.run`` while it goes on, as its ``on_start`` callable sees it.

    Attributes
    ----------
    endpoint : str
        Where the coordinator listens (``tcp/127.0.0.1:<port>``, ``tls/`` with ``secure``).
    run_id : str
    tls : Path or None
        The run's certificate directory (with ``secure=True``); its ``operator`` certificate
        signs the requests.
    folder : Path
        The run folder being written.
    scenario : Scenario, optional
        The run's scenario, which names the components a request may give by name.
    """

    def __init__(self, endpoint: str, run_id: str, tls: Path | None, folder: Path, scenario=None) -> None:
        self.endpoint = endpoint
        self.run_id = run_id
        self.tls = tls
        self.folder = folder
        self._scenario = scenario

    def setpoint(self, subsystem: str, x: Components = None, u: Components = None,
                 timeout: float = DEFAULT_TIMEOUT, sender: str = "python") -> SetpointAnswer:
        """:func:`dmpc.setpoint` for this run: ``subsystem``'s setpoint ``x`` and ``u`` (which may name the
        components), waiting at most ``timeout`` seconds for the answer, sent as ``sender``."""
        return setpoint(self.endpoint, self.run_id, subsystem, x, u, tls=self.tls, timeout=timeout, sender=sender,
                        scenario=self._scenario)

    def steps(self) -> int:
        """The number of steps recorded so far."""
        try:
            return (self.folder / STEP_LOG).read_bytes().count(b"\n")
        except FileNotFoundError:
            return 0

    def step(self, k: int) -> dict:
        """Step k's line of ``steps.jsonl`` (docs/records.md); KeyError if it is not recorded yet."""
        try:
            lines = (self.folder / STEP_LOG).read_text().splitlines()
        except FileNotFoundError:
            lines = []
        if k >= len(lines) or k < 0:
            raise KeyError(f"step {k} is not recorded (yet): {len(lines)} steps so far")
        return json.loads(lines[k])

    def wait_for_step(self, k: int, timeout: float = 60.0, poll: float = 0.02) -> bool:
        """Wait until step k is recorded, looking every ``poll`` seconds; False if ``timeout`` s pass first
        or the run ends without it."""
        deadline = time.monotonic() + timeout
        while True:
            if self.steps() > k:
                return True
            if (self.folder / SUMMARY).exists() or time.monotonic() >= deadline:
                return self.steps() > k
            time.sleep(poll)


class StartHook:
    """The ``on_ready`` of :func:`dmpc.runtime.launcher.launch` that calls ``on_start(LiveRun)`` once,
    in a daemon thread, and keeps what it raised to raise it again after the run; ``scenario`` (the
    run's) names the components of the LiveRun's requests."""

    def __init__(self, on_start: Callable[[LiveRun], object], scenario) -> None:
        self.on_start = on_start
        self.scenario = scenario
        self.live: LiveRun | None = None
        self.error: BaseException | None = None
        self.thread: threading.Thread | None = None

    def __call__(self, out: Path, run_id: str, endpoint: str, tls_dir: Path | None) -> None:
        if self.live is not None:  # the run starts again on another port: the same run, a new endpoint
            self.live.endpoint = endpoint
            return
        self.live = LiveRun(endpoint, run_id, tls_dir, Path(out), self.scenario)
        self.thread = threading.Thread(target=self._call, name="dmpc-on-start", daemon=True)
        self.thread.start()

    def _call(self) -> None:
        try:
            assert self.live is not None
            self.on_start(self.live)
        except BaseException as exc:  # noqa: BLE001 - raised again by dmpc.run once the processes are stopped
            self.error = exc

    def finish(self, wait: float = 1.0) -> None:
        """Give the callable ``wait`` s more to end, then raise what it raised (if anything)."""
        if self.thread is not None:
            self.thread.join(wait)
        if self.error is not None:
            raise self.error
