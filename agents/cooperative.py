"""The computing part of a cooperative agent (``tv-box-coop``): a release's iterate -> agent i's
proposal (docs/algorithm.md, "Cooperative DMPC").

Everything the proposal depends on is in the release: the iterate (every subsystem's planned
states and inputs), the target, the terminal box. So the agent reads no neighbour's plan, and the
same release gives the same proposal in any process.

Pure: no bus; no clock other than the solver's own timing and the caller's, if it gives one.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np

from dmpc.bus.messages import PlanMessage, Release
from dmpc.cooperative.agent_qp import CooperativeQP
from dmpc.cooperative.reach import input_reach
from dmpc.core.qp_status import QPStatus
from dmpc.core.system import CoupledSystem
from dmpc.core.trajectories import Plan
from dmpc.offline import ControllerDesign


class CooperativeController:
    """Agent ``index``'s cooperative QP, set up once.

    Parameters
    ----------
    system : CoupledSystem
    design : ControllerDesign
    index : int
        0-based subsystem index.
    solver_settings : dict, optional
        OSQP settings overriding the defaults.
    """

    def __init__(self, system: CoupledSystem, design: ControllerDesign, index: int,
                 solver_settings: dict | None = None) -> None:
        self.index = index
        self.system = system
        self.name = system.subsystems[index].name
        self.N = design.horizon
        self.reach = input_reach(system, design.horizon)[index]
        self._own_states = system.xs(index)
        self._inputs = system.us(index)
        self.neighbours: tuple[int, ...] = ()  # the release carries the iterate: no neighbour plan is awaited
        self.qp: CooperativeQP | None = None
        self._own_columns: slice | None = None
        if self.reach:
            self.qp = CooperativeQP(system, design.gains.P, design.horizon, index, self.reach, solver_settings)
            if index in self.reach:
                start = sum(system.subsystems[j].n for j in self.reach if j < index)
                self._own_columns = slice(start, start + system.subsystems[index].n)

    def answer(self, release: Release, plans: Mapping[int, Plan | None], run_id: str,
               clock: Callable[[], float] | None = None) -> PlanMessage:
        """Agent i's proposal for ``release``'s round: its own inputs over the horizon that minimise
        the cost of every subsystem they reach, the other agents' inputs at the iterate.

        Parameters
        ----------
        release : Release
            Must carry the iterate (:attr:`Release.iterate`), the target, and the terminal box
            (``centres``, shape (n,), and ``sizes``).
        plans : mapping j -> Plan or None
            Unused: the release holds everything (the agent has no neighbours to wait for,
            :attr:`neighbours` is empty).
        run_id : str
        clock : callable () -> float, optional
            The sender's clock, read once the proposal is solved: the message's ``sent_at``.

        Returns
        -------
        PlanMessage
            ``v`` (N, m_i): the proposed inputs; ``z`` (N+1, n_i): this subsystem's states under
            them (plant coordinates); ``cost``: the cost of the subsystems reached. With a QP that
            failed, its status and NaN plans: the coordinator keeps this agent's inputs at the iterate.

        Raises
        ------
        ValueError
            A release without an iterate (one made for another method).
        """
        if release.iterate is None:
            raise ValueError(f"a release of step {release.k} without the cooperative iterate: the coordinator "
                             "runs another method than this agent (tv-box-coop)")
        z_all, v_all = release.iterate
        x_s, u_s = release.target if release.target is not None else (np.zeros(self.system.n), np.zeros(self.system.m))
        own_v = v_all[:, self._inputs]
        if self.qp is None:  # inputs that reach no state: nothing to choose
            return self._message(release, run_id, clock, QPStatus.SOLVED.value, z_all[:, self._own_states], own_v,
                                 0.0, 0.0, 0)
        states, inputs = self.qp.states, self._inputs
        sol = self.qp.solve(z_all[:, states] - x_s[states], own_v - u_s[inputs], x_s[states], u_s[inputs],
                            release.centres[states], float(release.sizes[self.index]))
        if not sol.status.feasible:
            return self._message(release, run_id, clock, sol.status.value, sol.z[:, :self.system.subsystems[self.index].n],
                                 sol.v, sol.cost, sol.solve_time, sol.iterations)
        v = sol.v + u_s[inputs]
        if self._own_columns is not None:
            z = sol.z[:, self._own_columns] + x_s[self._own_states]
        else:
            z = z_all[:, self._own_states]
        return self._message(release, run_id, clock, sol.status.value, z, v, sol.cost, sol.solve_time,
                             int(sol.iterations))

    def neighbour_kept(self, j: int, plan: Plan, release: Release) -> Plan:
        """Never called: the cooperative method refuses the event trigger, so no neighbour keeps
        (``j``, ``plan`` and ``release`` as :meth:`AgentController.neighbour_kept
        <dmpc.agents.controller.AgentController.neighbour_kept>` takes them)."""
        raise ValueError(f"agent {self.name} runs tv-box-coop, which keeps no plans: a release names "
                         f"subsystem {j}'s plan of step {plan.k} as kept at step {release.k}")

    def _message(self, release: Release, run_id: str, clock: Callable[[], float] | None, status: str,
                 z: np.ndarray, v: np.ndarray, cost: float, solve_time: float, iterations: int) -> PlanMessage:
        return PlanMessage(run=run_id, k=release.k, round=release.round, sender=self.name, status=status, z=z, v=v,
                           cost=cost, solve_time=solve_time, qp_iterations=iterations,
                           sent_at=clock() if clock is not None else 0.0)
