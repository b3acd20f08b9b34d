"""The local QP_i of one agent (docs/algorithm.md, "Online step k, agent i", item 3), on the shared sparse MPC QP.

    min  sum_{t<N} z(t)'Q_i z(t) + v(t)'R_i v(t) + z(N)'P_i z(N)
    s.t. z(0) = x_i(k),  z(t+1) = A_ii z(t) + B_ii v(t) + c_i(t)
         U_i tightened by m_u(t),  X_i tightened by m_x(t)  (t = 1..N)
         |z(N) - alpha_i| <= beta - m_f  elementwise   (or the method's terminal rows, see below)

The terminal constraint is an :class:`~dmpc.methods.terminal_rows.AgentTerminal`: the box above by
default, a polytope inside an ellipsoid for the ellipsoid methods. The measured state, the coupling feed-forward and the terminal box are all bounds of the QP,
so per step only OSQP's ``l``/``u`` change and it warm-starts from its last solution.
"""
from __future__ import annotations

import numpy as np

from dmpc.core.mpc_qp import DEFAULT_SETTINGS, MpcQP, QPSolution, StageRows
from dmpc.core.qp_status import QPStatus
from dmpc.core.system import Subsystem
from dmpc.methods.terminal_rows import AgentTerminal, BoxTerminal
from dmpc.offline.tubes import Tightening

__all__ = ["DEFAULT_SETTINGS", "LocalQP", "QPSolution", "QPStatus"]


class LocalQP:
    """QP_i for one subsystem, set up once.

    Parameters
    ----------
    sub : Subsystem
    P_terminal : ndarray, shape (n, n)
    horizon : int
        N.
    tightening : Tightening
    settings : dict, optional
        OSQP settings overriding DEFAULT_SETTINGS.
    terminal : AgentTerminal, optional
        The terminal rows; the box |z(N) - alpha| <= beta - m_f by default.
    """

    def __init__(self, sub: Subsystem, P_terminal: np.ndarray, horizon: int, tightening: Tightening,
                 settings: dict | None = None, terminal: AgentTerminal | None = None) -> None:
        self.n, self.m, self.N = sub.n, sub.m, horizon
        U = sub.input_set
        inputs = StageRows(U.H, U.lower + tightening.input_margin, U.upper - tightening.input_margin)
        states = None
        if sub.state_set is not None:
            X = sub.state_set
            states = StageRows(X.H, X.lower + tightening.state_margin[1:], X.upper - tightening.state_margin[1:])
        self.terminal = terminal if terminal is not None else BoxTerminal(sub.n, tightening.terminal_margin)
        self._qp = MpcQP(sub.A, sub.B, sub.Q, sub.R, P_terminal, horizon, inputs, states, self.terminal.T, settings)

    def solve(self, x: np.ndarray, coupling: np.ndarray, centre: np.ndarray, size: float) -> QPSolution:
        """Solve QP_i for one step.

        Parameters
        ----------
        x : ndarray, shape (n,)
            Measured state x_i(k).
        coupling : ndarray, shape (N, n)
            Feed-forward c_i(t), t = 0..N-1 (zeros for the decoupled nominal model).
        centre : ndarray, shape (n,)
            The released terminal centre (of the box; unused by an ellipsoid, centred at zero).
        size : float
            The released terminal size: the box radius beta, or the ellipsoid level r_i.
        """
        lower, upper = self.terminal.bounds(centre, size)
        return self._qp.solve(x, coupling, lower, upper)

    def violations(self, x: np.ndarray, coupling: np.ndarray, centre: np.ndarray, size: float, z: np.ndarray,
                   v: np.ndarray) -> tuple[float, float]:
        """How far the plan z (N+1, n), v (N, m) is from feasible for the QP :meth:`solve` would
        solve with the same x, coupling, centre and size: (dynamics residual, excess over the other
        rows), relative."""
        lower, upper = self.terminal.bounds(centre, size)
        return self._qp.violations(x, coupling, lower, upper, z, v)

    def set_target(self, x_s: np.ndarray, u_s: np.ndarray) -> None:
        """Solve in deviation coordinates around the steady state x_s (n,), u_s (m,) of this
        subsystem from now on: U_i - u_s and X_i - x_s (zeros: the origin)."""
        self._qp.set_offset(x_s, u_s)

    def cost(self, z: np.ndarray, v: np.ndarray) -> float:
        """Own cost J_i of a plan: z shape (N+1, n), v shape (N, m)."""
        return self._qp.cost(z, v)
