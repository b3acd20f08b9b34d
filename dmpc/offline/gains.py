"""Block-diagonal terminal gains K = diag(K_i) and weights P = diag(P_i)
(docs/algorithm.md, "Offline design").

The requirement on the *global* coupled system is eq. (10):

    (A+BK)^T P (A+BK) - P <= -(Q + K^T R K).

Three ways to get them: ``lmi`` (eq. (11) with block-diagonal X = P^-1, Y = K X, maximising
log det X), ``lqr`` (per-subsystem DARE, then verified) and ``given`` (from the scenario,
verified). Every result is verified the same way, by ``verify_gains``.

The check value of (10) is its largest eigenvalue; it passes up to a tolerance of
1e-6 lambda_max(P), because a log-det optimum sits on the boundary of (10). A value within
one tolerance of zero passes only within the solver's accuracy, so the LMI is imposed with a
small strictness margin (Q + s I in place of Q), which puts the check value near -s instead,
and a design whose value still lies above -tolerance is flagged as thin.
"""
from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass

import numpy as np

from dmpc.core.errors import DesignError, DmpcError
from dmpc.core.system import CoupledSystem, Coupling, block_diag
from dmpc.offline.stabilisable import check_stabilisable

log = logging.getLogger("dmpc.offline")

LMI_OBJECTIVE = "maximise log det X (X = P^-1, block diagonal): the largest terminal ellipsoid"

# first strictness margin s, relative to lambda_max(Q): the check value of (10) lands near -s
LMI_STRICTNESS = 1e-4
# if that is still thin, the LMI is solved again with s = this many tolerances of the first result
LMI_RESOLVE_TOLERANCES = 10.0
# Clarabel's own defaults are 1e-8
CLARABEL_SETTINGS = dict(tol_gap_abs=1e-9, tol_gap_rel=1e-9, tol_feas=1e-9)
# at most this many coupled pairs are tried on their own to explain an infeasible LMI
MAX_PAIRS_TRIED = 40


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
        1e-6 * lambda_max(P): a log-det optimum of (11) sits on the boundary of (10), so the
        check value is judged against a tolerance relative to P, not against 0.
    objective : str
        What the design optimised (empty for ``given``).
    margin_thin : bool
        True when (10) holds by less than one tolerance below zero
        (``lyapunov_margin > -lyapunov_tolerance``): another solver release or platform could
        move the check value past its limit and reject the same gains.
    margin_note : str
        Why the margin is thin, in words (empty when it is not).
    """

    K: list[np.ndarray]
    P: list[np.ndarray]
    method: str
    rho: float
    lyapunov_margin: float
    lyapunov_tolerance: float
    objective: str = ""
    margin_thin: bool = False
    margin_note: str = ""

    def K_global(self) -> np.ndarray:
        return block_diag(*self.K)

    def P_global(self) -> np.ndarray:
        return block_diag(*self.P)


@dataclass(frozen=True)
class LyapunovFigures:
    """The figures of (10) for given gains.

    Attributes
    ----------
    rho : float
        Spectral radius of A + BK.
    margin : float
        Largest eigenvalue of (A+BK)'P(A+BK) - P + Q + K'RK.
    tolerance : float
        1e-6 lambda_max(P).
    p_min : float
        Smallest eigenvalue of P.
    """

    rho: float
    margin: float
    tolerance: float
    p_min: float

    @property
    def thin(self) -> bool:
        return self.margin > -self.tolerance


DENSE_EIGENVALUES = 600
"""Up to this size the spectral radius comes from all eigenvalues; above it from ARPACK."""


def spectral_radius(M: np.ndarray) -> float:
    """max |eigenvalue| of the square matrix M.

    Above ``DENSE_EIGENVALUES`` rows, the 20 largest-magnitude eigenvalues are found by ARPACK on
    the sparse matrix (coupled systems are sparse; asking for one alone can settle on another
    member of a cluster of nearly equal moduli), from a fixed start vector so that every process
    computing it gets the same figure.
    """
    if M.shape[0] <= DENSE_EIGENVALUES:
        return float(np.max(np.abs(np.linalg.eigvals(M))))
    import scipy.sparse as sp
    from scipy.sparse.linalg import eigs

    values = eigs(sp.csr_matrix(M), k=min(20, M.shape[0] - 2), which="LM", v0=np.ones(M.shape[0]), tol=0.0,
                  return_eigenvectors=False)
    return float(np.max(np.abs(values)))


def lyapunov_figures(system: CoupledSystem, K: list[np.ndarray], P: list[np.ndarray]) -> LyapunovFigures:
    """rho(A+BK) and the check value of (10) with its tolerance, on ``system``; K (m_i, n_i) and
    P (n_i, n_i) per subsystem."""
    Kg = block_diag(*K)
    Pg = block_diag(*P)
    AK = system.A + system.B @ Kg
    rho = spectral_radius(AK)
    lhs = AK.T @ Pg @ AK - Pg + system.Q + Kg.T @ system.R @ Kg
    margin = float(np.max(np.linalg.eigvalsh((lhs + lhs.T) / 2)))
    p_eigs = np.linalg.eigvalsh((Pg + Pg.T) / 2)
    return LyapunovFigures(rho=rho, margin=margin, tolerance=1e-6 * float(np.max(np.abs(p_eigs))),
                           p_min=float(np.min(p_eigs)))


def verify_gains(system: CoupledSystem, K: list[np.ndarray], P: list[np.ndarray], method: str,
                 objective: str = "", remark: str = "") -> GainDesign:
    """Check stability and (10) for the coupled system; raise DesignError with figures if not.

    Parameters
    ----------
    system : CoupledSystem
    K : list of ndarray, shapes (m_i, n_i)
    P : list of ndarray, shapes (n_i, n_i)
    method, objective : str
        Recorded in the result.
    remark : str
        How the gains were computed, added to the explanation of a thin margin.
    """
    f = lyapunov_figures(system, K, P)
    rho, margin, tolerance = f.rho, f.margin, f.tolerance
    if rho >= 1.0:
        worst = _worst_block(system, K)
        raise DesignError(
            f"gains ({method}) give an unstable closed loop: spectral radius of A+BK is {rho:.4g} >= 1"
            + worst
        )
    if f.p_min <= 0:
        raise DesignError(f"gains ({method}): P is not positive definite (smallest eigenvalue {f.p_min:.3g})")
    if margin > tolerance:
        raise DesignError(
            f"gains ({method}) violate the Lyapunov decrease (10) for the coupled system: largest "
            f"eigenvalue of (A+BK)'P(A+BK) - P + Q + K'RK is {margin:.4g} > {tolerance:.2g} "
            f"(rho(A+BK) = {rho:.4g})"
        )
    return GainDesign(K=[np.asarray(k, float) for k in K], P=[np.asarray(p, float) for p in P],
                      method=method, rho=rho, lyapunov_margin=margin, lyapunov_tolerance=tolerance,
                      objective=objective, margin_thin=f.thin, margin_note=_thin_note(f, remark) if f.thin else "")


def _thin_note(f: LyapunovFigures, remark: str) -> str:
    """Words on a thin margin of (10)."""
    note = (f"the check value of (10), {f.margin:.3g}, is less than one tolerance ({f.tolerance:.2g}) below zero: "
            f"it passes by {f.tolerance - f.margin:.2g}, about the accuracy of the SDP solver, so another solver "
            "release or platform may reject these gains")
    return f"{note} ({remark})" if remark else note


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

    check_stabilisable(system, "lqr")
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
    """Solve LMI (11) of ``system`` with block-diagonal X and Y, maximising log det X.

    Each (A_ii, B_ii) is checked for stabilisability first. The LMI is imposed with Q + s I in
    place of Q, s = LMI_STRICTNESS lambda_max(Q); if the check value of (10) is still within one
    tolerance of zero, once more with s = LMI_RESOLVE_TOLERANCES tolerances. Warnings of the
    solver go to the ``dmpc.offline`` logger.
    """
    check_stabilisable(system, "lmi")
    q_scale = float(np.max(np.linalg.eigvalsh(system.Q))) or 1.0
    best = _lmi_candidate(system, LMI_STRICTNESS * q_scale)
    if best.figures.thin:
        shift = LMI_RESOLVE_TOLERANCES * best.figures.tolerance
        log.info("LMI (11): check value %.3g within one tolerance %.2g of zero; solving again with Q + %.2g I",
                 best.figures.margin, best.figures.tolerance, shift)
        try:
            best = _better(best, _lmi_candidate(system, shift))
        except DesignError as exc:
            log.info("LMI (11) with Q + %.2g I: %s", shift, exc)
    return verify_gains(system, best.K, best.P, "lmi", LMI_OBJECTIVE, best.remark)


@dataclass(frozen=True)
class _Candidate:
    """Gains from one LMI solve: K_i (m_i, n_i), P_i (n_i, n_i), their figures and how they were found."""

    K: list[np.ndarray]
    P: list[np.ndarray]
    figures: LyapunovFigures
    remark: str

    @property
    def room(self) -> float:
        """How far (10) passes, in tolerances (-inf if the gains are unusable)."""
        f = self.figures
        if f.rho >= 1.0 or f.p_min <= 0:
            return -np.inf
        return (f.tolerance - f.margin) / f.tolerance


def _better(a: _Candidate, b: _Candidate) -> _Candidate:
    return b if b.room > a.room else a


def _lmi_candidate(system: CoupledSystem, shift: float) -> _Candidate:
    """Gains from LMI (11) with Q + shift I in place of Q.

    Clarabel with chordal decomposition handles the sparse block structure. If the direct
    solve fails numerically or ends inaccurate (badly scaled systems), a feasibility solve gives
    a per-subsystem state scaling, the log-det problem is solved in scaled coordinates and
    mapped back: log det X changes by a constant under the scaling, so the optimum is the same.
    Of two solutions the one with more room in (10) is kept.
    """
    try:
        sol = _solve_lmi(system, scaling=None, objective="logdet", shift=shift)
    except _LmiFailure as direct:
        _raise_if_infeasible(system)
        return _candidate(system, _solve_rescaled(system, shift, direct.detail), shift)
    first = _candidate(system, sol, shift)
    if not sol.inaccurate:
        return first
    try:
        return _better(first, _candidate(system, _solve_rescaled(system, shift, "inaccurate"), shift))
    except DesignError:
        return first


def _candidate(system: CoupledSystem, sol: "_LmiSolution", shift: float) -> _Candidate:
    K = [sol.Y[i] @ np.linalg.inv(sol.X[i]) for i in range(system.M)]
    P = [np.linalg.inv(sol.X[i]) for i in range(system.M)]
    P = [(p + p.T) / 2 for p in P]
    remark = f"LMI imposed with Q + {shift:.2g} I"
    if sol.inaccurate:
        remark += "; the SDP solver reported its solution as inaccurate"
    return _Candidate(K, P, lyapunov_figures(system, K, P), remark)


def _solve_rescaled(system: CoupledSystem, shift: float, direct: str) -> "_LmiSolution":
    """The log-det solve in the coordinates a feasibility solve suggests (``direct``: how the direct solve ended)."""
    try:
        feasible = _solve_lmi(system, scaling=None, objective="feasibility", shift=shift)
    except _LmiFailure as exc:
        _raise_if_infeasible(system)
        raise DesignError(
            f"gains (lmi): the SDP solver could not decide LMI (11), the Lyapunov decrease (10) with block-diagonal "
            f"X = P^-1 and Y = K X on the {exc.size}x{exc.size} LMI ({direct}; feasibility solve: {exc.detail}); "
            "the system may be badly scaled (rescale its states) or nearly not stabilisable by block-diagonal gains"
        ) from None
    scaling = [np.sqrt(np.clip(np.diag(x), 1e-12, None)) for x in feasible.X]
    try:
        return _solve_lmi(system, scaling=scaling, objective="logdet", shift=shift)
    except _LmiFailure as exc:
        raise DesignError(
            f"gains (lmi): LMI (11) is feasible (block-diagonal gains meeting (10) exist), but maximising log det X "
            f"over it failed numerically on the {exc.size}x{exc.size} LMI ({direct}; in rescaled coordinates: "
            f"{exc.detail}); rescale the system's states, or use design.gains: lqr or given"
        ) from None


class _LmiFailure(DmpcError):
    """An SDP solve that gave no usable X, Y (``detail``: how it ended) on a ``size`` x ``size`` LMI."""

    def __init__(self, detail: str, size: int) -> None:
        super().__init__(detail)
        self.detail = detail
        self.size = size


@dataclass(frozen=True)
class _LmiSolution:
    """X_i (n_i, n_i) and Y_i (m_i, n_i) in original coordinates; ``inaccurate`` as the solver said."""

    X: list[np.ndarray]
    Y: list[np.ndarray]
    inaccurate: bool


def _solve_lmi(system: CoupledSystem, scaling: list[np.ndarray] | None, objective: str,
               shift: float = 0.0) -> _LmiSolution:
    """Solve LMI (11) with Q + shift I in place of Q; _LmiFailure if there is no usable solution.

    Parameters
    ----------
    system : CoupledSystem
    scaling : list of ndarray, shapes (n_i,), or None
        Per-subsystem state scaling d_i: the LMI is solved for x = D x~, D = diag(d_i).
    objective : {"logdet", "feasibility"}
    shift : float
        Strictness margin s >= 0: (10) is imposed as (A+BK)'P(A+BK) - P <= -(Q + sI + K'RK).
    """
    from dmpc.offline.lmi_conic import solve_lmi  # start-up time: cvxpy only for the LMI design

    subs = system.subsystems
    if scaling is None:
        scaling = [np.ones(s.n) for s in subs]
    size = 3 * system.n + system.m
    # built block by block for Clarabel (dmpc.offline.lmi_conic): the same problem as _lmi_problem
    # gives to cvxpy, without compiling dense expressions, so that it scales with the couplings
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sol = solve_lmi(system, scaling, objective, shift, CLARABEL_SETTINGS)
    for w in caught:
        log.info("LMI (11), %s solve: %s: %s", objective, w.category.__name__, w.message)
    if sol.status == "solver_error":
        raise _LmiFailure("Clarabel stopped without a solution", size)
    X, Y = sol.X, sol.Y
    if sol.status not in ("optimal", "optimal_inaccurate") or X is None or Y is None:  # None exactly then
        raise _LmiFailure(f"solver status {sol.status}", size)
    Xv = [scaling[i][:, None] * X[i] * scaling[i][None, :] for i in range(len(subs))]
    Yv = [Y[i] * scaling[i][None, :] for i in range(len(subs))]
    return _LmiSolution(Xv, Yv, sol.status == "optimal_inaccurate")


def _solve_quietly(problem, stage: str, **settings) -> bool:
    """Solve with Clarabel, sending its and cvxpy's warnings to the ``dmpc.offline`` logger.

    Returns False if the solver stopped without a solution (cvxpy's SolverError).
    """
    import cvxpy as cp

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        # the block matrix has one subexpression per block; cvxpy's advice to vectorise is
        # about compile time only, which stays a fraction of the solve here
        warnings.filterwarnings("ignore", message=".*too many subexpressions.*")
        try:
            problem.solve(solver=cp.CLARABEL, **settings)
            solved = True
        except cp.error.SolverError:
            solved = False
    for w in caught:
        log.info("%s: %s: %s", stage, w.category.__name__, w.message)
    return solved


def _block_variables(system: CoupledSystem):
    """Variables X_i (n_i, n_i) symmetric and Y_i (m_i, n_i), and X = diag(X_i), Y = diag(Y_i)."""
    import cvxpy as cp

    subs = system.subsystems
    Xs = [cp.Variable((s.n, s.n), symmetric=True) for s in subs]
    Ys = [cp.Variable((s.m, s.n)) for s in subs]
    X = cp.bmat([[Xs[i] if i == j else np.zeros((subs[i].n, subs[j].n)) for j in range(len(subs))]
                 for i in range(len(subs))])
    Y = cp.bmat([[Ys[i] if i == j else np.zeros((subs[i].m, subs[j].n)) for j in range(len(subs))]
                 for i in range(len(subs))])
    return Xs, Ys, X, Y


def _lmi_problem(system: CoupledSystem, scaling: list[np.ndarray], objective: str, shift: float):
    """The cvxpy problem of LMI (11) in scaled coordinates, with its X_i and Y_i variables."""
    import cvxpy as cp
    from scipy.linalg import sqrtm

    D = block_diag(*[np.diag(d) for d in scaling])
    Dinv = np.linalg.inv(D)
    # x = D x~  =>  A~ = D^-1 A D, B~ = D^-1 B, Q~ = D Q D, R unchanged
    A = Dinv @ system.A @ D
    B = Dinv @ system.B
    Qh = sqrtm(D @ (system.Q + shift * np.eye(system.n)) @ D).real
    Rh = sqrtm(system.R).real
    Xs, Ys, X, Y = _block_variables(system)
    n, m = system.n, system.m
    AXBY = A @ X + B @ Y
    lmi = cp.bmat([
        [X, AXBY.T, (Qh @ X).T, (Rh @ Y).T],
        [AXBY, X, np.zeros((n, n)), np.zeros((n, m))],
        [Qh @ X, np.zeros((n, n)), np.eye(n), np.zeros((n, m))],
        [Rh @ Y, np.zeros((m, n)), np.zeros((m, n)), np.eye(m)],
    ])
    constraints = [(lmi + lmi.T) / 2 >> 0]
    constraints += [x >> 1e-8 * np.eye(x.shape[0]) for x in Xs]
    if objective == "logdet":
        problem = cp.Problem(cp.Maximize(sum(cp.log_det(x) for x in Xs)), constraints)
    else:
        problem = cp.Problem(cp.Minimize(0), constraints)
    return problem, Xs, Ys


def _raise_if_infeasible(system: CoupledSystem) -> None:
    """DesignError naming the condition and the coupled pairs at fault if (10) cannot be met."""
    if _lyapunov_feasible(system) is False:
        raise DesignError(_infeasible_message(system))


def _lyapunov_feasible(system: CoupledSystem) -> bool | None:
    """Whether block-diagonal K = diag(K_i), P = diag(P_i) > 0 with (A+BK)'P(A+BK) < P exist.

    This decides (11): with such gains, t P meets (10) for t large enough. The LMI is
    homogeneous, so it is posed with margins of 1, X >= I and [[X, (AX+BY)'], [AX+BY, X]] >= I,
    where (11) itself is only bounded away from X = 0 by its 1e-8 I and solvers call a nearly
    feasible instance inaccurate. None when the solver decides nothing.
    """
    import cvxpy as cp

    Xs, _, X, Y = _block_variables(system)
    AXBY = system.A @ X + system.B @ Y
    lyap = cp.bmat([[X, AXBY.T], [AXBY, X]])
    constraints = [(lyap + lyap.T) / 2 >> np.eye(2 * system.n)] + [x >> np.eye(x.shape[0]) for x in Xs]
    problem = cp.Problem(cp.Minimize(0), constraints)
    if not _solve_quietly(problem, "Lyapunov feasibility solve"):
        return None
    if problem.status in (cp.INFEASIBLE, cp.INFEASIBLE_INACCURATE):
        return False
    return True if problem.status in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) else None


def _infeasible_message(system: CoupledSystem) -> str:
    """Why LMI (11) is infeasible: the condition, and the coupled pairs that already fail alone."""
    head = ("gains (lmi): LMI (11) is infeasible: no block-diagonal K = diag(K_i) and P = diag(P_i) > 0 meet the "
            "Lyapunov decrease (10) on the coupled system, although each (A_ii, B_ii) is stabilisable on its own")
    pairs = sorted({tuple(sorted((c.target, c.source))) for c in system.couplings})
    failing = [(i, j) for i, j in pairs[:MAX_PAIRS_TRIED] if _lyapunov_feasible(_pair(system, i, j)) is False]
    names = [f"{system.subsystems[i].name}-{system.subsystems[j].name}" for i, j in failing]
    if names:
        return (f"{head}; the coupling of subsystems {', '.join(names)} alone is already too strong for "
                "block-diagonal gains (weaken A_ij / B_ij there, or use a centralised design)")
    tried = "every coupled pair" if len(pairs) <= MAX_PAIRS_TRIED else f"the first {MAX_PAIRS_TRIED} coupled pairs"
    return (f"{head}; {tried} meets it alone, so it is the couplings of the network together that are too "
            "strong for block-diagonal gains")


def _pair(system: CoupledSystem, i: int, j: int) -> CoupledSystem:
    """Subsystems i and j alone, with their mutual couplings."""
    local = {i: 0, j: 1}
    couplings = tuple(Coupling(local[c.target], local[c.source], c.A, c.B) for c in system.couplings
                      if {c.target, c.source} == {i, j})
    return CoupledSystem((system.subsystems[i], system.subsystems[j]), couplings)
