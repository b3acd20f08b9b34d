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
from dmpc.core.trajectories import Plan, assumed_trajectory, coupling_feedforward, kept_around, relative_to
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
        self._plan_target: tuple[np.ndarray, np.ndarray] | None = None
        self._kept = 0  # consecutive keeps
        self._rule = None
        if trigger is not None and trigger.event:
            P, K_i = design.gains.P[index], K[index]
            self._rule = KeepRule(self.qp, UnconstrainedBound(sub.A, sub.B, sub.Q, sub.R, P, design.horizon), sub.Q,
                                  sub.R, P, sub.A + sub.B @ K_i, K_i, trigger.threshold[index], trigger.cost[index],
                                  trigger.max_keep)

    def feedforward(self, k: int, states: dict[int, np.ndarray], plans: dict[int, Plan | None]) -> np.ndarray:
        """c_i(t) for t = 0..N-1 from the neighbours' assumed trajectories, shape (N, n_i)."""
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

    def _view(self, release: Release, plans: dict[int, Plan | None]) -> tuple[dict, dict, Offset]:
        """The states of this agent and its neighbours and their plans at the release, in
        deviation coordinates around the setpoint target, and that target's own part (x_s_i,
        u_s_i); the QP's stage rows moved to it (docs/algorithm.md, "Setpoints"). Without a
        target: as they are, and None."""
        x = release.x
        states = {j: x[part] for j, part in self._state_slices.items()}
        if release.target is None:
            self.qp.set_target(None, None)
            return states, plans, None
        x_s, u_s = release.target
        if u_s.shape != (self.system.m,):
            raise ValueError(f"a release's target has {u_s.size} inputs, the system {self.system.m}")
        offsets = {j: (x_s[part], u_s[self.system.us(j)]) for j, part in self._state_slices.items()}
        own = offsets[self.index]
        self.qp.set_target(*own)
        around = {j: x_j - offsets[j][0] for j, x_j in states.items()}
        moved = {j: relative_to(plan, *offsets[j]) for j, plan in plans.items() if j in offsets}
        return around, moved, own

    def _decide(self, release: Release, x: np.ndarray, coupling: np.ndarray, own: Offset, centre: np.ndarray,
                size: float) -> Decision:
        """The event trigger's decision at round 0 (:class:`dmpc.agents.trigger.KeepRule`)."""
        assert self._rule is not None
        previous = self._plan
        if previous is not None and release.reference(self.index) != (previous.k, previous.round):
            previous = None  # the coordinator holds another plan of this agent's (a fallback, a refusal)
        if previous is not None and not _same_target(self._plan_target, release.target):
            return Decision(TARGET)
        around = relative_to(previous, *own) if own is not None else previous
        return self._rule.decide(release.k, x, coupling, centre, size, around, self._kept)

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
        states, plans, own = self._view(release, plans)
        centre, size = release.centres[self._own], float(release.sizes[self.index])
        reason, coupling = "", None
        if self._rule is not None and release.round == 0:
            coupling = self.feedforward(release.k, states, plans)
            decision = self._decide(release, states[self.index], coupling, own, centre, size)
            if decision.keep:
                assert decision.plan is not None
                kept = decision.plan if own is None else Plan(release.k, 0, decision.plan.z + own[0],
                                                               decision.plan.v + own[1])
                self._remember(kept, release.target, kept=True)
                return Kept(run=run_id, k=release.k, round=release.round, sender=self.name,
                            sent_at=clock() if clock is not None else 0.0)
            reason = decision.reason
        if coupling is None:
            sol = self.solve(release.k, states, centre, size, plans)
        else:
            sol = self.solve(release.k, states, centre, size, plans, coupling=coupling)
        z, v = (sol.z, sol.v) if own is None else (sol.z + own[0], sol.v + own[1])
        self._remember(Plan(release.k, release.round, z, v) if sol.status.feasible else None, release.target)
        return PlanMessage(run=run_id, k=release.k, round=release.round, sender=self.name,
                           status=sol.status.value, z=z, v=v, cost=sol.cost, solve_time=sol.solve_time,
                           qp_iterations=int(sol.iterations), sent_at=clock() if clock is not None else 0.0,
                           reason=reason)

    def neighbour_kept(self, j: int, plan: Plan, release: Release) -> Plan:
        """Neighbour j's plan of ``release``'s step kept (its ``plan`` of the step before, with the
        release's state, centre and target), as the neighbour and the coordinator built it."""
        part = self.system.xs(j)
        offset = None if release.target is None else (release.target[0][part], release.target[1][self.system.us(j)])
        return kept_around(plan, release.k, release.x[part], release.centres[part], self._gamma[j], self._K[j], offset)

    def _remember(self, plan: Plan | None, target: tuple[np.ndarray, np.ndarray] | None, kept: bool = False) -> None:
        """This agent's plan of the step (its plant coordinates) and the target it was made for."""
        self._plan, self._plan_target = plan, target
        self._kept = self._kept + 1 if kept else 0


Offset = tuple[np.ndarray, np.ndarray] | None
"""A subsystem's part (x_s_i, u_s_i) of a setpoint target, or None at the origin."""


def _same_target(a: tuple[np.ndarray, np.ndarray] | None, b: tuple[np.ndarray, np.ndarray] | None) -> bool:
    if a is None or b is None:
        return a is b
    return np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
