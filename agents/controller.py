"""The computing part of agent i: assumed trajectories -> coupling feed-forward -> QP_i, and
the plan that answers a release (:meth:`AgentController.answer`, the one path from a release
to a plan message for the agent node and the direct loop).

Pure: no bus; no clock other than the solver's own timing and the caller's, if it gives one.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from dmpc.agents.local_qp import LocalQP, QPSolution
from dmpc.agents.trigger import TARGET, Decision, KeepRule
from dmpc.bus.messages import Kept, PlanMessage, Release
from dmpc.core.steps import TriggerOptions
from dmpc.core.system import CoupledSystem
from dmpc.core.trajectories import OperatingPoint, Plan, assumed_trajectory, coupling_feedforward, kept_around
from dmpc.core.unconstrained import UnconstrainedBound
from dmpc.methods import DEFAULT_METHOD, Method, terminal_policy
from dmpc.offline import ControllerDesign


class AgentController:
    """Builds and solves QP_i for subsystem ``index`` of ``system``.

    Parameters
    ----------
    system : CoupledSystem
    design : ControllerDesign
    index : int
        0-based subsystem index.
    coupling : {"feedforward", "nominal"}
        ``nominal`` drops the neighbours' terms from the prediction (the paper's model (5)).
    solver_settings : dict, optional
    method : str
        A distributed method of :mod:`dmpc.methods`: it sets the terminal rows of QP_i.
    trigger : TriggerOptions, optional
        With ``event``, the agent keeps its shifted plan while :class:`~dmpc.agents.trigger.KeepRule`
        allows (docs/algorithm.md, "Event-triggered DMPC"); otherwise it solves at every release.
    """

    def __init__(self, system: CoupledSystem, design: ControllerDesign, index: int, coupling: str = "feedforward",
                 solver_settings: dict | None = None, method: Method = DEFAULT_METHOD,
                 trigger: TriggerOptions | None = None) -> None:
        self.index = index
        self.system = system
        sub = system.subsystems[index]
        self.name = sub.name
        self._own = system.xs(index)
        self._state_slices = {j: system.xs(j) for j in system.neighbours[index]}  # i and its neighbours
        self.N = design.horizon
        self.n = sub.n
        self.neighbours = tuple(j for j in system.neighbours[index] if j != index)
        self.use_feedforward = coupling == "feedforward"
        K = design.gains.K
        self._gamma = {j: system.subsystems[j].A + system.subsystems[j].B @ K[j] for j in self.neighbours}
        self._K = {j: K[j] for j in self.neighbours}
        self._A = [system.coupling(index, j)[0] for j in self.neighbours]
        self._B = [B if B.any() else None for B in (system.coupling(index, j)[1] for j in self.neighbours)]
        self.method = method
        terminal = terminal_policy(method, system, design).agent_terminal(index)
        self.qp = LocalQP(sub, design.gains.P[index], design.horizon, design.tightening[index], solver_settings,
                          terminal=terminal)
        self._plan: Plan | None = None  # this agent's plan of the last step answered
        self._plan_target = OperatingPoint.origin(system.n, system.m)  # the operating point it was made around
        self._kept = 0  # consecutive keeps
        self._rule = None
        if trigger is not None and trigger.event:
            P, K_i = design.gains.P[index], K[index]
            self._rule = KeepRule(self.qp, UnconstrainedBound(sub.A, sub.B, sub.Q, sub.R, P, design.horizon), sub.Q,
                                  sub.R, P, sub.A + sub.B @ K_i, K_i, trigger.threshold[index], trigger.cost[index],
                                  trigger.max_keep)

    def feedforward(self, k: int, states: dict[int, np.ndarray], plans: dict[int, Plan | None]) -> np.ndarray:
        """c_i(t) for t = 0..N-1 from the neighbours' assumed trajectories, shape (N, n_i).

        Zeros with the ``nominal`` coupling or without neighbours.

        Parameters
        ----------
        k : int
            The step.
        states : dict j -> ndarray (n_j,)
            The measured states x_j(k); every neighbour's is needed.
        plans : dict j -> Plan or None
            The neighbours' plans to build the assumed trajectories from (missing or None: the
            K-rollout from x_j(k)).
        """
        if not self.use_feedforward or not self.neighbours:
            return np.zeros((self.N, self.n))
        assumed = [assumed_trajectory(plans.get(j), k, states[j], self.N, self._gamma[j], self._K[j])
                   for j in self.neighbours]
        return coupling_feedforward(self._A, self._B, assumed, self.N, self.n)

    def solve(self, k: int, states: dict[int, np.ndarray], centre: np.ndarray, size: float,
              plans: dict[int, Plan | None], coupling: np.ndarray | None = None) -> QPSolution:
        """Solve QP_i at step k.

        Parameters
        ----------
        k : int
        states : dict j -> ndarray (n_j,)
            Measured states of i and its neighbours.
        centre : ndarray, shape (n_i,)
            The released terminal centre (alpha_i for the box methods, zeros for the ellipsoids).
        size : float
            The released terminal size (the box radius beta, or the ellipsoid level r_i).
        plans : dict j -> Plan or None
            The neighbours' plans to build the assumed trajectories from (None: K-rollout).
        coupling : ndarray, shape (N, n_i), optional
            Their feed-forward c_i(t), when it is already at hand (computed from them otherwise).
        """
        c = self.feedforward(k, states, plans) if coupling is None else coupling
        return self.qp.solve(states[self.index], c, centre, size)

    def operating_point(self, release: Release) -> OperatingPoint:
        """The operating point (x_s (n,), u_s (m,)) of the whole system that ``release``'s step is
        controlled around: its setpoint target, or the origin, which the wire leaves out
        (:class:`~dmpc.bus.messages.Release`)."""
        if release.target is None:
            return OperatingPoint.origin(self.system.n, self.system.m)
        point = OperatingPoint(*release.target)
        if point.u.shape != (self.system.m,):
            raise ValueError(f"a release's target has {point.u.size} inputs, the system {self.system.m}")
        return point

    def _view(self, release: Release, point: OperatingPoint, plans: dict[int, Plan | None]
              ) -> tuple[dict[int, np.ndarray], dict[int, Plan | None], OperatingPoint]:
        """The states (n_j,) of this agent and its neighbours and their plans at the release, in
        deviation coordinates around the step's operating point ``point``, and this agent's part
        of it (x_s_i, u_s_i); the QP's stage rows moved to it (docs/algorithm.md, "Setpoints")."""
        parts = {j: point.subsystem(self.system, j) for j in self._state_slices}
        own = parts[self.index]
        self.qp.set_target(*own)
        states = {j: parts[j].state_around(release.x[cut]) for j, cut in self._state_slices.items()}
        moved = {j: parts[j].plan_around(plan) for j, plan in plans.items() if j in parts}
        return states, moved, own

    def _decide(self, release: Release, point: OperatingPoint, own: OperatingPoint, x: np.ndarray,
                coupling: np.ndarray, centre: np.ndarray, size: float) -> Decision:
        """The event trigger's decision at round 0 (:class:`dmpc.agents.trigger.KeepRule`): ``x``
        (n_i,), ``coupling`` (N, n_i) and ``centre`` (n_i,) around this agent's part ``own`` of the
        step's operating point ``point``."""
        assert self._rule is not None
        previous = self._plan
        if previous is not None and release.reference(self.index) != (previous.k, previous.round):
            previous = None  # the coordinator holds another plan of this agent's (a fallback, a refusal)
        if previous is not None and not self._plan_target.same_as(point):
            return Decision(TARGET)
        return self._rule.decide(release.k, x, coupling, centre, size, own.plan_around(previous), self._kept)

    def answer(self, release: Release, plans: dict[int, Plan | None], run_id: str,
               clock: Callable[[], float] | None = None) -> PlanMessage | Kept:
        """Answer ``release``: solve QP_i and return its plan message, or, with an event trigger
        that keeps the shifted plan, the Kept notice.

        Parameters
        ----------
        release : Release
            Gives the step and round, the measured state x (n,) (this agent's and its
            neighbours' parts are used), and this agent's terminal centre and size.
        plans : dict j -> Plan or None
            The neighbours' plans the release refers to (None: K-rollout).
        run_id : str
        clock : callable () -> float, optional
            The sender's clock, read once the plan is solved: the message's ``sent_at``
            (the records' latency); 0 without one.
        """
        point = self.operating_point(release)
        states, plans, own = self._view(release, point, plans)
        centre, size = release.centres[self._own], float(release.sizes[self.index])
        reason, coupling = "", None
        if self._rule is not None and release.round == 0:
            coupling = self.feedforward(release.k, states, plans)
            decision = self._decide(release, point, own, states[self.index], coupling, centre, size)
            if decision.keep:
                assert decision.plan is not None
                kept = Plan(release.k, 0, *own.trajectory_back(decision.plan.z, decision.plan.v))
                self._remember(kept, point, kept=True)
                return Kept(run=run_id, k=release.k, round=release.round, sender=self.name,
                            sent_at=clock() if clock is not None else 0.0)
            reason = decision.reason
        if coupling is None:
            sol = self.solve(release.k, states, centre, size, plans)
        else:
            sol = self.solve(release.k, states, centre, size, plans, coupling=coupling)
        z, v = own.trajectory_back(sol.z, sol.v)
        self._remember(Plan(release.k, release.round, z, v) if sol.status.feasible else None, point)
        return PlanMessage(run=run_id, k=release.k, round=release.round, sender=self.name,
                           status=sol.status.value, z=z, v=v, cost=sol.cost, solve_time=sol.solve_time,
                           qp_iterations=int(sol.iterations), sent_at=clock() if clock is not None else 0.0,
                           reason=reason)

    def neighbour_kept(self, j: int, plan: Plan, release: Release) -> Plan:
        """Neighbour j's plan of ``release``'s step kept (its ``plan`` of the step before, with the
        release's state, centre and operating point), as the neighbour and the coordinator built it."""
        part = self.system.xs(j)
        return kept_around(plan, release.k, release.x[part], release.centres[part], self._gamma[j], self._K[j],
                           self.operating_point(release).subsystem(self.system, j))

    def _remember(self, plan: Plan | None, point: OperatingPoint, kept: bool = False) -> None:
        """This agent's plan of the step (its plant coordinates) and the operating point it was made around."""
        self._plan, self._plan_target = plan, point
        self._kept = self._kept + 1 if kept else 0
