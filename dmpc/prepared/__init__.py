"""A run ready to start: the shared description every role of a run is built from.

The agents, the plant, the records, the runtimes and the live view all read a
:class:`Prepared`; it is built from a scenario (:func:`dmpc.setup.prepare`) or from a
run bundle (:mod:`dmpc.prepared.bundle`), so it sits below all of them and imports none of them.
"""
from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from dmpc.bus.faults import FaultPlan
from dmpc.core.steps import DEFAULT_METHOD, Coupling, Method, Mode, ProtocolOptions, TriggerOptions
from dmpc.core.system import CoupledSystem
from dmpc.methods import lacks
from dmpc.offline import ControllerDesign
from dmpc.tracking.schedule import SetpointEntry
from dmpc.tracking.targets import DEFAULT_MARGIN

if TYPE_CHECKING:  # the scenario package needs pydantic, which agent processes can do without
    from dmpc.scenario import Scenario

PlantFunction = Callable[[np.ndarray, np.ndarray, int], np.ndarray]
"""``f(x, u, k) -> x_next``: x (n,) and u (m,) in the global order, k the step index."""


@dataclass(frozen=True, eq=False)
class PlantSetup:
    """The plant's model and disturbance for one run.

    Attributes
    ----------
    model : str
        ``nominal`` (the controllers' model), ``exact`` (A, B below) or ``function``.
    A, B : ndarray or None
        The plant's matrices for ``exact``: (n, n) and (n, m).
    disturbance : ndarray or None
        w(k), shape (steps, n); None without a disturbance.
    disturbance_kind : str
        ``uniform``, ``gaussian``, ``file`` or "".
    disturbance_bound : ndarray or None
        |w| <= this, shape (n,): the box of a ``uniform`` disturbance, the largest |w| per state of
        a ``file``; None for ``gaussian`` (unbounded) or without a disturbance.
    function : callable (x, u, k) -> x_next, or None
        The user's plant for ``function``.
    function_name : str
        How the function is named (``module:function``).
    """

    model: str = "nominal"
    A: np.ndarray | None = None
    B: np.ndarray | None = None
    disturbance: np.ndarray | None = None
    disturbance_kind: str = ""
    disturbance_bound: np.ndarray | None = None
    function: PlantFunction | None = None
    function_name: str = ""

    def describe(self) -> dict:
        """What the plant was, for ``summary.json`` (``plant``)."""
        out: dict = {"model": self.model}
        if self.function_name:
            out["function"] = self.function_name
        if self.disturbance is not None:
            out["disturbance"] = self.disturbance_kind
            out["disturbance_max_abs"] = float(np.max(np.abs(self.disturbance), initial=0.0))
        return out


@dataclass(frozen=True)
class Prepared:
    """A scenario ready to run.

    Attributes
    ----------
    scenario : Scenario or None
        None when loaded from a run bundle (dmpc.prepared.bundle).
    system : CoupledSystem
    design : ControllerDesign
    digest : str
        Short hash of the design (:func:`design_digest`); every process of a run must agree on it.
    protocol : ProtocolOptions
    mode : str
    dt : float
    deadline : float or None
    faults : FaultPlan
    name : str
        The scenario's name.
    coupling : str
        ``feedforward`` or ``nominal``.
    method : str
        The control method (:mod:`dmpc.methods`), ``tv-box`` by default.
    plant : PlantSetup
        What the plant simulates (model, disturbance, the user's function); the nominal model by default.
    model : dict or None
        For ``time: continuous``, the discretisation (``dmpc.core.discretisation.DiscreteModel.to_json``).
    setpoints : tuple of SetpointEntry
        The scenario's setpoint schedule (empty: the origin throughout).
    setpoint_margin : float
        The fraction of every bound setpoint targets keep free.
    trigger : TriggerOptions
        When the agents solve (``always``: at every step).
    """

    scenario: "Scenario | None"
    system: CoupledSystem
    design: ControllerDesign
    digest: str
    protocol: ProtocolOptions
    mode: Mode
    dt: float
    deadline: float | None
    faults: FaultPlan = FaultPlan()
    name: str = "scenario"
    coupling: Coupling = "feedforward"
    method: Method = DEFAULT_METHOD
    plant: PlantSetup = PlantSetup()
    model: dict | None = None
    setpoints: tuple[SetpointEntry, ...] = ()
    setpoint_margin: float = DEFAULT_MARGIN
    trigger: TriggerOptions = TriggerOptions()

    @property
    def tracks(self) -> bool:
        """True if the method tracks setpoints (the records carry the targets)."""
        return lacks(self.method, "tracks_setpoints") is None

    @property
    def names(self) -> list[str]:
        return [s.name for s in self.system.subsystems]

    def design_json(self, omega: bool = True) -> dict:
        """The content of ``design.json``: the design, its digest, and how its horizon and beta0 were
        chosen; ``omega=False`` leaves out the rows of X^f."""
        data = self.design.to_json(omega=omega)
        data["digest"] = self.digest
        if self.design.start is not None:
            data["start"] = self.design.start
        if self.model is not None:
            data["model"] = self.model
        return data

    @property
    def plan_wait(self) -> float | None:
        """How long an agent waits for a referenced neighbour plan (half the deadline)."""
        return None if self.deadline is None else 0.5 * self.deadline


def design_digest(design: ControllerDesign, method: Method = DEFAULT_METHOD,
                  trigger: TriggerOptions | None = None) -> str:
    """Short hash of the design, of the method unless it is the default ``tv-box``, and of the
    event trigger if there is one (every process must decide alike).

    Omega enters through the hash of its float64 bytes and its shape: the same for an Omega read
    back from a file (JSON keeps every float exactly), and far cheaper than its text, which has
    millions of entries at a thousand subsystems.
    """
    data = design.to_json(omega=False)
    omega = np.ascontiguousarray(design.terminal.omega, dtype=np.float64)
    data["omega"] = [list(omega.shape), hashlib.sha256(omega.tobytes()).hexdigest()]
    if method != DEFAULT_METHOD:
        data["method"] = method
    if trigger is not None and trigger.event:
        data["trigger"] = trigger.to_json()
    text = json.dumps(data, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]
