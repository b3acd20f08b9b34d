"""Agent i's cooperative QP: the whole system's cost over its own inputs, the others' fixed.

With R the subsystems agent i's inputs reach (:func:`dmpc.cooperative.reach.input_reach`) and the
round's iterate (z^p, v^p), the states of R move with v_i as

    z_R(t+1) = A_RR z_R(t) + B_Ri v_i(t) + c(t),   c(t) = z_R^p(t+1) - A_RR z_R^p(t) - B_Ri v_i^p(t),

where c(t) holds everything the other agents' inputs and the subsystems outside R contribute at
the iterate. The other subsystems' states do not depend on v_i, so their cost and constraints are
constants of this problem, and

    min  sum_{j in R} [ sum_{t<N} z_j(t)'Q_j z_j(t) + z_j(N)'P_j z_j(N) ] + sum_{t<N} v_i(t)'R_i v_i(t)
    s.t. the dynamics above, z_R(0) = x_R(k),  v_i(t) in U_i,  z_j(t) in X_j (t = 1..N, j in R),
         |z_j(N) - alpha_j| <= beta (j in R)

is the centralised problem restricted to v_i: every feasible point of it, with the other agents'
inputs at the iterate, is a feasible point of the centralised problem (the rest of the iterate's
rows do not move). All in deviation coordinates around the step's target.
"""
from __future__ import annotations

import numpy as np

from dmpc.core.mpc_qp import POLISH_RETRY_REFINE_ITER, MpcQP, QPSolution, StageRows
from dmpc.core.system import CoupledSystem, block_diag, stack_sets

COOPERATIVE_SETTINGS = dict(eps_prim_inf=1e-9, eps_dual_inf=1e-9, polish_refine_iter=POLISH_RETRY_REFINE_ITER)
"""OSQP's infeasibility tolerances, tighter than its defaults (1e-4): an agent's feasible set can
be thin (the iterate on the boundary of a row shared with another subsystem), and a certificate
accepted at 1e-4 then calls a feasible problem infeasible. And the polished solution refined to
convergence: with the default 3 steps a polish that OSQP reports as successful can leave
dynamics residuals of ~5e-8, so the states the proposed inputs really give (the coordinator
simulates them) missed a row by up to 4e-7 on about 1 % of random coupled systems
(tests/test_cooperative_core.py); with 25 steps by 1e-14. A solve that OSQP ends at its
iteration cap (one small, well-conditioned agent QP in a thousand needed 17,760 iterations; on a
random input-coupled system with a setpoint an agent's QP hit the cap at a dozen steps) or solves
only inaccurately is solved again by Clarabel, an interior-point method, on the same matrices
(:class:`dmpc.core.mpc_qp.MpcQP`, ``interior_point``): a proposal that fails is no proposal, and
the agent's inputs stay at the iterate."""


class CooperativeQP:
    """Agent ``index``'s QP over the subsystems ``reach`` (set up once).

    Parameters
    ----------
    system : CoupledSystem
    P : list of ndarray
        P_j, shape (n_j, n_j), for every subsystem.
    horizon : int
    index : int
    reach : tuple of int
        The subsystems agent ``index``'s inputs reach, sorted.
    settings : dict, optional
        OSQP settings overriding the project's defaults and COOPERATIVE_SETTINGS.
    """

    def __init__(self, system: CoupledSystem, P: list[np.ndarray], horizon: int, index: int,
                 reach: tuple[int, ...], settings: dict | None = None) -> None:
        self.index = index
        self.reach = reach
        self.N = horizon
        self.states = np.concatenate([np.arange(system.n)[system.xs(j)] for j in reach])
        self.inputs = system.us(index)
        subs = [system.subsystems[j] for j in reach]
        self.n = self.states.size
        A = system.A[np.ix_(self.states, self.states)]
        B = system.B[self.states, self.inputs]
        Q = block_diag(*[s.Q for s in subs])
        P_R = block_diag(*[P[j] for j in reach])
        own = system.subsystems[index]
        U = own.input_set
        inputs = StageRows(U.H, np.tile(U.lower, (horizon, 1)), np.tile(U.upper, (horizon, 1)))
        X = stack_sets([s.state_set for s in subs], [s.n for s in subs])
        states = None if X is None else StageRows(X.H, np.tile(X.lower, (horizon, 1)), np.tile(X.upper, (horizon, 1)))
        opts = dict(COOPERATIVE_SETTINGS)
        opts.update(settings or {})
        self._A, self._B = A, B
        self._qp = MpcQP(A, B, Q, own.R, P_R, horizon, inputs, states, np.eye(self.n), opts, interior_point=True)

    def coupling(self, z: np.ndarray, v: np.ndarray) -> np.ndarray:
        """c(t) for t = 0..N-1, shape (N, n_R), from the iterate's states of R, z (N+1, n_R), and
        this agent's inputs, v (N, m_i)."""
        return z[1:] - z[:-1] @ self._A.T - v @ self._B.T

    def solve(self, z: np.ndarray, v: np.ndarray, x_s: np.ndarray, u_s: np.ndarray, alpha: np.ndarray,
              beta: float) -> QPSolution:
        """Agent i's proposal for the round.

        Parameters
        ----------
        z : ndarray, shape (N + 1, n_R)
            The iterate's states of R (deviation coordinates); z[0] is the measured x_R(k).
        v : ndarray, shape (N, m_i)
            The iterate's inputs of this agent (deviation coordinates).
        x_s, u_s : ndarray, shapes (n_R,), (m_i,)
            R's and this agent's parts of the target (the rows move to X - x_s, U - u_s).
        alpha : ndarray, shape (n_R,)
            The terminal box centres of R (deviation coordinates).
        beta : float
            The terminal box radius.

        Returns
        -------
        QPSolution
            z (N+1, n_R), v (N, m_i); its cost is R's part of the global cost with this agent's inputs.
        """
        self._qp.set_offset(x_s, u_s)
        # from the iterate, a feasible point and often near the optimum (after the first rounds)
        return self._qp.solve(z[0], self.coupling(z, v), alpha - beta, alpha + beta, start=(z, v))
