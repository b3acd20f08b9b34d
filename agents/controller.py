"""The computing part of agent i: assumed trajectories -> coupling feed-forward -> QP_i, and
the plan that answers a release (:meth:`AgentController.answer`, the one path from a release
to a plan message for the agent node and the direct loop).

Pure: no bus; no clock other than the solver's own timing and the caller's, if it gives one.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from dmpc.agents.local_qp import LocalQP, QPSolution
from dmpc.bus.messages import PlanMessage, Release
from dmpc.core.system import CoupledSystem
from dmpc.core.trajectories import Plan, assumed_trajectory, coupling_feedforward, relative_to
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
    """

    def __init__(self, system: CoupledSystem, design: ControllerDesign, index: int, coupling: str = "feedforward",
                 solver_settings: dict | None = None, method: Method = DEFAULT_METHOD) -> None:
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

    def feedforward(self, k: int, states: dict[int, np.ndarray], plans: dict[int, Plan | None]) -> np.ndarray:
        """c_i(t) for t = 0..N-1 from the neighbours' assumed trajectories, shape (N, n_i)."""
        if not self.use_feedforward or not self.neighbours:
            return np.zeros((self.N, self.n))
        assumed = [assumed_trajectory(plans.get(j), k, states[j], self.N, self._gamma[j], self._K[j])
                   for j in self.neighbours]
        return coupling_feedforward(self._A, self._B, assumed, self.N, self.n)

    def solve(self, k: int, states: dict[int, np.ndarray], centre: np.ndarray, size: float,
              plans: dict[int, Plan | None]) -> QPSolution:
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
        """
        c = self.feedforward(k, states, plans)
        return self.qp.solve(states[self.index], c, centre, size)

    def _solve_around(self, release: Release, target: tuple[np.ndarray, np.ndarray], states: dict[int, np.ndarray],
                      plans: dict[int, Plan | None]) -> QPSolution:
        """QP_i in deviation coordinates around the released setpoint target (x_s (n,), u_s (m,)),
        its plan given back around the origin (docs/algorithm.md, "Setpoints")."""
        x_s, u_s = target
        if u_s.shape != (self.system.m,):
            raise ValueError(f"a release's target has {u_s.size} inputs, the system {self.system.m}")
        system = self.system
        offsets = {j: (x_s[part], u_s[system.us(j)]) for j, part in self._state_slices.items()}
        own_x, own_u = offsets[self.index]
        self.qp.set_target(own_x, own_u)
        around = {j: x_j - offsets[j][0] for j, x_j in states.items()}
        moved = {j: relative_to(plan, *offsets[j]) for j, plan in plans.items() if j in offsets}
        sol = self.solve(release.k, around, release.centres[self._own], float(release.sizes[self.index]), moved)
        return replace(sol, z=sol.z + own_x, v=sol.v + own_u)

    def answer(self, release: Release, plans: dict[int, Plan | None], run_id: str,
               clock: Callable[[], float] | None = None) -> PlanMessage:
        """Solve QP_i for ``release`` and return the plan message that answers it.

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
        x = release.x
        states = {j: x[part] for j, part in self._state_slices.items()}
        target = release.target
        if target is None:
            self.qp.set_target(None, None)
            sol = self.solve(release.k, states, release.centres[self._own], float(release.sizes[self.index]), plans)
        else:
            sol = self._solve_around(release, target, states, plans)
        return PlanMessage(run=run_id, k=release.k, round=release.round, sender=self.name,
                           status=sol.status.value, z=sol.z, v=sol.v, cost=sol.cost, solve_time=sol.solve_time,
                           qp_iterations=int(sol.iterations), sent_at=clock() if clock is not None else 0.0)
