"""The terminal set X^f = {x : Omega x <= 1} and sigma(alpha) (ALGORITHM.md 2.2-2.3).

X^f is the maximal admissible set of x+ = A_K x under x in X and K x in U, computed with the
Gilbert-Tan recursion: rows H A_K^t are added for t = 1, 2, ... until every new row is
redundant over the current set (one LP per row, HiGHS), then redundant rows are removed.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dmpc.design.errors import DesignError
from dmpc.system import CoupledSystem, block_diag

REDUNDANCY_TOL = 1e-9


@dataclass(frozen=True)
class TerminalSet:
    """``X^f = {x : Omega x <= 1}`` for the global state.

    Attributes
    ----------
    omega : ndarray, shape (rows, n)
    t_star : int
        Smallest t with O_t = O_{t+1} (the rows kept come from powers 0..t_star of A_K).
    """

    omega: np.ndarray
    t_star: int

    @property
    def rows(self) -> int:
        return self.omega.shape[0]

    @property
    def row_norms(self) -> np.ndarray:
        """||Omega_l||_1 per row, shape (rows,)."""
        return np.abs(self.omega).sum(axis=1)

    def sigma(self, alpha: np.ndarray) -> float:
        """Largest theta with the cube ||x - alpha||_inf <= theta inside X^f.

        Parameters
        ----------
        alpha : ndarray, shape (n,)
        """
        return float(np.min((1.0 - self.omega @ alpha) / self.row_norms))

    def contains(self, x: np.ndarray, tol: float = 1e-9) -> bool:
        return bool(np.all(self.omega @ x <= 1.0 + tol))


def admissible_rows(system: CoupledSystem, K: list[np.ndarray]) -> np.ndarray:
    """Constraint rows of X and K x in U normalised to ``G x <= 1``, shape (q, n).

    Raises DesignError if the origin is not in the interior of a constraint set.
    """
    Kg = block_diag(*K)
    rows = []
    for i, s in enumerate(system.subsystems):
        G, g = s.input_set.one_sided()
        _append_normalised(rows, G @ Kg[system.us(i)], g, f"input set of subsystem {s.name}")
        if s.state_set is not None:
            G, g = s.state_set.one_sided()
            full = np.zeros((G.shape[0], system.n))
            full[:, system.xs(i)] = G
            _append_normalised(rows, full, g, f"state set of subsystem {s.name}")
    if not rows:
        raise DesignError("the terminal set is unbounded: there are no input or state constraints")
    return np.array(rows)


def _append_normalised(rows: list, G: np.ndarray, g: np.ndarray, what: str) -> None:
    for r in range(G.shape[0]):
        if g[r] <= 0:
            raise DesignError(f"{what}: the origin is not in its interior (row {r} has bound {g[r]:.4g} <= 0)")
        if np.any(G[r] != 0):
            rows.append(G[r] / g[r])


def maximal_admissible_set(system: CoupledSystem, K: list[np.ndarray], max_t: int = 500) -> TerminalSet:
    """Gilbert-Tan maximal admissible set of A + BK under the system's constraints.

    Parameters
    ----------
    system : CoupledSystem
    K : list of ndarray, shapes (m_i, n_i)
    max_t : int
        Give up (DesignError) if the recursion has not stopped after this many powers.
    """
    AK = system.A + system.B @ block_diag(*K)
    base = admissible_rows(system, K)
    omega = _drop_duplicates(base)
    power = base
    for t in range(1, max_t + 1):
        power = power @ AK
        new_rows = [row for row in _drop_duplicates(power) if not _is_redundant(omega, row)]
        if not new_rows:
            return TerminalSet(omega=remove_redundant_rows(omega), t_star=t - 1)
        omega = np.vstack([omega, new_rows])
    raise DesignError(f"terminal set: the Gilbert-Tan recursion did not stop within t = {max_t} "
                      f"({omega.shape[0]} rows); is A+BK stable and (A+BK, constraints) observable?")


def _drop_duplicates(rows: np.ndarray) -> np.ndarray:
    _, idx = np.unique(np.round(rows, 12), axis=0, return_index=True)
    return rows[np.sort(idx)]


def _support(omega: np.ndarray, c: np.ndarray, cap: float | None = None) -> float:
    """max c x s.t. omega x <= 1 (and c x <= cap if given); +inf if unbounded."""
    from scipy.optimize import linprog  # offline only: keeps agent processes small

    A_ub, b_ub = omega, np.ones(omega.shape[0])
    if cap is not None:
        A_ub = np.vstack([omega, c])
        b_ub = np.append(b_ub, cap)
    attempts = ({"method": "highs"}, {"method": "highs", "options": {"presolve": False}},
                {"method": "highs-ipm"}, {"method": "highs-ds", "options": {"presolve": False}})
    for kwargs in attempts:
        res = linprog(-c, A_ub=A_ub, b_ub=b_ub, bounds=(None, None), **kwargs)
        if res.status == 0:
            return float(-res.fun)
        if res.status == 3:
            return np.inf
        # status 2 (infeasible) cannot be right (0 is feasible): HiGHS mislabels unbounded
        # problems this way with presolve on, so try again without it / with another method
    return np.inf


def _is_redundant(omega: np.ndarray, row: np.ndarray) -> bool:
    return _support(omega, row) <= 1.0 + REDUNDANCY_TOL


def remove_redundant_rows(omega: np.ndarray) -> np.ndarray:
    """Drop rows implied by the others (one LP per row, capped so it stays bounded)."""
    keep = list(range(omega.shape[0]))
    for l in range(omega.shape[0]):
        others = [r for r in keep if r != l]
        if not others:
            continue
        if _support(omega[others], omega[l], cap=2.0) <= 1.0 + REDUNDANCY_TOL:
            keep = others
    return omega[keep]
