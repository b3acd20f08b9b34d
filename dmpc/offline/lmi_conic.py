"""LMI (11) as a sparse conic program for Clarabel, built directly from the subsystems' blocks.

The LMI couples only subsystems that are coupled in the model: with X = diag(X_i), Y = diag(Y_i),

    [[X, (AX+BY)', (Qh X)', (Rh Y)'], [AX+BY, X, 0, 0], [Qh X, 0, I, 0], [Rh Y, 0, 0, I]] >= 0

has nonzero blocks only where A_ij or B_ij is nonzero (and on the diagonal), so its sparsity graph
is the coupling graph, four times over. It is written here entry by entry, never as dense n x n
matrices, and Clarabel's chordal decomposition splits the one large PSD constraint into small
ones along that graph (a chain of M subsystems gives cliques of two neighbours). Building it
takes time and memory proportional to the number of nonzero blocks, where a modelling layer
spends most of the solve compiling dense expressions.

log det X_i is maximised in the usual way: [[X_i, Z_i], [Z_i', diag(Z_i)]] >= 0 with Z_i lower
triangular, and t_ik <= log Z_i[k, k] in exponential cones; the objective is sum t_ik.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from dmpc.core.system import CoupledSystem

X_FLOOR = 1e-8
"""X_i >= X_FLOOR I keeps the LMI away from X = 0."""
# Clarabel's statuses, named as cvxpy names them
_STATUS = {"Solved": "optimal", "AlmostSolved": "optimal_inaccurate", "PrimalInfeasible": "infeasible",
           "AlmostPrimalInfeasible": "infeasible_inaccurate", "DualInfeasible": "unbounded",
           "AlmostDualInfeasible": "unbounded_inaccurate", "MaxIterations": "user_limit", "MaxTime": "user_limit"}


@dataclass(frozen=True)
class ConicSolution:
    """X_i (n_i, n_i) and Y_i (m_i, n_i) in scaled coordinates, and how the solve ended.

    Attributes
    ----------
    X, Y : list of ndarray, or None when the solver gave no solution
    status : str
        As cvxpy names it: ``optimal``, ``optimal_inaccurate``, ``infeasible``, ..., or
        ``solver_error`` when Clarabel stopped on a numerical error.
    """

    X: list[np.ndarray] | None
    Y: list[np.ndarray] | None
    status: str


class _Builder:
    """Rows of ``A x + s = b`` and their cones, added one cone at a time."""

    def __init__(self) -> None:
        self.rows: list[np.ndarray] = []
        self.cols: list[np.ndarray] = []
        self.vals: list[np.ndarray] = []
        self.b: list[np.ndarray] = []
        self.cones: list = []
        self.count = 0
        self.variables = 0

    def new(self, count: int) -> np.ndarray:
        first = self.variables
        self.variables += count
        return np.arange(first, first + count)

    def psd(self, size: int, entries: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
            constants: list[tuple[int, int, float]]) -> None:
        """A PSD cone of ``size``: entries (r, c, variable, coefficient) with r <= c, constants (r, c, value).

        Clarabel stores the upper triangle by columns, off-diagonal entries times sqrt(2), and
        s = b - A x.
        """
        import clarabel

        def place(r, c):
            return c * (c + 1) // 2 + r, np.where(r == c, 1.0, np.sqrt(2.0))

        if entries:
            r, c, var, coef = (np.concatenate(parts) for parts in zip(*entries))
            index, scale = place(r, c)
            self.rows.append(self.count + index)
            self.cols.append(var)
            self.vals.append(-scale * coef)
        dim = size * (size + 1) // 2
        b = np.zeros(dim)
        for row, col, value in constants:
            index, scale = place(np.asarray(row), np.asarray(col))
            b[index] += scale * value
        self.b.append(b)
        self.cones.append(clarabel.PSDTriangleConeT(size))
        self.count += dim

    def exponential(self, t: int, z: int) -> None:
        """(t, 1, z) in the exponential cone: t <= log z."""
        import clarabel

        self.rows.append(self.count + np.array([0, 2]))
        self.cols.append(np.array([t, z]))
        self.vals.append(np.array([-1.0, -1.0]))
        self.b.append(np.array([0.0, 1.0, 0.0]))
        self.cones.append(clarabel.ExponentialConeT())
        self.count += 3

    def matrices(self) -> tuple[sp.csc_matrix, np.ndarray]:
        A = sp.csc_matrix((np.concatenate(self.vals), (np.concatenate(self.rows), np.concatenate(self.cols))),
                          shape=(self.count, self.variables))
        return A, np.concatenate(self.b)


def _sym_index(size: int) -> tuple[np.ndarray, np.ndarray]:
    """Row and column of each upper-triangle entry of a size x size matrix, in one fixed order."""
    r, c = np.triu_indices(size)
    return r, c


def _sqrtm_psd(M: np.ndarray) -> np.ndarray:
    w, V = np.linalg.eigh((M + M.T) / 2)
    return (V * np.sqrt(np.clip(w, 0.0, None))) @ V.T


def solve_lmi(system: CoupledSystem, scaling: list[np.ndarray], objective: str, shift: float,
              settings: dict) -> ConicSolution:
    """Solve LMI (11) for the state scaling x = D x~ (D = diag(scaling_i)), with Q + shift I.

    Parameters
    ----------
    system : CoupledSystem
    scaling : list of ndarray, shapes (n_i,)
    objective : {"logdet", "feasibility"}
    shift : float
    settings : dict
        Clarabel settings (tolerances).
    """
    import clarabel

    subs = system.subsystems
    n, m = system.n, system.m
    xoff, uoff = system.state_offsets, system.input_offsets
    builder = _Builder()
    Xvar, Yvar = [], []
    for s in subs:
        Xv = np.empty((s.n, s.n), dtype=int)
        r, c = _sym_index(s.n)
        Xv[r, c] = Xv[c, r] = builder.new(r.size)
        Xvar.append(Xv)
        Yvar.append(builder.new(s.m * s.n).reshape(s.m, s.n))
    # scaled blocks: A~_ij = D_i^-1 A_ij D_j, B~_ij = D_i^-1 B_ij, Q~_i = D_i (Q_i + shift I) D_i
    blocks: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
    for i, s in enumerate(subs):
        blocks[(i, i)] = (s.A, s.B)
    for cpl in system.couplings:
        A0, B0 = blocks.get((cpl.target, cpl.source), (0.0, 0.0))
        blocks[(cpl.target, cpl.source)] = (A0 + cpl.A, B0 + cpl.B)
    entries: list = []

    def add(rows, cols, variables, coefs):
        rows, cols = np.broadcast_arrays(np.asarray(rows), np.asarray(cols))
        variables, coefs = np.broadcast_arrays(np.asarray(variables), np.asarray(coefs, dtype=float))
        keep = coefs != 0
        entries.append((rows[keep].ravel(), cols[keep].ravel(), variables[keep].ravel(), coefs[keep].ravel()))

    for j, s in enumerate(subs):
        r, c = _sym_index(s.n)
        for block in (0, n):  # the two X blocks on the diagonal
            add(block + xoff[j] + r, block + xoff[j] + c, Xvar[j][r, c], 1.0)
    for (i, j), (Aij, Bij) in blocks.items():
        di, dj = scaling[i], scaling[j]
        At = Aij * dj[None, :] / di[:, None]
        Bt = Bij / di[:, None]
        nj = subs[j].n
        # entry (x_j alpha, n + x_i beta) = sum_g At[beta, g] X_j[g, alpha] + sum_d Bt[beta, d] Y_j[d, alpha]
        beta, alpha, g = np.meshgrid(np.arange(subs[i].n), np.arange(nj), np.arange(nj), indexing="ij")
        add(xoff[j] + alpha, n + xoff[i] + beta, Xvar[j][g, alpha], At[beta, g])
        beta, alpha, d = np.meshgrid(np.arange(subs[i].n), np.arange(nj), np.arange(subs[j].m), indexing="ij")
        add(xoff[j] + alpha, n + xoff[i] + beta, Yvar[j][d, alpha], Bt[beta, d])
    for j, s in enumerate(subs):
        D = scaling[j]
        Qh = _sqrtm_psd(D[:, None] * (s.Q + shift * np.eye(s.n)) * D[None, :])
        Rh = _sqrtm_psd(s.R)
        beta, alpha, g = np.meshgrid(np.arange(s.n), np.arange(s.n), np.arange(s.n), indexing="ij")
        add(xoff[j] + alpha, 2 * n + xoff[j] + beta, Xvar[j][g, alpha], Qh[beta, g])
        e, alpha, d = np.meshgrid(np.arange(s.m), np.arange(s.n), np.arange(s.m), indexing="ij")
        add(xoff[j] + alpha, 3 * n + uoff[j] + e, Yvar[j][d, alpha], Rh[e, d])
    identity = [(k, k, 1.0) for k in range(2 * n, 3 * n + m)]
    builder.psd(3 * n + m, entries, identity)
    for j, s in enumerate(subs):
        r, c = _sym_index(s.n)
        builder.psd(s.n, [(r, c, Xvar[j][r, c], np.ones(r.size))], [(k, k, -X_FLOOR) for k in range(s.n)])
    q = np.zeros(0)
    if objective == "logdet":
        logs = []
        for j, s in enumerate(subs):
            p, k = np.tril_indices(s.n)
            Z = np.full((s.n, s.n), -1)
            Z[p, k] = builder.new(p.size)
            t = builder.new(s.n)
            logs.append(t)
            r, c = _sym_index(s.n)
            parts = [(r, c, Xvar[j][r, c], np.ones(r.size)),
                     (p, s.n + k, Z[p, k], np.ones(p.size)),  # Z_j in the upper-right block (lower triangular)
                     (s.n + np.arange(s.n), s.n + np.arange(s.n), np.diag(Z), np.ones(s.n))]
            builder.psd(2 * s.n, parts, [])
            for kk in range(s.n):
                builder.exponential(int(t[kk]), int(Z[kk, kk]))
        q = np.zeros(builder.variables)
        q[np.concatenate(logs)] = -1.0
    A, b = builder.matrices()
    if q.size == 0:
        q = np.zeros(builder.variables)
    options = clarabel.DefaultSettings()
    options.verbose = False
    for key, value in settings.items():
        setattr(options, key, value)
    solver = clarabel.DefaultSolver(sp.csc_matrix((builder.variables, builder.variables)), q, A, b, builder.cones,
                                    options)
    try:
        result = solver.solve()
    except BaseException as exc:  # Clarabel's Rust panics arrive as pyo3's PanicException, a BaseException
        if type(exc).__name__ != "PanicException":
            raise
        # seen as "Eigval error" on a badly conditioned LMI: a failed solve, like any other solver error
        return ConicSolution(None, None, "solver_error")
    kind = _STATUS.get(str(result.status), "solver_error")
    if kind not in ("optimal", "optimal_inaccurate"):
        return ConicSolution(None, None, kind)
    x = np.asarray(result.x)
    return ConicSolution([x[Xv] for Xv in Xvar], [x[Yv] for Yv in Yvar], kind)
