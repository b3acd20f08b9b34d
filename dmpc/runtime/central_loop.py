"""The ``centralized`` method: one QP over the whole system per step, no agents, no bus.

Problem (9) of the paper with X^f itself as terminal set (Omega z(N) <= 1), on the shared MPC QP
(dmpc.core.central_qp.CentralQP). It is the optimality reference the distributed methods are
compared with. Each step becomes a StepRecord like a distributed step, so the run folder is the
same: the plan is split into the subsystems' parts, J_i are their own terms, and every agent's
status, solve time and iteration count is the central QP's. An infeasible step applies the
previous plan shifted by one step (with the global terminal controller K as its tail), projected
onto U, as the distributed fallback does.
"""
from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from dmpc.core.central_qp import CentralQP
from dmpc.core.mpc_qp import plan_cost
from dmpc.core.steps import StepRecord
from dmpc.core.system import CoupledSystem, project_onto
from dmpc.core.trajectories import Plan, candidate_plan
from dmpc.offline import ControllerDesign
from dmpc.plant.dynamics import Plant


@dataclass
class CentralRun:
    """The outcome of a centralised run: steps completed and a failure ("" if none)."""

    steps: int
    failure: str = ""


class CentralLoop:
    """The centralised closed loop, set up once (the QP is reused for every run and x(0)).

    Parameters
    ----------
    system : CoupledSystem
    design : ControllerDesign
    settings : dict, optional
        OSQP settings.
    """

    def __init__(self, system: CoupledSystem, design: ControllerDesign, settings: dict | None = None) -> None:
        self.system = system
        self.design = design
        self.N = design.horizon
        self.qp = CentralQP(system, design.gains.P_global(), design.horizon, terminal="omega",
                            omega=design.terminal.omega, settings=settings)
        self._K = design.gains.K_global()
        self._AK = system.A + system.B @ self._K

    def run(self, steps: int, on_step: Callable[[StepRecord], None], x0: np.ndarray | None = None,
            stop: Callable[[StepRecord], bool] | None = None, plant: Plant | None = None) -> CentralRun:
        """Run from x0 (the scenario's by default) for ``steps`` steps.

        ``stop(record)`` returning True ends the run after that step (used by the region of
        attraction to stop once converged). ``plant`` replaces the nominal plant started at x0.
        """
        plant = plant if plant is not None else Plant(self.system, x0)
        last: Plan | None = None
        for k in range(steps):
            record, last = self.step(k, plant, last)
            on_step(record)
            if stop is not None and stop(record):
                return CentralRun(k + 1)
        return CentralRun(steps)

    def step(self, k: int, plant: Plant, last: Plan | None) -> tuple[StepRecord, Plan | None]:
        """Solve, apply and record step k; returns the record and the plan to shift next time."""
        system, M = self.system, self.system.M
        started = time.perf_counter()
        x = plant.x.copy()
        sol = self.qp.solve(x)
        if sol.status.feasible:
            z, v, reason = sol.z, sol.v, ""
            u = v[0].copy()
            plan = Plan(k, 0, z, v)
        else:
            z, v = self._candidate(k, last, x)
            raw = v[0] + self._K @ (x - z[0])
            u = np.concatenate([project_onto(s.input_set, raw[system.us(i)]) for i, s in enumerate(system.subsystems)])
            reason = f"qp {sol.status.value}"
            plan = last
        P = self.design.gains.P
        J_agents = [plan_cost(z[:, system.xs(i)], v[:, system.us(i)], s.Q, s.R, P[i])
                    for i, s in enumerate(system.subsystems)]
        S = system.spread(x)
        x_next = plant.step(u)
        zeros = np.zeros(system.n)
        record = StepRecord(
            k=k, x=x, u=u, alpha=zeros, beta=float("nan"), x_next=x_next.copy(), alpha_next=zeros,
            beta_next=float("nan"), J=float(np.sum(J_agents)), J_agents=J_agents, S=S, rounds=1,
            max_change=float("nan"), status=[sol.status.value] * M, fallback=[bool(reason)] * M,
            fallback_reason=[reason] * M, solve_time=[sol.solve_time] * M, qp_iterations=[int(sol.iterations)] * M,
            plans_z=[z[:, system.xs(i)] for i in range(M)], plans_v=[v[:, system.us(i)] for i in range(M)],
            latency=[float("nan")] * M, step_time=time.perf_counter() - started)
        return record, plan

    def _candidate(self, k: int, last: Plan | None, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The last plan shifted to step k with the global K tail, or the K-rollout from x."""
        return candidate_plan(last, k, x, self.N, self._AK, self._K)
