"""One QP over the whole coupled system (problem (9) without tubes), on the shared MPC QP.

Used to seed k = 0 when the first Jacobi round is infeasible from decoupled rollouts
(docs/algorithm.md, "Online step k, agent i", item 4), and as the optimality reference. The
terminal constraint is either X^f itself, ``Omega z(N) <= 1``, or given rows (the agents'
terminal sets stacked: what the distributed QPs impose together). Around a setpoint target
(x_s, u_s) with scale lambda (dmpc.tracking.targets) the same QP is solved in deviation
coordinates, with the stage rows moved to X - x_s, U - u_s and the terminal set lambda X^f:
``Omega (z(N) - x_s) <= lambda`` (:meth:`CentralQP.solve_around`).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from dmpc.core.mpc_qp import MpcQP, QPSolution, StageRows
from dmpc.core.system import CoupledSystem, stack_sets


class CentralQP:
    """The centralised MPC QP, set up once.

    Parameters
    ----------
    system : CoupledSystem
    P_terminal : ndarray, shape (n, n)
    horizon : int
    terminal : {"omega", "rows"}
        ``omega``: Omega z(N) <= 1 (X^f); ``rows``: given rows lower <= T z(N) <= upper (the
        agents' terminal sets stacked, see ``solve_rows``).
    omega : ndarray, shape (rows, n), required for ``terminal="omega"``
    settings : dict, optional
    rows : ndarray, shape (r, n), required for ``terminal="rows"``
    """

    def __init__(self, system: CoupledSystem, P_terminal: np.ndarray, horizon: int, terminal: str,
                 omega: np.ndarray | None = None, settings: dict[str, Any] | None = None,
                 rows: np.ndarray | None = None) -> None:
        if terminal not in ("omega", "rows") or (terminal == "omega" and omega is None) \
                or (terminal == "rows" and rows is None):
            raise ValueError("terminal must be 'omega' with omega given, or 'rows' with rows given")
        N = horizon
        self.terminal = terminal
        self._rows = None if omega is None else omega.shape[0]
        self._omega_norms = None if omega is None else np.abs(np.asarray(omega, float)).sum(axis=1)
        U = stack_sets([s.input_set for s in system.subsystems], [s.m for s in system.subsystems])
        assert U is not None  # every subsystem has an input set
        inputs = StageRows(U.H, np.tile(U.lower, (N, 1)), np.tile(U.upper, (N, 1)))
        X = stack_sets([s.state_set for s in system.subsystems], [s.n for s in system.subsystems])
        states = None if X is None else StageRows(X.H, np.tile(X.lower, (N, 1)), np.tile(X.upper, (N, 1)))
        T = np.asarray(omega if terminal == "omega" else rows, float)
        self._qp = MpcQP(system.A, system.B, system.Q, system.R, P_terminal, N, inputs, states, T, settings)

    def set_target(self, x_s: np.ndarray, u_s: np.ndarray) -> None:
        """Solve in deviation coordinates around the steady state x_s (n,), u_s (m,) of the whole
        system from now on: the stage rows become X - x_s and U - u_s (zeros: the origin)."""
        self._qp.set_offset(x_s, u_s)

    def solve(self, x: np.ndarray, shrink: float = 0.0) -> QPSolution:
        """Solve from the global state x (n,) with the terminal set X^f.

        ``shrink`` > 0 asks for X^f shrunk by a cube of that radius:
        Omega_l z(N) <= 1 - shrink ||Omega_l||_1, i.e. sigma(z(N)) >= shrink.
        """
        if self.terminal == "rows":
            raise ValueError("terminal 'rows': use solve_rows")
        assert self._rows is not None and self._omega_norms is not None  # set with omega, which 'omega' requires
        upper = np.ones(self._rows) if shrink == 0.0 else 1.0 - shrink * self._omega_norms
        return self._qp.solve(x, None, np.full(self._rows, -np.inf), upper)

    def solve_around(self, x: np.ndarray, x_s: np.ndarray, u_s: np.ndarray, scale: float) -> QPSolution:
        """Solve from x (n,) around the steady state x_s (n,), u_s (m,) with the terminal set scaled
        by ``scale`` (lambda in (0, 1]), in deviation coordinates dz = z - x_s, dv = v - u_s:

            min  sum_t dz(t)'Q dz(t) + dv(t)'R dv(t) + dz(N)'P dz(N)
            s.t. dz(0) = x - x_s, dz(t+1) = A dz(t) + B dv(t),
                 dv(t) in U - u_s, dz(t) in X - x_s, Omega dz(N) <= lambda.

        The solution's z (from dz(0) = x - x_s), v and cost are in deviation coordinates: add x_s,
        u_s for the plan itself. Zeros for x_s and u_s are the origin (the rows as set up, and
        scale 1 is X^f: the problem of :meth:`solve`). The stage rows stay where this call moved
        them for later solves too.
        """
        if self.terminal == "rows":
            raise ValueError("terminal 'rows': use solve_rows")
        assert self._rows is not None  # set with omega, which terminal 'omega' requires
        self._qp.set_offset(x_s, u_s)
        return self._qp.solve(x - x_s, None, np.full(self._rows, -np.inf), np.full(self._rows, float(scale)))

    def solve_rows_accurately(self, x: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> QPSolution:
        """:meth:`solve_rows` by the interior-point method, to 1e-10 (:meth:`MpcQP.solve_accurately
        <dmpc.core.mpc_qp.MpcQP.solve_accurately>`): from x (n,) with the terminal rows' bounds
        ``lower``, ``upper`` (r,)."""
        return self._qp.solve_accurately(x, None, lower, upper)

    def solve_rows(self, x: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> QPSolution:
        """Solve from x (n,) with the terminal rows' bounds ``lower``, ``upper``, each shape (r,)."""
        return self._qp.solve(x, None, lower, upper)

