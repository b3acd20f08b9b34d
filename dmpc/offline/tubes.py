"""Constraint tightening by the error tube E_i(t) (docs/algorithm.md, "Offline design", tubes E_i).

E_i(t) is the reachable set of e+ = Gamma_i e + w, w in W_i, e(0) = 0, with
Gamma_i = A_ii + B_ii K_i. Only support functions are needed:

    h_E(t)(d) = sum_{s<t} h_W((Gamma_i^s)^T d),
    h_W(d)    = sum_{j != i} xbar_j^T |A_ij^T d| + ubar_j^T |B_ij^T d|,

where (xbar_j, ubar_j) bound neighbour j's plan revisions. An additive disturbance on the
plant, |w_i| <= wbar_i, adds wbar_i^T |d| to h_W. With ``tube: none`` E_i = {0}.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dmpc.core.errors import DesignError
from dmpc.core.system import CoupledSystem


@dataclass(frozen=True)
class Tightening:
    """Per-step constraint margins of one subsystem for a horizon N.

    Attributes
    ----------
    input_margin : ndarray, shape (N, r_u)
        Subtracted from both sides of each input row ``H_u v`` (from ``upper``, added to ``lower``).
    state_margin : ndarray, shape (N + 1, r_x)
        The same for state rows ``H_x z``.
    terminal_margin : ndarray, shape (n_i,)
        Subtracted from the terminal box radius beta, per coordinate.
    """

    input_margin: np.ndarray
    state_margin: np.ndarray
    terminal_margin: np.ndarray

    @classmethod
    def none(cls, n: int, r_u: int, r_x: int, N: int) -> "Tightening":
        """No tightening: zeros for r_u input rows (N steps), r_x state rows (N + 1) and n terminal margins."""
        return cls(np.zeros((N, r_u)), np.zeros((N + 1, r_x)), np.zeros(n))


@dataclass(frozen=True)
class RevisionBound:
    """Bounds on a subsystem's plan revisions: |dz| <= state, |dv| <= input (elementwise)."""

    state: np.ndarray
    input: np.ndarray


def disturbance_support(system: CoupledSystem, i: int, bounds: dict[int, RevisionBound],
                        additive: np.ndarray | None = None):
    """Return h_W for subsystem i of ``system`` as a function of a direction d of shape (n_i,), from
    the neighbours' revision ``bounds`` (per subsystem index).

    ``additive`` (shape (n_i,)) bounds an additive disturbance |w_i| <= additive on the plant.
    """
    terms = []
    for j in system.neighbours[i]:
        if j == i:
            continue
        Aij, Bij = system.coupling(i, j)
        if not (np.any(Aij) or np.any(Bij)):
            continue
        if j not in bounds:
            raise DesignError(f"tube: robust needs revision_bound on subsystem {system.subsystems[j].name} "
                              f"(it couples into subsystem {system.subsystems[i].name})")
        terms.append((Aij, Bij, bounds[j].state, bounds[j].input))

    wbar = None if additive is None else np.asarray(additive, float)

    def h_W(d: np.ndarray) -> float:
        coupled = sum(xb @ np.abs(A.T @ d) + ub @ np.abs(B.T @ d) for A, B, xb, ub in terms)
        return float(coupled + (0.0 if wbar is None else wbar @ np.abs(d)))

    return h_W


def robust_tightening(system: CoupledSystem, i: int, K_i: np.ndarray, N: int,
                      bounds: dict[int, RevisionBound], additive: np.ndarray | None = None) -> Tightening:
    """Support-function tightening of subsystem i's constraints over the horizon N, for the
    subsystem of ``system`` with gain K_i (m_i, n_i) and the neighbours' revision ``bounds``.

    ``additive`` (shape (n_i,)): the bound of an additive plant disturbance on subsystem i.
    Raises DesignError naming the set and step if a tightened set is empty.
    """
    s = system.subsystems[i]
    h_W = disturbance_support(system, i, bounds, additive)
    Gamma = s.A + s.B @ K_i
    powers = [np.eye(s.n)]
    for _ in range(N):
        powers.append(Gamma @ powers[-1])

    def h_E(t: int, d: np.ndarray) -> float:
        return sum(h_W(powers[q].T @ d) for q in range(t))

    Hu = s.input_set.H
    input_margin = np.array([[h_E(t, (Hu[r] @ K_i)) for r in range(Hu.shape[0])] for t in range(N)])
    if s.state_set is not None:
        Hx = s.state_set.H
        state_margin = np.array([[h_E(t, Hx[r]) for r in range(Hx.shape[0])] for t in range(N + 1)])
    else:
        state_margin = np.zeros((N + 1, 0))
    terminal_margin = np.array([h_E(N, e) for e in np.eye(s.n)])
    tight = Tightening(input_margin, state_margin, terminal_margin)
    _check_nonempty(s.input_set, tight.input_margin, f"input set U_{s.name}")
    if s.state_set is not None:
        _check_nonempty(s.state_set, tight.state_margin[1:], f"state set X_{s.name}", first_step=1)
    return tight


def _check_nonempty(linear_set, margins: np.ndarray, what: str, first_step: int = 0) -> None:
    H, lo, hi = linear_set.H, linear_set.lower, linear_set.upper
    for t, m in enumerate(margins):
        upper, lower = hi - m, lo + m
        if np.any(lower > upper) or not _feasible(H, lower, upper):
            step = t + first_step
            worst = float(np.max(m))
            raise DesignError(
                f"tube: robust: the tightened {what} is empty at t = {step} (margin up to {worst:.4g} "
                f"against bounds {np.array2string(hi, precision=4)}): the revision bounds are too large "
                "for these constraints. Treating the neighbours' whole constraint sets as the "
                "disturbance (the paper's W_i) is known to empty the sets; bound the plan revisions instead"
            )


def _feasible(H: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> bool:
    from scipy.optimize import linprog  # offline only: keeps agent processes small

    finite_hi, finite_lo = np.isfinite(upper), np.isfinite(lower)
    A_ub = np.vstack([H[finite_hi], -H[finite_lo]])
    b_ub = np.concatenate([upper[finite_hi], -lower[finite_lo]])
    if A_ub.shape[0] == 0:
        return True
    res = linprog(np.zeros(H.shape[1]), A_ub=A_ub, b_ub=b_ub, bounds=(None, None), method="highs")
    return res.status == 0
