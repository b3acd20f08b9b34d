"""What a run's steps are made of: the protocol's settings and the record of one step.

Shared by the coordinator that builds the records, the centralised and direct loops, the run
folder that writes them and the live view that shows them, so it sits below all of them.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal, get_args

import numpy as np

Mode = Literal["lockstep", "realtime"]
"""How steps follow each other: as soon as every plan is in (``lockstep``), or every dt (``realtime``)."""
MODES: tuple[Mode, ...] = get_args(Mode)
Coupling = Literal["feedforward", "nominal"]
"""What an agent's prediction takes of its neighbours: their assumed trajectories (``feedforward``),
or nothing (``nominal``, the paper's decoupled model)."""
COUPLINGS: tuple[Coupling, ...] = get_args(Coupling)
Method = Literal["tv-box", "tv-box-opt", "tv-box-coop", "fixed-box", "ellipsoid", "ellipsoid-adaptive", "centralized"]
"""The name of a control method (``options.method``, ``--method``; dmpc.methods says what each does
and what it can do: its ``MethodSpec``)."""
METHOD_NAMES: tuple[Method, ...] = get_args(Method)
DEFAULT_METHOD: Method = "tv-box"

Trigger = Literal["always", "event"]
"""When an agent solves: at every step (``always``), or when its event trigger fires (``event``;
docs/algorithm.md, "Event-triggered DMPC")."""
TRIGGERS: tuple[Trigger, ...] = get_args(Trigger)

NO_SEED = "no centralised seed: "
"""Starts the part of a k = 0 note that says why the centralised QP gave no plan to start from,
when the agents' first round was infeasible (the verdict's ``infeasible-start`` quotes it)."""


@dataclass(frozen=True)
class ProtocolOptions:
    """What the coordinator needs from the scenario's options.

    Attributes
    ----------
    steps : int
    rounds, initial_rounds : int
        The most Jacobi rounds per step, at k > 0 and at k = 0 (the scenario's
        ``options.iterations`` and ``options.initial_iterations``).
    tolerance, initial_tolerance : float
        The rounds stop early when the largest plan change is below this.
    cooperative_step : {"line", "equal"}
        How a round of the cooperative method combines the agents' proposals
        (``options.cooperative_step``; docs/algorithm.md, "Cooperative DMPC"); unused by the others.
    """

    steps: int
    rounds: int = 1
    tolerance: float = 1e-9
    initial_rounds: int = 200
    initial_tolerance: float = 1e-9
    cooperative_step: Literal["line", "equal"] = "line"

    def to_json(self) -> dict[str, Any]:
        """As run.json holds it: the scenario's option names."""
        data: dict[str, Any] = {"steps": self.steps, "iterations": self.rounds, "tolerance": self.tolerance,
                                "initial_iterations": self.initial_rounds, "initial_tolerance": self.initial_tolerance}
        if self.cooperative_step != "line":  # the default is left out: run.json as without the option
            data["cooperative_step"] = self.cooperative_step
        return data

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> "ProtocolOptions":
        """From :meth:`to_json`'s content.

        Parameters
        ----------
        data : dict
            The map :meth:`to_json` wrote (run.json's ``protocol``): ``steps``, ``iterations``,
            ``tolerance``, ``initial_iterations``, ``initial_tolerance`` and, optionally,
            ``cooperative_step`` (``"line"`` when absent or anything but ``"equal"``).
        """
        return cls(steps=int(data["steps"]), rounds=int(data["iterations"]), tolerance=float(data["tolerance"]),
                   initial_rounds=int(data["initial_iterations"]), initial_tolerance=float(data["initial_tolerance"]),
                   cooperative_step="equal" if data.get("cooperative_step") == "equal" else "line")


@dataclass(frozen=True)
class TriggerOptions:
    """The event trigger of every agent (``options.trigger`` and its thresholds).

    Attributes
    ----------
    mode : {"always", "event"}
    threshold : tuple of float
        Per subsystem, the largest prediction error ||x_i(k) - z_i(k|k-1)||_inf kept (its states' units).
    cost : tuple of float
        Per subsystem, the largest cost an agent gives up by keeping its plan.
    max_keep : int or None
        Most consecutive keeps of an agent (None: no limit).
    """

    mode: Trigger = "always"
    threshold: tuple[float, ...] = ()
    cost: tuple[float, ...] = ()
    max_keep: int | None = None

    @property
    def event(self) -> bool:
        return self.mode == "event"

    def to_json(self) -> dict[str, Any]:
        return {"mode": self.mode, "threshold": list(self.threshold), "cost": list(self.cost),
                "max_keep": self.max_keep}

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> "TriggerOptions":
        """From :meth:`to_json`'s content.

        Parameters
        ----------
        data : dict
            The map :meth:`to_json` wrote: ``mode`` (``"always"`` when absent), ``threshold`` and
            ``cost`` (lists of float, empty when absent) and ``max_keep`` (an int, or None or absent:
            no limit).

        Raises
        ------
        ValueError
            ``mode`` is not one of :data:`TRIGGERS`.
        """
        mode = data.get("mode", "always")
        if mode not in TRIGGERS:
            raise ValueError(f"trigger mode {mode!r} is not one of {', '.join(TRIGGERS)}")
        max_keep = data.get("max_keep")
        return cls(mode=mode, threshold=tuple(float(v) for v in data.get("threshold", ())),
                   cost=tuple(float(v) for v in data.get("cost", ())),
                   max_keep=None if max_keep is None else int(max_keep))


@dataclass(frozen=True)
class StepRecord:
    """Everything recorded about one step, built once when the step completes.

    Array shapes: x (n,), u (m,), alpha (n,), x_next (n,); per-agent lists have M entries.
    ``r`` and ``r_next`` (M,) are the ellipsoid levels of the ellipsoid methods (None otherwise);
    those methods record alpha = 0 and beta = NaN.

    ``solve_reason`` (M,), with an event trigger: per agent, why it solved ("" where it kept its
    plan, or without a plan of its own); None without one.

    ``tracking`` (a :class:`dmpc.tracking.tracker.TrackingStep`) says what the step tracked: the
    request, its target and the target applied (None where nothing was ever requested). With
    estimation a request names outputs (``request.y``, (p,); its ``x`` all free), recorded as
    ``setpoint_y`` (docs/records.md).

    ``latency`` (M,) is, per agent, the time from the agent publishing the plan the step used to
    the host receiving it (NaN for an agent without a plan, or where no clock is kept);
    ``step_time`` is the step's wall time on the host's clock (NaN where none is kept).

    Attributes
    ----------
    k : int
        The step index.
    x, u : ndarray, shapes (n,) and (m,)
        The measured state x(k) and the input applied u(k), in the global order.
    alpha, beta : ndarray (n,), float
        The terminal box of step k (with setpoints, alpha is relative to the target applied).
    x_next : ndarray, shape (n,)
        The state x(k+1) the plant reached.
    alpha_next, beta_next : ndarray (n,), float
        The terminal box of step k+1 (alpha(k+1) = (A+BK) eta(k), beta(k+1) = sigma(alpha(k+1))).
    J : float
        sum_i J_i*(k), the sum of ``J_agents``.
    J_agents : list of float, M entries
        Each agent's own cost (a fallback agent's: the cost of its shifted candidate).
    S : float
        S(x(k)) = sum_i ||x_i(k)||^2 / |N_i| (:meth:`dmpc.core.system.CoupledSystem.spread`).
    rounds : int
        The Jacobi rounds the step used.
    max_change : float
        The largest plan change in the last round (NaN where no rounds are run).
    status : list of str, M entries
        Per agent, its QP status (a QPStatus value), ``missed`` or ``kept``.
    fallback : list of bool, M entries
        Whether the plant applied agent i's fallback.
    fallback_reason : list of str, M entries
        Why (``missed``, ``lost``, ``qp infeasible``, ..., ``input outside U_i``); "" without a fallback.
    solve_time : list of float, M entries
        Seconds in the solver per agent (last round; NaN for an agent that sent nothing).
    qp_iterations : list of int, M entries
        The solver's iteration count per agent (last round).
    plans_z, plans_v : list of ndarray, shapes (N+1, n_i) and (N, m_i)
        The plan the step recorded for each agent (its shifted candidate for a fallback).
    latency : list of float, M entries
        See above.
    step_time : float
        See above.
    note : str
        What else happened in the step (an agent lost or back, a setpoint taken, how k = 0
        started); "" if nothing.
    r, r_next : ndarray (M,) or None
        See above.
    tracking : TrackingStep or None
        See above.
    solve_reason : list of str or None
        See above.
    estimate : Estimate or None
        With estimation (:class:`dmpc.coordinator.estimation.Estimate`): the outputs y(k) measured,
        the estimates x^(k), d^(k) the controllers worked from, and the innovation's size; None
        without. ``x`` is then the plant's own state, where the plant reports it.
    """

    k: int
    x: np.ndarray
    u: np.ndarray
    alpha: np.ndarray
    beta: float
    x_next: np.ndarray
    alpha_next: np.ndarray
    beta_next: float
    J: float
    J_agents: list[float]
    S: float
    rounds: int
    max_change: float
    status: list[str]
    fallback: list[bool]
    fallback_reason: list[str]
    solve_time: list[float]
    qp_iterations: list[int]
    plans_z: list[np.ndarray]
    plans_v: list[np.ndarray]
    latency: list[float]
    step_time: float
    note: str = ""
    r: np.ndarray | None = None
    r_next: np.ndarray | None = None
    tracking: Any = None
    solve_reason: list[str] | None = None
    estimate: Any = None
