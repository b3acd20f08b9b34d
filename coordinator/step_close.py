"""The close of a step: each agent's part (its plan, or its fallback), the inputs, the next
terminal sets and target, and the record (docs/algorithm.md, "Online step k, agent i", item 7).

An agent without a usable plan of the step (missed, lost, infeasible, refused) gets the shifted
candidate of its last plan, its input v*(k|k') + K_i (x_i(k) - z*(k|k')) projected onto U_i, both
taken around the step's operating point.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from dmpc.coordinator.candidates import Candidates
from dmpc.coordinator.open_step import OpenStep
from dmpc.coordinator.refusals import INPUT_REFUSED, InputRefusals
from dmpc.coordinator.setpoint_intake import SetpointIntake
from dmpc.core.steps import StepRecord
from dmpc.core.system import CoupledSystem, project_onto
from dmpc.core.trajectories import Plan
from dmpc.methods.policy import TerminalPolicy, TerminalState
from dmpc.tracking.targets import Target
from dmpc.tracking.tracker import TrackingStep


@dataclass(frozen=True)
class AgentStep:
    """One agent's part of a step record.

    Attributes
    ----------
    u : ndarray, shape (m_i,)
        The input applied.
    eta : ndarray, shape (n_i,)
        Its terminal state (of its plan, or of its fallback's candidate).
    J : float
        Its part of the step's cost.
    status : str
        What its answer said (the QP status, ``kept``, or ``missed``).
    fallback : bool
        True where its plan of the step was not usable.
    reason : str
        Why it fell back ("" otherwise).
    solve_time : float
        Seconds in its solver (NaN without an answer).
    qp_iterations : int
        Its solver's iterations.
    latency : float
        Seconds from its answer's publication to its acceptance (NaN without one).
    z : ndarray, shape (N+1, n_i)
    v : ndarray, shape (N, m_i)
        The plan the step recorded for it.
    solved_because : str
        Why it solved rather than kept (an event trigger; "" otherwise).
    plan : Plan or None
        Its plan of the step, which becomes its last plan (None for a fallback).
    """

    u: np.ndarray
    eta: np.ndarray
    J: float
    status: str
    fallback: bool
    reason: str
    solve_time: float
    qp_iterations: int
    latency: float
    z: np.ndarray
    v: np.ndarray
    solved_because: str = ""
    plan: Plan | None = None


@dataclass(frozen=True)
class PendingStep:
    """What a completed step's record is made of, fixed when the step closes.

    Attributes
    ----------
    k : int
    x : ndarray, shape (n,)
        The state x(k).
    u : ndarray, shape (m,)
        The inputs applied.
    alpha : ndarray, shape (n,)
    beta : float
        The terminal sets of step k (box centres and radius).
    rounds : int
    agents : list of AgentStep
        Each agent's part.
    note : str
    r : ndarray, shape (M,), or None
        The ellipsoid levels of step k (the ellipsoid methods).
    terminal : TerminalState
        The terminal sets of step k+1.
    max_change : callable () -> float
        The last round's plan change (measured when the record is built).
    target : Target
        The target of the next step.
    tracking : TrackingStep or None
        What the step tracked.
    triggered : bool
        An event trigger: the record says why each agent solved.
    estimate : Estimate or None
        With estimation: the outputs measured and the estimates the step was controlled from.
    """

    k: int
    x: np.ndarray
    u: np.ndarray
    alpha: np.ndarray
    beta: float
    rounds: int
    agents: list[AgentStep]
    note: str
    r: np.ndarray | None
    terminal: TerminalState
    max_change: Callable[[], float]
    target: Target  # the target of the next step
    tracking: TrackingStep | None = None
    triggered: bool = False  # an event trigger: the record says why each agent solved
    estimate: Any = None  # with estimation: what the controllers saw (dmpc.coordinator.estimation.Estimate)

    def record(self, x_next: np.ndarray, step_time: float, system: CoupledSystem) -> StepRecord:
        """The step's record, with ``x_next`` = x(k+1) (n,), ``step_time`` the step's wall time (s)
        and the ``system`` (for the spread S(x))."""
        agents, nxt = self.agents, self.terminal
        J_agents = [a.J for a in agents]
        return StepRecord(
            k=self.k, x=self.x, u=self.u, alpha=self.alpha, beta=self.beta, alpha_next=nxt.alpha, beta_next=nxt.beta,
            J=float(np.sum(J_agents)), J_agents=J_agents, S=system.spread(self.x), rounds=self.rounds,
            max_change=self.max_change(), status=[a.status for a in agents], fallback=[a.fallback for a in agents],
            fallback_reason=[a.reason for a in agents], solve_time=[a.solve_time for a in agents],
            qp_iterations=[a.qp_iterations for a in agents], plans_z=[a.z for a in agents],
            plans_v=[a.v for a in agents], latency=[a.latency for a in agents], note=self.note, r=self.r,
            r_next=nxt.r, x_next=x_next, step_time=step_time, tracking=self.tracking,
            solve_reason=[a.solved_because for a in agents] if self.triggered else None, estimate=self.estimate)


class StepCloser:
    """Closes the steps of one run.

    Parameters
    ----------
    system : CoupledSystem
    candidates : Candidates
        The agents' terminal controllers (candidates, fallback inputs, costs).
    policy : TerminalPolicy
        The method's terminal sets: the fallback's terminal state and the next step's sets.
    refusals : InputRefusals
        Which answers were refused (their fallback applies).
    setpoints : SetpointIntake
        What each step tracked and the next step's target.
    triggered : bool
        The agents have an event trigger: the records say why each agent solved.
    """

    def __init__(self, system: CoupledSystem, candidates: Candidates, policy: TerminalPolicy,
                 refusals: InputRefusals, setpoints: SetpointIntake, triggered: bool) -> None:
        self.system = system
        self.candidates = candidates
        self.policy = policy
        self.refusals = refusals
        self.setpoints = setpoints
        self.triggered = triggered

    def close(self, step: OpenStep, x: np.ndarray, terminal: TerminalState, last_plan: Sequence[Plan | None],
              lost: set[int], max_change: Callable[[], float], agents: list[AgentStep] | None = None,
              disturbance: np.ndarray | None = None) -> PendingStep:
        """Close ``step``: every agent's input and terminal state decide the next terminal sets and
        the next target.

        Parameters
        ----------
        step : OpenStep
        x : ndarray, shape (n,)
            The measured state x(k) (a copy the record keeps).
        terminal : TerminalState
            The terminal sets of step k.
        last_plan : sequence of Plan or None
            Per agent: its last plan (made at k' < k; None if it never had one).
        lost : set of int
            The agents lost now (their fallback says so).
        max_change : callable () -> float
            The last round's plan change, for the record.
        agents : list of AgentStep, optional
            The agents' parts as the round combiner made them (the cooperative iterate's); by
            default each agent's plan of the step, or its fallback (:meth:`agent_step`).
        disturbance : ndarray, shape (n_d,), optional
            With estimation, the disturbance estimate the next step's target is computed from.
        """
        if agents is None:
            x_parts = self.system.split_state(x)
            agents = [self.agent_step(i, x_parts[i], step, terminal, last_plan[i], lost) for i in range(self.system.M)]
        u = np.concatenate([a.u for a in agents])
        eta = np.concatenate([a.eta for a in agents])
        tracking, target = self.setpoints.close_step(step.k, eta, disturbance)
        # the next step's terminal set is around its target (docs/algorithm.md, "Setpoints")
        nxt = self.policy.update(terminal, eta - target.x, target.scale)
        return PendingStep(k=step.k, x=x, u=u, alpha=terminal.alpha.copy(), beta=terminal.beta, rounds=step.round + 1,
                           agents=agents, note="; ".join(t for t in (step.note, nxt.note) if t), r=terminal.r,
                           terminal=nxt, max_change=max_change, tracking=tracking, target=target,
                           triggered=self.triggered)

    def agent_step(self, i: int, x_i: np.ndarray, step: OpenStep, terminal: TerminalState, last: Plan | None,
                   lost: set[int]) -> AgentStep:
        """Agent i's part of ``step`` from the measured x_i (n_i,): its plan of the step, or its
        fallback (the shifted candidate of its ``last`` plan, input projected onto U_i, its
        terminal state as the method's ``terminal`` sets of step k give it), with what the record
        says of it (``lost``: the agents lost now, whose fallback reason says so)."""
        msg = step.answers.get(i)
        plan = step.latest.get(i)
        point = step.point.subsystem(self.system, i)
        if msg is None:
            status, solve_time, qp_iterations = "missed", math.nan, 0
        else:
            status, solve_time, qp_iterations = msg.status, msg.solve_time, msg.qp_iterations
        latency, solved_because = step.latency(i), step.solve_reason.get(i, "")
        if plan is not None:
            if msg is not None and self.refusals.usable(i, msg):
                J = float(msg.cost)
            else:  # an earlier round's plan, or the centralised seed at k = 0: its candidate's cost
                J = self.candidates.candidate_cost(i, point.plan_around(plan), step.k)
            return AgentStep(u=plan.v[0], eta=plan.z[-1], J=J, status=status, fallback=False, reason="",
                             solve_time=solve_time, qp_iterations=qp_iterations, latency=latency, z=plan.z,
                             v=plan.v, solved_because=solved_because, plan=plan)
        around, x_around = point.plan_around(last), point.state_around(x_i)
        u_c = self.candidates.fallback_input(i, around, step.k, x_around)
        z_c, v_c = self.candidates.candidate(i, around, step.k, x_around)
        eta = self.policy.fallback_terminal(terminal, i, z_c[-1])
        z_c, v_c = point.trajectory_back(z_c, v_c)
        if msg is None:
            reason = "lost" if i in lost else "missed"
        else:
            reason = INPUT_REFUSED if self.refusals.refused(i, msg) else f"qp {msg.status}"
        return AgentStep(u=project_onto(self.system.subsystems[i].input_set, u_c + point.u), eta=eta + point.x,
                         J=self.candidates.candidate_cost(i, around, step.k) if around is not None else math.nan,
                         status=status, fallback=True, reason=reason, solve_time=solve_time,
                         qp_iterations=qp_iterations, latency=latency, z=z_c, v=v_c, solved_because=solved_because)
