"""The coordinator's side of cooperative DMPC: the iterate of each round, in the plant's coordinates.

Per step k the coordinator holds one iterate of the whole system (every agent's planned inputs and
the states they give from x(k)). Round p releases it; each agent proposes its own inputs
(:class:`~dmpc.cooperative.agent_qp.CooperativeQP`); :func:`~dmpc.cooperative.iterate.combine`
makes the next iterate. After the last round the iterate's first inputs are applied and its last
states are the terminal states eta of the time-varying boxes. The next step starts from the
iterate shifted, with the terminal controller at its tail (:meth:`CooperativeRounds.next_step`).

At k = 0 there is no iterate to shift: the terminal controller's rollout from x(0) is used when it
meets every constraint and the terminal box; otherwise the centralised QP's plan with the same
terminal box (a feasible first iterate is what the method's guarantees start from).

Every iterate here is in the plant's coordinates; a step's target (x_s, u_s) only moves the
deviation coordinates the cost and the rows are taken in.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dmpc.cooperative.iterate import DEFAULT_STEP_RULE, Combination, GlobalModel, Iterate, StepRule, combine
from dmpc.core.central_qp import CentralQP
from dmpc.core.system import CoupledSystem
from dmpc.tracking.targets import Target

FEASIBLE = 1e-9
"""A first iterate whose rows are met to this (relative) is taken as it is."""

FIRST_SETTINGS = dict(max_iter=100_000)
"""OSQP's iteration cap for the centralised QP of the first iterate (once per run): at the
default 10 000 it stopped unsolved on a random input-coupled system whose start is centrally
feasible with a slack of 0.03 (tests/test_cooperative_core.py), and the rounds then started
outside the feasible set. A larger cap changes nothing where the default sufficed."""


@dataclass(frozen=True)
class FirstIterate:
    """The iterate step 0 starts from and what the records say of it.

    Attributes
    ----------
    iterate : Iterate
        Plant coordinates.
    note : str
        "" for the terminal controller's rollout; otherwise how it was found.
    """

    iterate: Iterate
    note: str


@dataclass(frozen=True)
class AgentPart:
    """One agent's part of an iterate: its states z (N+1, n_i), inputs v (N, m_i), its first
    input u (m_i,), its terminal state eta (n_i,), and its subsystem's part of the cost."""

    z: np.ndarray
    v: np.ndarray
    u: np.ndarray
    eta: np.ndarray
    cost: float


class CooperativeRounds:
    """The iterates of one run.

    Parameters
    ----------
    system : CoupledSystem
    K, P : list of ndarray
        The design's K_i (m_i, n_i) and P_i (n_i, n_i).
    P_global : ndarray, shape (n, n)
        diag(P_i), for the centralised QP of the first iterate.
    horizon : int
    rule : {"line", "equal"}
        How the proposals combine (:func:`~dmpc.cooperative.iterate.combine`).
    """

    def __init__(self, system: CoupledSystem, K: list[np.ndarray], P: list[np.ndarray], P_global: np.ndarray,
                 horizon: int, rule: StepRule = DEFAULT_STEP_RULE) -> None:
        self.system = system
        self.model = GlobalModel(system, K, P, horizon)
        self.rule: StepRule = rule
        self._P_global = P_global
        self.N = horizon

    def first(self, x: np.ndarray, target: Target, alpha: np.ndarray, beta: float,
              terminal_rows: tuple[np.ndarray, np.ndarray, np.ndarray]) -> FirstIterate:
        """The iterate of step 0 from the measured x(0) (n,).

        Parameters
        ----------
        x : ndarray, shape (n,)
        target : Target
            The target of step 0.
        alpha : ndarray, shape (n,)
            The terminal box centre (deviation coordinates).
        beta : float
        terminal_rows : (T, lower, upper)
            The method's terminal constraint on z(N) for the centralised QP (deviation coordinates).
        """
        rollout = self.model.rollout(x - target.x)
        excess = self.model.excess(rollout, target.x, target.u, alpha, beta)
        if excess <= FEASIBLE:
            return FirstIterate(rollout.moved(target.x, target.u), "")
        T, lower, upper = terminal_rows
        qp = CentralQP(self.system, self._P_global, self.N, terminal="rows", rows=T, settings=FIRST_SETTINGS)
        qp.set_target(target.x, target.u)
        # to 1e-10: the agents' QPs hold every row of the iterate, and a first iterate that leaves one
        # by OSQP's 1e-7 can make an agent's problem infeasible at the tolerances its solvers keep
        sol = qp.solve_rows_accurately(x - target.x, lower, upper)
        if not sol.status.feasible:
            sol = qp.solve_rows(x - target.x, lower, upper)
        if not sol.status.feasible:
            return FirstIterate(rollout.moved(target.x, target.u),
                                f"k=0: the terminal controller's rollout leaves the constraints (by {excess:.3g}) and "
                                f"the centralised QP found no plan ({sol.status.value}): the rounds start outside "
                                "the feasible set")
        seeded = Iterate(self.model.simulate(x - target.x, sol.v), sol.v)
        return FirstIterate(seeded.moved(target.x, target.u),
                            f"k=0: the terminal controller's rollout leaves the constraints (by {excess:.3g}); "
                            "started from the centralised QP's plan")

    def combine(self, iterate: Iterate, proposals: dict[int, np.ndarray], target: Target, alpha: np.ndarray,
                beta: float) -> Combination:
        """The round's next iterate (plant coordinates) from the agents' proposed inputs
        (i -> (N, m_i), plant coordinates); see :func:`dmpc.cooperative.iterate.combine`.

        Parameters
        ----------
        iterate : Iterate
            The round's iterate, plant coordinates.
        proposals : dict i -> ndarray (N, m_i)
            Agent i's proposed inputs, plant coordinates; an agent without one keeps its inputs.
        target : Target
            The step's target (x_s, u_s): the cost and the rows are taken around it.
        alpha : ndarray, shape (n,)
            The terminal box centre (deviation coordinates).
        beta : float
            The terminal box radius.
        """
        x_s, u_s = target.x, target.u
        around = Iterate(iterate.z - x_s, iterate.v - u_s)
        moved = {i: v - u_s[self.system.us(i)] for i, v in proposals.items()}
        done = combine(self.model, around, moved, x_s, u_s, alpha, beta, self.rule)
        return Combination(done.iterate.moved(x_s, u_s), done.step, done.cost_before, done.cost_after, done.change)

    def next_step(self, iterate: Iterate, x: np.ndarray, target: Target) -> Iterate:
        """The iterate of step k+1: the step k iterate shifted, the terminal controller around
        the next step's target at its tail, from the measured x(k+1) (n,)."""
        around = Iterate(iterate.z - target.x, iterate.v - target.u)
        return self.model.shifted(around, x - target.x).moved(target.x, target.u)

    def parts(self, iterate: Iterate, target: Target) -> list[AgentPart]:
        """Every agent's part of the iterate (plant coordinates; costs around ``target``)."""
        costs = self.model.stage_costs(Iterate(iterate.z - target.x, iterate.v - target.u))
        system = self.system
        parts = []
        for i in range(system.M):
            z, v = iterate.z[:, system.xs(i)], iterate.v[:, system.us(i)]
            parts.append(AgentPart(z=z, v=v, u=v[0], eta=z[-1], cost=float(costs[i])))
        return parts
