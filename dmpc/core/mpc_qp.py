"""The sparse MPC QP in OSQP form, shared by the local and the centralised problems.

Decision vector ``[z(0), ..., z(N), v(0), ..., v(N-1)]`` (OSQP's MPC example layout):

    min  sum_{t<N} z(t)'Q z(t) + v(t)'R v(t) + z(N)'P z(N)
    s.t. z(0) = x,  z(t+1) = A z(t) + B v(t) + c(t)       (equality rows, right side updated per solve)
         lower_u(t) <= H_u v(t) <= upper_u(t)              t = 0..N-1
         lower_x(t) <= H_x z(t) <= upper_x(t)              t = 1..N
         T z(N) in [terminal lower, terminal upper]        (updated per solve)

Only bound vectors change between solves, so the matrices are factorised once.

Accuracy: the k = 0 Jacobi iteration stops at a plan change of 1e-9, below what OSQP's ADMM
reaches at eps 1e-7, so every solve relies on polishing (a solve of the KKT system of the
guessed active set). The polished solution is refined iteratively against OSQP's regularisation
delta; with one refinement step polishing failed on a quarter of the solves of badly scaled
QPs and the iteration stalled at its cap. Three steps (OSQP's own default) suffice on the
shipped and test systems. An instance whose solve still fails to polish switches to
POLISH_RETRY_REFINE_ITER steps for good and repeats the solve, warm-started from the unpolished
iterate (a few ADMM iterations and a polish), so badly conditioned QPs pay for the extra
steps and the others do not.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import osqp
import scipy.sparse as sp
from osqp import SolverStatus

from dmpc.core.qp_status import QPStatus

# OSQP's integer status codes (its SolverStatus enum) in the project's terms
_OSQP_STATUS = {
    SolverStatus.OSQP_SOLVED: QPStatus.SOLVED,
    SolverStatus.OSQP_SOLVED_INACCURATE: QPStatus.INACCURATE,
    SolverStatus.OSQP_PRIMAL_INFEASIBLE: QPStatus.INFEASIBLE,
    SolverStatus.OSQP_PRIMAL_INFEASIBLE_INACCURATE: QPStatus.INFEASIBLE,
    SolverStatus.OSQP_DUAL_INFEASIBLE: QPStatus.UNBOUNDED,
    SolverStatus.OSQP_DUAL_INFEASIBLE_INACCURATE: QPStatus.UNBOUNDED,
    SolverStatus.OSQP_MAX_ITER_REACHED: QPStatus.MAX_ITER,
}

OSQP_INFTY = 1e30

# info.status_polish codes of OSQP 1.x (osqp_polish_status_type in osqp_api_constants.h; the
# Python package exports no enum for them)
POLISH_SUCCESS = 1
POLISH_FAILED = -1

POLISH_RETRY_REFINE_ITER = 25

DENSE_ROWS = 60_000
"""A QP whose constraint matrix has at most this many entries (rows x variables) also keeps it
dense, for :meth:`MpcQP.violations` (about 0.5 MB at most)."""

DEFAULT_SETTINGS = dict(
    eps_abs=1e-7,
    eps_rel=1e-7,
    max_iter=10000,
    polishing=True,
    warm_starting=True,
    check_termination=5,
    polish_refine_iter=3,
    adaptive_rho_interval=25,  # fixed: the default (0) adapts on measured time, which is not reproducible
    verbose=False,
)


@dataclass(frozen=True)
class QPSolution:
    """One solve.

    Attributes
    ----------
    status : QPStatus
    z : ndarray, shape (N + 1, n)
        Nominal states; ``z[0]`` is the measured state. NaN when not solved.
    v : ndarray, shape (N, m)
        Nominal inputs. NaN when not solved.
    cost : float
        The objective value of the plan (NaN when not solved).
    solve_time : float
        Seconds spent in update + solve.
    iterations : int
        ADMM iterations (of the repeated solve, if the first one did not polish).
    polished : bool
        True when OSQP's polishing succeeded (``info.status_polish`` = 1): the solution is the
        exact optimum of the guessed active set, accurate far below eps_abs. False when
        polishing failed, was not run (infeasible, iteration limit, polishing off) or the
        problem was decided without OSQP.
    """

    status: QPStatus
    z: np.ndarray
    v: np.ndarray
    cost: float
    solve_time: float
    iterations: int
    polished: bool = False


@dataclass(frozen=True)
class StageRows:
    """Constraint rows applied at every step: ``lower[t] <= H w(t) <= upper[t]``.

    H has shape (r, d); lower and upper have shape (steps, r).
    """

    H: np.ndarray
    lower: np.ndarray
    upper: np.ndarray


class MpcQP:
    """The QP above for given matrices; ``solve`` updates x, c and the terminal bounds.

    Parameters
    ----------
    A : ndarray, shape (n, n)
    B : ndarray, shape (n, m)
    Q, R, P : ndarray
        Stage and terminal weights.
    horizon : int
    inputs : StageRows
        Rows on v(t), ``steps = N``.
    states : StageRows or None
        Rows on z(t), t = 1..N (``steps = N``).
    terminal : ndarray, shape (r_f, n)
        T in the terminal rows.
    settings : dict, optional
        OSQP settings overriding DEFAULT_SETTINGS.
    interior_point : bool
        A solve that OSQP ends at its iteration cap, or solves only inaccurately, is solved again
        by an interior-point method (Clarabel) on the same matrices and bounds: ADMM can crawl on
        degenerate problems (many active rows, a thin feasible set) that an interior-point method
        settles in a few dozen iterations. Off by default (the paper's QPs never needed it).
    """

    def __init__(self, A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray, P: np.ndarray, horizon: int,
                 inputs: StageRows, states: StageRows | None, terminal: np.ndarray,
                 settings: dict[str, Any] | None = None, interior_point: bool = False) -> None:
        n, m, N = B.shape[0], B.shape[1], horizon
        self.n, self.m, self.N = n, m, N
        self._Q, self._R, self._P = Q, R, P
        nz, nv = (N + 1) * n, N * m
        self._nz = nz
        cost = sp.block_diag([sp.kron(sp.eye(N), Q), P, sp.kron(sp.eye(N), R)], format="csc")
        Ax = sp.kron(sp.eye(N + 1), -sp.eye(n)) + sp.kron(sp.eye(N + 1, k=-1), A)
        Bv = sp.kron(sp.vstack([sp.csc_matrix((1, N)), sp.eye(N)]), B)
        blocks, lower, upper = [sp.hstack([Ax, Bv])], [np.zeros(nz)], [np.zeros(nz)]
        Hu = inputs.H
        blocks.append(sp.hstack([sp.csc_matrix((N * Hu.shape[0], nz)), sp.kron(sp.eye(N), Hu)]))
        lower.append(np.asarray(inputs.lower, float).ravel())
        upper.append(np.asarray(inputs.upper, float).ravel())
        # the stage rows, to move them with a setpoint target (set_offset)
        self._stages = [(slice(nz, nz + lower[-1].size), np.asarray(Hu, float), N)]
        if states is not None and states.H.shape[0]:
            Hx = states.H
            sel = sp.hstack([sp.csc_matrix((N, 1)), sp.eye(N)])
            blocks.append(sp.hstack([sp.kron(sel, Hx), sp.csc_matrix((N * Hx.shape[0], nv))]))
            lower.append(np.asarray(states.lower, float).ravel())
            upper.append(np.asarray(states.upper, float).ravel())
            start = self._stages[0][0].stop
            self._stages.append((slice(start, start + lower[-1].size), np.asarray(Hx, float), N))
        T = sp.csc_matrix(terminal)
        start = sum(b.size for b in lower)
        self._terminal = slice(start, start + T.shape[0])
        blocks.append(sp.hstack([sp.csc_matrix((T.shape[0], N * n)), T, sp.csc_matrix((T.shape[0], nv))]))
        lower.append(np.full(T.shape[0], -np.inf))
        upper.append(np.full(T.shape[0], np.inf))
        # OSQP treats |bounds| >= OSQP_INFTY as infinite; clip once here instead of on every update
        self._l = np.clip(np.concatenate(lower), -OSQP_INFTY, OSQP_INFTY)
        self._u = np.clip(np.concatenate(upper), -OSQP_INFTY, OSQP_INFTY)
        opts = dict(DEFAULT_SETTINGS)
        opts.update(settings or {})
        self._rows = sp.vstack(blocks, format="csc")
        self._interior_point = interior_point
        self._hessian = 2.0 * sp.triu(cost, format="csc")
        self._solver = osqp.OSQP()
        self._solver.setup(P=2.0 * sp.triu(cost, format="csc"), q=np.zeros(nz + nv),
                           A=self._rows, l=self._l, u=self._u, **opts)
        self._refine = int(opts["polish_refine_iter"])
        self._nvars = nz + nv
        self._cold = False
        self._base = (self._l.copy(), self._u.copy())  # the stage bounds around the origin
        self._offset = (np.zeros(n), np.zeros(m))  # the steady state the stage rows are around (set_offset)
        # violations() multiplies a plan by the rows at every kept step: dense is faster while small
        self._dense_rows = self._rows.toarray() if self._rows.shape[0] * self._rows.shape[1] <= DENSE_ROWS else None
        self._scale_row_bounds()

    def set_offset(self, x_s: np.ndarray, u_s: np.ndarray) -> None:
        """Move the stage rows to deviation coordinates around a steady state: U - u_s, X - x_s.

        x_s (n,) and u_s (m,); zeros are the origin, the rows as set up (restored exactly). Only
        the bounds change, so the factorisation is kept.
        """
        x_s, u_s = np.array(x_s, float), np.array(u_s, float)
        if np.array_equal(self._offset[0], x_s) and np.array_equal(self._offset[1], u_s):
            return
        self._offset = (x_s, u_s)
        at_origin = not np.any(x_s) and not np.any(u_s)
        for (rows, H, steps), shift in zip(self._stages, (u_s, x_s)):
            if at_origin:
                self._l[rows], self._u[rows] = self._base[0][rows], self._base[1][rows]
                continue
            moved = np.tile(H @ shift, steps)
            self._l[rows] = np.clip(self._base[0][rows] - moved, -OSQP_INFTY, OSQP_INFTY)
            self._u[rows] = np.clip(self._base[1][rows] - moved, -OSQP_INFTY, OSQP_INFTY)
        self._scale_row_bounds()

    def solve(self, x: np.ndarray, coupling: np.ndarray | None, terminal_lower: np.ndarray,
              terminal_upper: np.ndarray, start: tuple[np.ndarray, np.ndarray] | None = None) -> QPSolution:
        """Solve from x (n,) with the feed-forward ``coupling`` c (N, n) or None and the terminal rows'
        bounds ``terminal_lower``, ``terminal_upper`` (r_f,).

        Infinite terminal bounds are allowed (clipped to OSQP_INFTY). ``start`` (z (N+1, n),
        v (N, m)), when given, is the primal point the solver starts from (its duals stay those
        of the last solve); otherwise it starts from the last solution."""
        n, nz = self.n, self._nz
        l, u = self._l, self._u
        N = self.N
        if not self._set_bounds(x, coupling, terminal_lower, terminal_upper):
            # an empty terminal set (e.g. beta below the tube margin): OSQP would reject the
            # update and silently keep the previous problem, so answer here
            return QPSolution(QPStatus.INFEASIBLE, np.full((N + 1, n), np.nan), np.full((N, self.m), np.nan),
                              float("nan"), 0.0, 0)
        if self._cold:
            self._solver.warm_start(x=np.zeros(self._nvars), y=np.zeros(l.size))
            self._cold = False
        if start is not None:
            self._solver.warm_start(x=np.concatenate((start[0].reshape(-1), start[1].reshape(-1))))
        t0 = time.perf_counter()
        info, solution = self._run(l, u)
        if info.status_polish == POLISH_FAILED and self._refine < POLISH_RETRY_REFINE_ITER:
            self._refine = POLISH_RETRY_REFINE_ITER
            self._solver.update_settings(polish_refine_iter=self._refine)
            info, solution = self._run(l, u)
        status = _OSQP_STATUS.get(info.status_val, QPStatus.ERROR)
        polished = info.status_polish == POLISH_SUCCESS
        settled = None
        if self._interior_point and status in (QPStatus.MAX_ITER, QPStatus.INACCURATE):
            settled = _interior_point_solve(self._hessian, self._rows, l, u)
            if settled is not None:
                status, solution, polished = QPStatus.SOLVED, settled, True
                self._solver.warm_start(x=settled)
        elapsed = time.perf_counter() - t0
        if not status.feasible:
            # a failed solve leaves iterates that mislead the next warm start: start cold
            self._cold = True
            return QPSolution(status, np.full((N + 1, n), np.nan), np.full((N, self.m), np.nan), float("nan"),
                              elapsed, info.iter)
        z = solution[:nz].reshape(N + 1, n)
        z[0] = x
        v = solution[nz:].reshape(N, self.m)
        # q = 0 and P = 2 * cost, so OSQP's objective is the plan's cost
        cost = float(info.obj_val) if settled is None else self.cost(z, v)
        return QPSolution(status, z, v, cost, elapsed, info.iter, polished)

    def _set_bounds(self, x: np.ndarray, coupling: np.ndarray | None, terminal_lower: np.ndarray,
                    terminal_upper: np.ndarray) -> bool:
        """Put x (n,), the feed-forward (N, n) or None and the terminal bounds (r_f,) into the rows'
        bounds; False where the terminal set is empty (lower > upper somewhere)."""
        n, nz = self.n, self._nz
        l, u = self._l, self._u
        np.negative(x, out=l[:n])
        if coupling is None:
            l[n:nz] = 0.0
        else:
            np.negative(coupling.reshape(-1), out=l[n:nz])
        u[:nz] = l[:nz]
        # clipped to +-OSQP_INFTY (np.clip's values, without its dispatch: this runs every step)
        lower_f, upper_f = l[self._terminal], u[self._terminal]
        np.minimum(np.maximum(terminal_lower, -OSQP_INFTY, out=lower_f), OSQP_INFTY, out=lower_f)
        np.minimum(np.maximum(terminal_upper, -OSQP_INFTY, out=upper_f), OSQP_INFTY, out=upper_f)
        return not (lower_f > upper_f).any()

    def solve_accurately(self, x: np.ndarray, coupling: np.ndarray | None, terminal_lower: np.ndarray,
                         terminal_upper: np.ndarray) -> QPSolution:
        """The QP of :meth:`solve` (same arguments: x (n,), ``coupling`` (N, n) or None, the terminal
        bounds ``terminal_lower``, ``terminal_upper`` (r_f,)) solved by the interior-point method
        to 1e-10, where a plan must meet its rows far below OSQP's accuracy (a starting point
        others build on); status ``infeasible`` where it finds none."""
        N, n = self.N, self.n
        t0 = time.perf_counter()
        solution = None
        if self._set_bounds(x, coupling, terminal_lower, terminal_upper):
            solution = _interior_point_solve(self._hessian, self._rows, self._l, self._u)
        elapsed = time.perf_counter() - t0
        if solution is None:
            return QPSolution(QPStatus.INFEASIBLE, np.full((N + 1, n), np.nan), np.full((N, self.m), np.nan),
                              float("nan"), elapsed, 0)
        z = solution[:self._nz].reshape(N + 1, n)
        z[0] = x
        v = solution[self._nz:].reshape(N, self.m)
        return QPSolution(QPStatus.SOLVED, z, v, self.cost(z, v), elapsed, 0, True)

    def violations(self, x: np.ndarray, coupling: np.ndarray | None, terminal_lower: np.ndarray,
                   terminal_upper: np.ndarray, z: np.ndarray, v: np.ndarray) -> tuple[float, float]:
        """How far the plan z (N+1, n), v (N, m) is from a feasible point of the QP that
        :meth:`solve` would solve with the same arguments (x, coupling, terminal_lower,
        terminal_upper): the largest residual of its dynamics rows, and the largest excess over its
        input, state and terminal rows, each relative to max(1, |bound|). Both 0 for a feasible plan,
        both inf for a plan that is not finite; nothing is solved."""
        nz, n = self._nz, self.n
        w = np.concatenate((z.reshape(-1), v.reshape(-1)))
        if not np.isfinite(w).all():
            return float("inf"), float("inf")
        rows = self._dense_rows @ w if self._dense_rows is not None else self._rows @ w
        target = np.zeros(nz)
        np.negative(x, out=target[:n])
        if coupling is not None:
            np.negative(coupling.reshape(-1), out=target[n:])
        dynamics = float((np.abs(rows[:nz] - target) / np.maximum(1.0, np.abs(target))).max())
        lower, upper, lower_scale, upper_scale = self._row_bounds  # the input and state rows set, the terminal's now
        terminal = slice(self._terminal.start - nz, self._terminal.stop - nz)
        np.minimum(np.maximum(terminal_lower, -OSQP_INFTY, out=lower[terminal]), OSQP_INFTY, out=lower[terminal])
        np.minimum(np.maximum(terminal_upper, -OSQP_INFTY, out=upper[terminal]), OSQP_INFTY, out=upper[terminal])
        np.maximum(1.0, np.abs(lower[terminal]), out=lower_scale[terminal])
        np.maximum(1.0, np.abs(upper[terminal]), out=upper_scale[terminal])
        rest = rows[nz:]
        excess = np.maximum((lower - rest) / lower_scale, (rest - upper) / upper_scale)
        return dynamics, max(float(excess.max()), 0.0) if excess.size else 0.0

    def _scale_row_bounds(self) -> None:
        """The bounds of the rows after the dynamics and their scales max(1, |bound|), for
        :meth:`violations`: the input and state rows' change only with :meth:`set_offset`, the
        terminal rows' are set by each call."""
        rows = slice(self._nz, None)
        lower, upper = self._l[rows].copy(), self._u[rows].copy()
        self._row_bounds = (lower, upper, np.maximum(1.0, np.abs(lower)), np.maximum(1.0, np.abs(upper)))

    def _run(self, l: np.ndarray, u: np.ndarray) -> tuple[Any, np.ndarray]:
        """Set the bounds l, u (each (rows,)) and solve; OSQP's info and primal solution (vars,)."""
        self._solver.update(l=l, u=u)
        res = self._solver.solve(raise_error=False)
        return res.info, res.x

    def cost(self, z: np.ndarray, v: np.ndarray) -> float:
        """Objective of a plan: z (N+1, n), v (N, m)."""
        return plan_cost(z, v, self._Q, self._R, self._P)


def plan_cost(z: np.ndarray, v: np.ndarray, Q: np.ndarray, R: np.ndarray, P: np.ndarray) -> float:
    """sum_{t<N} z'Qz + v'Rv + z(N)'P z(N) for z (N+1, n), v (N, m), with the weights Q (n, n),
    R (m, m) and P (n, n)."""
    zs, zN = z[:-1], z[-1]
    return float(((zs @ Q) * zs).sum() + ((v @ R) * v).sum() + zN @ P @ zN)


def _interior_point_solve(hessian: sp.csc_matrix, rows: sp.csc_matrix, lower: np.ndarray,
                          upper: np.ndarray) -> np.ndarray | None:
    """min w' (hessian / 2) w subject to lower <= rows w <= upper, by Clarabel; None unless solved.

    Parameters
    ----------
    hessian : sparse matrix, shape (d, d)
        Upper triangular (OSQP's P).
    rows : sparse matrix, shape (r, d)
    lower, upper : ndarray, shape (r,)
        Bounds; |bound| >= OSQP_INFTY is no bound, lower = upper an equality.
    """
    import clarabel  # only where OSQP gave up: an agent process loads it on its first such solve

    equal = lower == upper
    up = ~equal & (upper < OSQP_INFTY)
    low = ~equal & (lower > -OSQP_INFTY)
    A = sp.vstack([rows[np.flatnonzero(equal)], rows[np.flatnonzero(up)], -rows[np.flatnonzero(low)]], format="csc")
    b = np.concatenate([upper[equal], upper[up], -lower[low]])
    cones = [clarabel.ZeroConeT(int(equal.sum())), clarabel.NonnegativeConeT(int(up.sum() + low.sum()))]
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    settings.tol_gap_abs = settings.tol_gap_rel = settings.tol_feas = 1e-10
    result = clarabel.DefaultSolver(hessian, np.zeros(hessian.shape[0]), A, b, cones, settings).solve()
    if str(result.status) != "Solved":
        return None
    return np.asarray(result.x, dtype=float)
