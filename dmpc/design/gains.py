"""Block-diagonal terminal gains K = diag(K_i) and weights P = diag(P_i) (ALGORITHM.md 2.1).

The requirement on the *global* coupled system is eq. (10):

    (A+BK)^T P (A+BK) - P <= -(Q + K^T R K).

Three ways to get them: ``lmi`` (eq. (11) with block-diagonal X = P^-1, Y = K X, maximising
log det X), ``lqr`` (per-subsystem DARE, then verified) and ``given`` (from the scenario,
verified). Every result is verified the same way.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from dmpc.design.errors import DesignError
from dmpc.system import CoupledSystem, block_diag

LMI_OBJECTIVE = "maximise log det X (X = P^-1, block diagonal): the largest terminal ellipsoid"


@dataclass(frozen=True)
class GainDesign:
    """Terminal gains and weights with their verification figures.

    Attributes
    ----------
    K : list of ndarray, shapes (m_i, n_i)
    P : list of ndarray, shapes (n_i, n_i)
    method : str
        ``lmi``, ``lqr`` or ``given``.
    rho : float
        Spectral radius of A + BK (global).
    lyapunov_margin : float
        Largest eigenvalue of (A+BK)^T P (A+BK) - P + Q + K^T R K; (10) holds when it is
        <= ``lyapunov_tolerance``.
    lyapunov_tolerance : float
        1e-6 * lambda_max(P): the log-det optimum sits on the boundary of (10).
    objective : str
        What the design optimised (empty for ``given``).
    """

    K: list[np.ndarray]
    P: list[np.ndarray]
    method: str
    rho: float
    lyapunov_margin: float
    lyapunov_tolerance: float
    objective: str = ""

    def K_global(self) -> np.ndarray:
        return block_diag(*self.K)

    def P_global(self) -> np.ndarray:
        return block_diag(*self.P)


def closed_loop_matrix(system: CoupledSystem, K: list[np.ndarray]) -> np.ndarray:
    """A + B diag(K_i), shape (n, n)."""
    return system.A + system.B @ block_diag(*K)


def verify_gains(system: CoupledSystem, K: list[np.ndarray], P: list[np.ndarray], method: str,
                 objective: str = "") -> GainDesign:
    """Check stability and (10) for the coupled system; raise DesignError with figures if not.

    Parameters
    ----------
    system : CoupledSystem
    K : list of ndarray, shapes (m_i, n_i)
    P : list of ndarray, shapes (n_i, n_i)
    method, objective : str
        Recorded in the result.
    """
    Kg = block_diag(*K)
    Pg = block_diag(*P)
    AK = system.A + system.B @ Kg
    rho = float(np.max(np.abs(np.linalg.eigvals(AK))))
    lhs = AK.T @ Pg @ AK - Pg + system.Q + Kg.T @ system.R @ Kg
    margin = float(np.max(np.linalg.eigvalsh((lhs + lhs.T) / 2)))
    p_eigs = np.linalg.eigvalsh((Pg + Pg.T) / 2)
    tolerance = 1e-6 * float(np.max(np.abs(p_eigs)))
    if rho >= 1.0:
        worst = _worst_block(system, K)
        raise DesignError(
            f"gains ({method}) give an unstable closed loop: spectral radius of A+BK is {rho:.4g} >= 1"
            + worst
        )
    if np.min(p_eigs) <= 0:
        raise DesignError(f"gains ({method}): P is not positive definite (smallest eigenvalue {np.min(p_eigs):.3g})")
    if margin > tolerance:
        raise DesignError(
            f"gains ({method}) violate the Lyapunov decrease (10) for the coupled system: largest "
            f"eigenvalue of (A+BK)'P(A+BK) - P + Q + K'RK is {margin:.4g} > {tolerance:.2g} "
            f"(rho(A+BK) = {rho:.4g})"
        )
    return GainDesign(K=[np.asarray(k, float) for k in K], P=[np.asarray(p, float) for p in P],
                      method=method, rho=rho, lyapunov_margin=margin, lyapunov_tolerance=tolerance,
                      objective=objective)


def _worst_block(system: CoupledSystem, K: list[np.ndarray]) -> str:
    parts = []
    for i, s in enumerate(system.subsystems):
        r = float(np.max(np.abs(np.linalg.eigvals(s.A + s.B @ K[i]))))
        if r >= 1.0:
            parts.append(f"subsystem {s.name}: rho(A_ii + B_ii K_i) = {r:.4g}")
    return ("; " + ", ".join(parts)) if parts else ""


def lqr_gains(system: CoupledSystem) -> GainDesign:
    """Per-subsystem DARE gains, verified on the coupled system."""
    from scipy.linalg import solve_discrete_are

    K, P = [], []
    for s in system.subsystems:
        try:
            Pi = solve_discrete_are(s.A, s.B, s.Q, s.R)
        except (np.linalg.LinAlgError, ValueError) as exc:
            raise DesignError(f"gains (lqr): the Riccati equation of subsystem {s.name} has no solution: {exc}") from None
        Ki = -np.linalg.solve(s.R + s.B.T @ Pi @ s.B, s.B.T @ Pi @ s.A)
        K.append(Ki)
        P.append((Pi + Pi.T) / 2)
    return verify_gains(system, K, P, "lqr", "per-subsystem DARE (not optimised for the coupling)")


def lmi_gains(system: CoupledSystem) -> GainDesign:
    """Solve LMI (11) with block-diagonal X and Y, maximising log det X.

    Clarabel with chordal decomposition handles the sparse block structure. If the direct
    solve fails numerically (badly scaled systems), a feasibility solve gives a per-subsystem
    state scaling, the log-det problem is solved in scaled coordinates and mapped back:
    log det X changes by a constant under the scaling, so the optimum is the same.
    """
    try:
        X, Y = _solve_lmi(system, scaling=None, objective="logdet")
    except DesignError:
        Xf, _ = _solve_lmi(system, scaling=None, objective="feasibility")
        scaling = [np.sqrt(np.clip(np.diag(x), 1e-12, None)) for x in Xf]
        X, Y = _solve_lmi(system, scaling=scaling, objective="logdet")
    K = [Y[i] @ np.linalg.inv(X[i]) for i in range(system.M)]
    P = [np.linalg.inv(X[i]) for i in range(system.M)]
    P = [(p + p.T) / 2 for p in P]
    return verify_gains(system, K, P, "lmi", LMI_OBJECTIVE)


def _solve_lmi(system: CoupledSystem, scaling: list[np.ndarray] | None, objective: str):
    """Return per-subsystem X_i (n_i, n_i) and Y_i (m_i, n_i) in original coordinates."""
    import cvxpy as cp
    from scipy.linalg import sqrtm

    subs = system.subsystems
    if scaling is None:
        scaling = [np.ones(s.n) for s in subs]
    D = block_diag(*[np.diag(d) for d in scaling])
    Dinv = np.linalg.inv(D)
    # x = D x~  =>  A~ = D^-1 A D, B~ = D^-1 B, Q~ = D Q D, R unchanged
    A = Dinv @ system.A @ D
    B = Dinv @ system.B
    Qh = sqrtm(D @ system.Q @ D).real
    Rh = sqrtm(system.R).real
    Xs = [cp.Variable((s.n, s.n), symmetric=True) for s in subs]
    Ys = [cp.Variable((s.m, s.n)) for s in subs]
    X = cp.bmat([[Xs[i] if i == j else np.zeros((subs[i].n, subs[j].n)) for j in range(len(subs))]
                 for i in range(len(subs))])
    Y = cp.bmat([[Ys[i] if i == j else np.zeros((subs[i].m, subs[j].n)) for j in range(len(subs))]
                 for i in range(len(subs))])
    n, m = system.n, system.m
    AXBY = A @ X + B @ Y
    lmi = cp.bmat([
        [X, AXBY.T, (Qh @ X).T, (Rh @ Y).T],
        [AXBY, X, np.zeros((n, n)), np.zeros((n, m))],
        [Qh @ X, np.zeros((n, n)), np.eye(n), np.zeros((n, m))],
        [Rh @ Y, np.zeros((m, n)), np.zeros((m, n)), np.eye(m)],
    ])
    size = 3 * n + m
    constraints = [(lmi + lmi.T) / 2 >> 0]
    constraints += [x >> 1e-8 * np.eye(x.shape[0]) for x in Xs]
    with warnings.catch_warnings():
        # the block matrix has one subexpression per block; cvxpy's advice to vectorise is
        # about compile time only, which stays a fraction of the solve here
        warnings.filterwarnings("ignore", message=".*too many subexpressions.*")
        if objective == "logdet":
            problem = cp.Problem(cp.Maximize(sum(cp.log_det(x) for x in Xs)), constraints)
        else:
            problem = cp.Problem(cp.Minimize(0), constraints)
        try:
            problem.solve(solver=cp.CLARABEL)
        except cp.error.SolverError as exc:
            raise DesignError(f"gains (lmi): the SDP solver failed ({exc}) on a {size}x{size} LMI") from None
    if problem.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE):
        raise DesignError(f"gains (lmi): LMI (11) has no solution with block-diagonal X, Y (solver status: {problem.status})")
    Xv = [scaling[i][:, None] * Xs[i].value * scaling[i][None, :] for i in range(len(subs))]
    Yv = [Ys[i].value * scaling[i][None, :] for i in range(len(subs))]
    return Xv, Yv
