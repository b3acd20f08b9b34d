"""The event trigger of one agent: keep the shifted plan, or solve QP_i (docs/algorithm.md,
"Event-triggered DMPC").

At step k the agent's plan of step k-1, shifted by one step and corrected for the prediction error
e = x_i(k) - z_i(k|k-1) with the terminal controller (z(t) = z(t+1|k-1) + Gamma_i^t e,
v(t) = v(t+1|k-1) + K_i Gamma_i^t e, v(N-1) = K_i z(N-1), z(N) = alpha_i(k) + Gamma_i^N e), is
kept when

1. there is such a plan (a plan of step k-1 the coordinator holds too, the same target), and
   keeps so far are fewer than the limit;
2. ||e||_inf <= the threshold (the prediction held);
3. it meets this step's QP: its dynamics with the neighbours' feed-forward of step k (they change
   when a neighbour's plan changed), its input and state rows and the terminal box, each to
   ``FEASIBILITY_TOLERANCE`` — so a kept plan is always a feasible point of the QP the solve
   would have had;
4. its cost exceeds the QP's unconstrained optimum (a lower bound of what the solve would find)
   by at most the cost threshold: keeping gives up at most that much.

Otherwise the agent solves, and says which test failed first. Pure: no bus, no clock.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dmpc.agents.local_qp import LocalQP
from dmpc.core.mpc_qp import plan_cost
from dmpc.core.trajectories import Plan, kept_plan
from dmpc.core.unconstrained import UnconstrainedBound

FEASIBILITY_TOLERANCE = 1e-7
"""How far a kept plan may leave a row of the QP (times max(1, |bound|)): the accuracy the solver
itself meets its rows to (OSQP's eps_abs)."""

NO_PLAN = "no plan"
LIMIT = "limit"
PREDICTION = "prediction"
CHANGED = "changed"
CONSTRAINTS = "constraints"
COST = "cost"
TARGET = "target"
REASONS = (NO_PLAN, LIMIT, PREDICTION, CHANGED, CONSTRAINTS, COST, TARGET)
"""Why an agent solved, first test failed first: no plan of the last step to keep (k = 0, a
fallback, a refused plan), the limit of consecutive keeps, the prediction error above the
threshold, the neighbours' feed-forward changed (a neighbour's plan changed), a constraint or the
terminal box broken by the kept plan, keeping would cost more than the cost threshold, or the
setpoint target moved."""


@dataclass(frozen=True)
class Decision:
    """Keep (``reason`` "") or solve (``reason`` one of REASONS).

    Attributes
    ----------
    reason : str
    plan : Plan or None
        The kept plan (deviation coordinates of the step's target), z (N+1, n_i), v (N, m_i).
    cost : float
        Its cost J_i (NaN when solving).
    """

    reason: str
    plan: Plan | None = None
    cost: float = float("nan")

    @property
    def keep(self) -> bool:
        return not self.reason


@dataclass(frozen=True)
class KeepRule:
    """The trigger of one agent.

    Parameters
    ----------
    qp : LocalQP
        The agent's QP: its rows and bounds decide whether a kept plan is feasible.
    bound : UnconstrainedBound
    Q, R, P : ndarray
        The agent's weights.
    Gamma : ndarray, shape (n_i, n_i)
        A_ii + B_ii K_i.
    K : ndarray, shape (m_i, n_i)
    threshold : float
        Largest prediction error ||e||_inf kept, in the state's units.
    cost : float
        Largest cost given up by keeping.
    max_keep : int or None
        Most consecutive keeps; None: no limit.
    """

    qp: LocalQP
    bound: UnconstrainedBound
    Q: np.ndarray
    R: np.ndarray
    P: np.ndarray
    Gamma: np.ndarray
    K: np.ndarray
    threshold: float
    cost: float
    max_keep: int | None = None

    def decide(self, k: int, x: np.ndarray, coupling: np.ndarray, centre: np.ndarray, size: float,
               previous: Plan | None, kept_so_far: int) -> Decision:
        """Keep or solve at step k (round 0), everything in the step's deviation coordinates.

        Parameters
        ----------
        x : ndarray, shape (n_i,)
            The measured state.
        coupling : ndarray, shape (N, n_i)
            This step's feed-forward c_i(t).
        centre, size
            The released terminal box.
        previous : Plan or None
            The agent's plan of step k - 1 (None: none to keep).
        kept_so_far : int
            Consecutive keeps before this step.
        """
        if previous is None or previous.k != k - 1:
            return Decision(NO_PLAN)
        if self.max_keep is not None and kept_so_far >= self.max_keep:
            return Decision(LIMIT)
        e = x - previous.z[1]
        if np.max(np.abs(e)) > self.threshold:
            return Decision(PREDICTION)
        plan = kept_plan(previous, k, x, centre, self.Gamma, self.K)
        dynamics, rows = self.qp.violations(x, coupling, centre, size, plan.z, plan.v)
        if dynamics > FEASIBILITY_TOLERANCE:
            return Decision(CHANGED)
        if rows > FEASIBILITY_TOLERANCE:
            return Decision(CONSTRAINTS)
        cost = plan_cost(plan.z, plan.v, self.Q, self.R, self.P)
        if cost - self.bound.cost(x, coupling) > self.cost:
            return Decision(COST)
        return Decision("", plan, cost)
