"""The local QP_i of one agent, solved with OSQP (ALGORITHM.md 3.3).

Decision vector ``[z(0), ..., z(N), v(0), ..., v(N-1)]``. The matrices are built once; per step
only the bound vectors change (measured state, coupling feed-forward, terminal box, which are
all constants of the QP) and OSQP is warm-started from its last solution.

    min  sum_{t<N} z(t)'Q z(t) + v(t)'R v(t) + z(N)'P z(N)
    s.t. z(0) = x,  z(t+1) = A z(t) + B v(t) + c(t)
         lower_u + m_u(t) <= H_u v(t) <= upper_u - m_u(t)              t = 0..N-1
         lower_x + m_x(t) <= H_x z(t) <= upper_x - m_x(t)              t = 1..N
         |z(N) - alpha| <= beta - m_f                                  (elementwise)
"""
from __future__ import annotations

import enum
import time
from dataclasses import dataclass

import numpy as np
import osqp
import scipy.sparse as sp

from dmpc.design.tubes import Tightening
from dmpc.system import Subsystem


class QPStatus(str, enum.Enum):
    """Solver outcome in the project's own terms."""

    SOLVED = "solved"
    INACCURATE = "solved_inaccurate"
    INFEASIBLE = "infeasible"
    UNBOUNDED = "unbounded"
    MAX_ITER = "max_iter"
    ERROR = "error"

    @property
    def feasible(self) -> bool:
        return self in (QPStatus.SOLVED, QPStatus.INACCURATE)


_OSQP_STATUS = {
    "solved": QPStatus.SOLVED,
    "solved inaccurate": QPStatus.INACCURATE,
    "primal infeasible": QPStatus.INFEASIBLE,
    "primal infeasible inaccurate": QPStatus.INFEASIBLE,
    "dual infeasible": QPStatus.UNBOUNDED,
    "dual infeasible inaccurate": QPStatus.UNBOUNDED,
    "maximum iterations reached": QPStatus.MAX_ITER,
}

DEFAULT_SETTINGS = dict(
    eps_abs=1e-7,
    eps_rel=1e-7,
    eps_prim_inf=1e-8,
    eps_dual_inf=1e-8,
    max_iter=20000,
    polishing=True,
    warm_starting=True,
    check_termination=5,
    verbose=False,
)


@dataclass(frozen=True)
class QPSolution:
    """One solve of QP_i.

    Attributes
    ----------
    status : QPStatus
    z : ndarray, shape (N + 1, n)
        Nominal states; ``z[0]`` is the measured state. NaN when infeasible.
    v : ndarray, shape (N, m)
        Nominal inputs. NaN when infeasible.
    cost : float
        Own cost J_i (NaN when infeasible).
    solve_time : float
        Seconds spent in update + solve.
    iterations : int
    """

    status: QPStatus
    z: np.ndarray
    v: np.ndarray
    cost: float
    solve_time: float
    iterations: int


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
    """

    def __init__(self, sub: Subsystem, P_terminal: np.ndarray, horizon: int, tightening: Tightening,
                 settings: dict | None = None) -> None:
        n, m, N = sub.n, sub.m, horizon
        self.n, self.m, self.N = n, m, N
        self._Q, self._R, self._P = sub.Q, sub.R, P_terminal
        nz, nv = (N + 1) * n, N * m
        self._nz = nz
        cost = sp.block_diag([sp.kron(sp.eye(N), sub.Q), P_terminal, sp.kron(sp.eye(N), sub.R)], format="csc")
        # dynamics rows: -z(0) = -x ; A z(t) - z(t+1) + B v(t) = -c(t)
        Ax = sp.kron(sp.eye(N + 1), -sp.eye(n)) + sp.kron(sp.eye(N + 1, k=-1), sub.A)
        Bv = sp.kron(sp.vstack([sp.csc_matrix((1, N)), sp.eye(N)]), sub.B)
        blocks = [sp.hstack([Ax, Bv])]
        lower, upper = [np.zeros(nz)], [np.zeros(nz)]
        # input rows
        Hu = sub.input_set.H
        blocks.append(sp.hstack([sp.csc_matrix((N * Hu.shape[0], nz)), sp.kron(sp.eye(N), Hu)]))
        lower.append((sub.input_set.lower + tightening.input_margin).ravel())
        upper.append((sub.input_set.upper - tightening.input_margin).ravel())
        # state rows for t = 1..N
        if sub.state_set is not None:
            Hx = sub.state_set.H
            sel = sp.hstack([sp.csc_matrix((N, 1)), sp.eye(N)])
            blocks.append(sp.hstack([sp.kron(sel, Hx), sp.csc_matrix((N * Hx.shape[0], nv))]))
            lower.append((sub.state_set.lower + tightening.state_margin[1:]).ravel())
            upper.append((sub.state_set.upper - tightening.state_margin[1:]).ravel())
        # terminal box rows
        blocks.append(sp.hstack([sp.csc_matrix((n, N * n)), sp.eye(n), sp.csc_matrix((n, nv))]))
        self._terminal = slice(sum(b.size for b in lower), sum(b.size for b in lower) + n)
        lower.append(np.zeros(n))
        upper.append(np.zeros(n))
        self._terminal_margin = tightening.terminal_margin
        self._l = np.concatenate(lower)
        self._u = np.concatenate(upper)
        A = sp.vstack(blocks, format="csc")
        self._solver = osqp.OSQP()
        opts = dict(DEFAULT_SETTINGS)
        opts.update(settings or {})
        self._solver.setup(P=2.0 * sp.triu(cost, format="csc"), q=np.zeros(nz + nv), A=A,
                           l=self._l, u=self._u, **opts)

    def solve(self, x: np.ndarray, coupling: np.ndarray, alpha: np.ndarray, beta: float) -> QPSolution:
        """Solve QP_i for one step.

        Parameters
        ----------
        x : ndarray, shape (n,)
            Measured state x_i(k).
        coupling : ndarray, shape (N, n)
            Feed-forward c_i(t), t = 0..N-1 (zeros for the decoupled nominal model).
        alpha : ndarray, shape (n,)
            Centre of the terminal box.
        beta : float
            Radius of the terminal box.
        """
        n, N = self.n, self.N
        l, u = self._l, self._u
        l[:n] = -x
        u[:n] = -x
        l[n:self._nz] = -coupling.ravel()
        u[n:self._nz] = -coupling.ravel()
        radius = beta - self._terminal_margin
        l[self._terminal] = alpha - radius
        u[self._terminal] = alpha + radius
        t0 = time.perf_counter()
        self._solver.update(l=l, u=u)
        res = self._solver.solve()
        elapsed = time.perf_counter() - t0
        status = _OSQP_STATUS.get(res.info.status, QPStatus.ERROR)
        if not status.feasible:
            nan_z, nan_v = np.full((N + 1, n), np.nan), np.full((N, self.m), np.nan)
            return QPSolution(status, nan_z, nan_v, float("nan"), elapsed, res.info.iter)
        z = res.x[: self._nz].reshape(N + 1, n).copy()
        z[0] = x
        v = res.x[self._nz :].reshape(N, self.m).copy()
        return QPSolution(status, z, v, self.cost(z, v), elapsed, res.info.iter)

    def cost(self, z: np.ndarray, v: np.ndarray) -> float:
        """Own cost J_i of a plan: z shape (N+1, n), v shape (N, m)."""
        stage = np.einsum("ti,ij,tj->", z[:-1], self._Q, z[:-1]) + np.einsum("ti,ij,tj->", v, self._R, v)
        return float(stage + z[-1] @ self._P @ z[-1])
