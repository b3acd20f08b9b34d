"""What the coordinator computes of an agent's plans with the agent's terminal controller.

The shifted candidate of a plan (docs/algorithm.md, "Online step k, agent i", items 2 and 7), the
fallback input, a kept plan rebuilt from a kept notice (:func:`dmpc.core.trajectories.kept_around`,
the same floats as the agent's), and a plan's own cost J_i. Every plan here is in deviation
coordinates around the step's operating point unless said otherwise.
"""
from __future__ import annotations

import numpy as np

from dmpc.core.mpc_qp import plan_cost
from dmpc.core.system import CoupledSystem
from dmpc.core.trajectories import OperatingPoint, Plan, candidate_plan, kept_around, shifted_input
from dmpc.offline import ControllerDesign


class Candidates:
    """Each agent's terminal controller K_i, Gamma_i = A_ii + B_ii K_i and terminal weight P_i.

    Parameters
    ----------
    system : CoupledSystem
    design : ControllerDesign
        Gives K_i (m_i, n_i), P_i (n_i, n_i) and the horizon N.
    """

    def __init__(self, system: CoupledSystem, design: ControllerDesign) -> None:
        self.system = system
        self.N = design.horizon
        self.K = design.gains.K
        self.P = design.gains.P
        self.gamma = [s.A + s.B @ self.K[i] for i, s in enumerate(system.subsystems)]

    def candidate(self, i: int, plan: Plan | None, k: int, x_i: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """Agent i's candidate at step k: ``plan`` shifted to k and continued with K_i, or without
        a plan the K_i-rollout from x_i (n_i,); z (N+1, n_i), v (N, m_i)."""
        return candidate_plan(plan, k, x_i, self.N, self.gamma[i], self.K[i])

    def fallback_input(self, i: int, plan: Plan | None, k: int, x_i: np.ndarray) -> np.ndarray:
        """Agent i's fallback input at step k from ``plan`` and the measured x_i (n_i,), shape (m_i,)."""
        return shifted_input(plan, k, x_i, self.gamma[i], self.K[i])

    def cost(self, i: int, plan: Plan) -> float:
        """J_i of agent i's ``plan``."""
        sub = self.system.subsystems[i]
        return plan_cost(plan.z, plan.v, sub.Q, sub.R, self.P[i])

    def candidate_cost(self, i: int, plan: Plan, k: int) -> float:
        """J_i of the candidate of agent i's ``plan`` at step k."""
        sub = self.system.subsystems[i]
        z, v = self.candidate(i, plan, k, None)
        return plan_cost(z, v, sub.Q, sub.R, self.P[i])

    def kept(self, i: int, plan: Plan, k: int, x_i: np.ndarray, end: np.ndarray, point: OperatingPoint) -> Plan:
        """Agent i's ``plan`` of step k - 1 (the plant's coordinates) kept at step k from the
        measured x_i (n_i,), ended at ``end`` (alpha_i(k), n_i), around agent i's part ``point`` of
        the step's operating point; in the plant's coordinates, as the agent holds it."""
        return kept_around(plan, k, x_i, end, self.gamma[i], self.K[i], point)
