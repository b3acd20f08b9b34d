"""The ``centralized`` method: one QP over the whole system per step, no agents, no bus.

Problem (9) of the paper with X^f itself as terminal set (Omega z(N) <= 1), on the shared MPC QP
(dmpc.core.central_qp.CentralQP). It is the optimality reference the distributed methods are
compared with. Each step becomes a StepRecord like a distributed step, so the run folder is the
same: the plan is split into the subsystems' parts, J_i are their own terms, and every agent's
status, solve time and iteration count is the central QP's. An infeasible step applies the
previous plan shifted by one step (with the global terminal controller K as its tail), projected
onto U, as the distributed fallback does.

With setpoints it tracks them with the distributed methods' targets and reference governor
(dmpc.tracking.tracker.Tracker; docs/algorithm.md, "Setpoints"): step k applies the target
(x_s, u_s) with scale lambda the governor chose at the end of step k - 1 (the origin at k = 0), and
solves the same QP in deviation coordinates around it, dz = z - x_s, dv = v - u_s, with X - x_s,
U - u_s and the terminal set of the target, Omega (z(N) - x_s) <= lambda. The governor's test is
the one of the distributed methods with the central plan's terminal state as eta: its condition
(b), Omega (A+BK)(eta - x_s') <= lambda', is exactly this terminal constraint for the shifted
plan at step k + 1, and (a) keeps its last input u_s' + K (eta - x_s') in U, so the shifted plan
stays feasible whenever the target moves. J_i are the plan's cost around the target applied, and
the records carry the tracking (request, target, target applied, governor) as the distributed
ones do.
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
from dmpc.core.trajectories import Plan, candidate_plan, relative_to
from dmpc.offline import ControllerDesign
from dmpc.plant.dynamics import Plant
from dmpc.tracking.schedule import SetpointEntry
from dmpc.tracking.targets import DEFAULT_MARGIN
from dmpc.tracking.tracker import Tracker


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
    setpoints : tuple of SetpointEntry
        The setpoint schedule each run tracks (empty: the origin throughout, and the records carry
        no tracking).
    setpoint_margin : float
        The fraction of every bound the targets keep free (dmpc.tracking.targets.TargetSpace).
    """

    def __init__(self, system: CoupledSystem, design: ControllerDesign, settings: dict | None = None,
                 setpoints: tuple[SetpointEntry, ...] = (), setpoint_margin: float = DEFAULT_MARGIN) -> None:
        self.system = system
        self.design = design
        self.N = design.horizon
        self.qp = CentralQP(system, design.gains.P_global(), design.horizon, terminal="omega",
                            omega=design.terminal.omega, settings=settings)
        self._K = design.gains.K_global()
        self._AK = system.A + system.B @ self._K
        self.setpoints = tuple(setpoints)
        self.setpoint_margin = setpoint_margin

    def tracker(self) -> Tracker | None:
        """A new tracker for one run of the schedule, or None without setpoints."""
        if not self.setpoints:
            return None
        return Tracker(self.system, self.design.terminal, self._AK, self._K, self.setpoints, self.setpoint_margin)

    def run(self, steps: int, on_step: Callable[[StepRecord], None], x0: np.ndarray | None = None,
            stop: Callable[[StepRecord], bool] | None = None, plant: Plant | None = None) -> CentralRun:
        """Run from x0 (the scenario's by default) for ``steps`` steps; ``on_step`` sees each
        step's record.

        ``stop(record)`` returning True ends the run after that step (used by the region of
        attraction to stop once converged). ``plant`` replaces the nominal plant started at x0.
        """
        plant = plant if plant is not None else Plant(self.system, x0)
        tracker = self.tracker()
        last: Plan | None = None
        for k in range(steps):
            record, last = self.step(k, plant, last, tracker)
            on_step(record)
            if stop is not None and stop(record):
                return CentralRun(k + 1)
        return CentralRun(steps)

    def step(self, k: int, plant: Plant, last: Plan | None,
             tracker: Tracker | None = None) -> tuple[StepRecord, Plan | None]:
        """Solve, apply to ``plant`` and record step k; returns the record and the plan to shift
        next time (``last``: the one of the step before, None at first).

        With a ``tracker``, the step works around the target it applies and decides the next one.
        """
        system, M = self.system, self.system.M
        started = time.perf_counter()
        x = plant.x.copy()
        if tracker is None:
            offset = None
            sol = self.qp.solve(x)
        else:  # around the target applied (the origin at k = 0: the same problem)
            target = tracker.applied
            offset = (target.x, target.u)
            sol = self.qp.solve_around(x, target.x, target.u, target.scale)
        plan: Plan | None
        if sol.status.feasible:
            z, v, reason = sol.z, sol.v, ""  # around the target applied (with one)
            plan = Plan(k, 0, z, v) if offset is None else Plan(k, 0, z + offset[0], v + offset[1])
            u = plan.v[0].copy()
        else:
            z, v, u = self._fallback(k, last, x, offset)
            reason = f"qp {sol.status.value}"
            plan = last
        P = self.design.gains.P
        J_agents = [plan_cost(z[:, system.xs(i)], v[:, system.us(i)], s.Q, s.R, P[i])
                    for i, s in enumerate(system.subsystems)]
        if offset is not None:  # the records hold the plans as applied, in the plant's coordinates
            z, v = z + offset[0], v + offset[1]
        tracking = None
        if tracker is not None:
            tracking = tracker.step(k) if tracker.active else tracker.idle
            if tracker.active:
                tracker.advance(k + 1, z[-1])
        S = system.spread(x)
        x_next = plant.step(u)
        zeros = np.zeros(system.n)
        record = StepRecord(
            k=k, x=x, u=u, alpha=zeros, beta=float("nan"), x_next=x_next.copy(), alpha_next=zeros,
            beta_next=float("nan"), J=float(np.sum(J_agents)), J_agents=J_agents, S=S, rounds=1,
            max_change=float("nan"), status=[sol.status.value] * M, fallback=[bool(reason)] * M,
            fallback_reason=[reason] * M, solve_time=[sol.solve_time] * M, qp_iterations=[int(sol.iterations)] * M,
            plans_z=[z[:, system.xs(i)] for i in range(M)], plans_v=[v[:, system.us(i)] for i in range(M)],
            latency=[float("nan")] * M, step_time=time.perf_counter() - started, tracking=tracking)
        return record, plan

    def _fallback(self, k: int, last: Plan | None, x: np.ndarray,
                  offset: tuple[np.ndarray, np.ndarray] | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The last plan shifted to step k with the global K tail (or the K-rollout from x), around
        the target's ``offset`` (x_s, u_s) if any, and its first input with the feedback on the
        prediction error, projected onto U: z (N+1, n) and v (N, m) around the target, u (m,)."""
        system = self.system
        if offset is not None:
            last, x = relative_to(last, *offset), x - offset[0]
        z, v = candidate_plan(last, k, x, self.N, self._AK, self._K)
        raw = v[0] + self._K @ (x - z[0])
        if offset is not None:
            raw = raw + offset[1]
        u = np.concatenate([project_onto(s.input_set, raw[system.us(i)]) for i, s in enumerate(system.subsystems)])
        return z, v, u
