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
from dmpc.core.measurement import MeasurementNoise
from dmpc.core.steps import DEFAULT_METHOD, Coupling, Method, Mode, ProtocolOptions, TriggerOptions
from dmpc.core.system import CoupledSystem
from dmpc.estimation.kalman import EstimatorDesign
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
    measurement_noise : MeasurementNoise or None
        v(k) (p,), added to the outputs y(k) = C x(k) the plant reports; None: exact measurements.
    """

    model: str = "nominal"
    A: np.ndarray | None = None
    B: np.ndarray | None = None
    disturbance: np.ndarray | None = None
    disturbance_kind: str = ""
    disturbance_bound: np.ndarray | None = None
    function: PlantFunction | None = None
    function_name: str = ""
    measurement_noise: MeasurementNoise | None = None

    def describe(self) -> dict:
        """What the plant was, for ``summary.json`` (``plant``)."""
        out: dict = {"model": self.model}
        if self.function_name:
            out["function"] = self.function_name
        if self.disturbance is not None:
            out["disturbance"] = self.disturbance_kind
            out["disturbance_max_abs"] = float(np.max(np.abs(self.disturbance), initial=0.0))
        if self.measurement_noise is not None:
            out["measurement_noise_max_std"] = float(np.max(self.measurement_noise.std, initial=0.0))
            out["measurement_noise_seed"] = self.measurement_noise.seed
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
    estimator : EstimatorDesign or None
        The agents' observers (scenario ``estimation``): the augmented model with every subsystem's C
        and disturbance model, and the gains; None without estimation (the plant reports the whole
        state).
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
    estimator: EstimatorDesign | None = None

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
        if self.estimator is not None:
            data["estimation"] = estimation_json(self.estimator)
        return data

    @property
    def plan_wait(self) -> float | None:
        """How long an agent waits for a referenced neighbour plan (half the deadline)."""
        return None if self.deadline is None else 0.5 * self.deadline


def estimation_json(estimator: EstimatorDesign) -> dict:
    """The estimator's figures for ``design.json`` and ``dmpc design --json`` (``estimation``): per
    subsystem its disturbance model, outputs p, disturbances n_d and the spectral radius of its own
    filter's error dynamics (couplings left out); the coupled estimator's spectral radius (below 1);
    and the ranks of the detectability checks.

    Parameters
    ----------
    estimator : EstimatorDesign
    """
    model = estimator.model
    subsystems = {part.name: {"disturbance": part.kind, "outputs": part.p, "disturbances": part.nd,
                              "radius": gain.radius}
                  for part, gain in zip(model.parts, estimator.gains)}
    out: dict = {"subsystems": subsystems, "coupled_radius": estimator.radius}
    if estimator.detectability:
        out["detectability"] = [{"where": d.where, "n": d.n, "nd": d.nd, "p": d.p, "rank": d.rank}
                                for d in estimator.detectability]
    return out


def _estimator_hash(estimator: EstimatorDesign) -> dict:
    """What every process's estimator must agree on: each subsystem's disturbance model, C and gain L
    (the hash of their float64 bytes)."""
    digest = hashlib.sha256()
    for part, gain in zip(estimator.model.parts, estimator.gains):
        for matrix in (part.C, gain.L):
            array = np.ascontiguousarray(matrix, dtype=np.float64)
            digest.update(repr(array.shape).encode())
            digest.update(array.tobytes())
    return {"disturbance": [part.kind for part in estimator.model.parts], "gains": digest.hexdigest()}


def design_digest(design: ControllerDesign, method: Method = DEFAULT_METHOD,
                  trigger: TriggerOptions | None = None, estimator: EstimatorDesign | None = None) -> str:
    """Short hash of the design, of the method unless it is the default ``tv-box``, of the
    event trigger if there is one, and of the estimator if there is one (every process must decide
    alike).

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
    if estimator is not None:
        data["estimation"] = _estimator_hash(estimator)
    text = json.dumps(data, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]
