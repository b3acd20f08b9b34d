"""The terminal set X^f = {x : Omega x <= 1} and sigma(alpha) (docs/algorithm.md, "Offline design").

X^f is the maximal admissible set of x+ = A_K x under x in X and K x in U, computed with the
Gilbert-Tan recursion: rows H A_K^t are added for t = 1, 2, ... until every new row is
redundant over the current set, then redundant rows are removed. The rows are sparse (a row of
H A_K^t reaches only the subsystems t couplings away from its own), and each redundancy test
is decided by LPs on the variables near the row (:mod:`dmpc.offline.redundancy`), which give
the same answers as one LP over the whole set.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from dmpc.core.errors import DesignError
from dmpc.core.system import CoupledSystem
from dmpc.offline.redundancy import SparseRows

DENSE_SIGMA = 50_000
"""sigma uses the dense Omega up to this many entries (faster for small sets), the sparse one above."""


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

    @cached_property
    def row_norms(self) -> np.ndarray:
        """||Omega_l||_1 per row, shape (rows,)."""
        return np.abs(self.omega).sum(axis=1)

    @cached_property
    def sparse(self) -> sp.csr_matrix:
        """Omega as a sparse matrix (its rows reach a few subsystems each)."""
        return sp.csr_matrix(self.omega)

    def sigma(self, alpha: np.ndarray, scale: float = 1.0) -> float:
        """Largest theta with the cube ||x - alpha||_inf <= theta inside ``scale`` X^f.

        Parameters
        ----------
        alpha : ndarray, shape (n,)
        scale : float
            The terminal set scaled about the origin, {x : Omega x <= scale} (the terminal set around
            a setpoint target, dmpc.tracking.targets); 1 for X^f itself.
        """
        omega = self.omega if self.omega.size <= DENSE_SIGMA else self.sparse
        return float(np.min((scale - omega @ alpha) / self.row_norms))

    def contains(self, x: np.ndarray, tol: float = 1e-9) -> bool:
        """Whether x (n,) lies in X^f, up to ``tol``."""
        return bool(np.all(self.omega @ x <= 1.0 + tol))


def admissible_rows(system: CoupledSystem, K: list[np.ndarray]) -> sp.csr_matrix:
    """Constraint rows of X and K x in U of ``system`` normalised to ``G x <= 1``, sparse, shape (q, n).

    Raises DesignError if the origin is not in the interior of a constraint set.
    """
    blocks = []
    for i, s in enumerate(system.subsystems):
        parts = [_normalised(*s.input_set.one_sided(), f"input set of subsystem {s.name}", K[i])]
        if s.state_set is not None:
            parts.append(_normalised(*s.state_set.one_sided(), f"state set of subsystem {s.name}"))
        rows = np.vstack(parts)
        if rows.shape[0]:
            lead = system.state_offsets[i]
            blocks.append(sp.hstack([sp.csr_matrix((rows.shape[0], lead)), sp.csr_matrix(rows),
                                     sp.csr_matrix((rows.shape[0], system.n - lead - s.n))], format="csr"))
    if not blocks:
        raise DesignError("the terminal set is unbounded: there are no input or state constraints")
    return sp.vstack(blocks, format="csr")


def _normalised(G: np.ndarray, g: np.ndarray, what: str, K: np.ndarray | None = None) -> np.ndarray:
    """The rows G (on the input if K is given, then mapped by K) over their bounds g, zero rows dropped."""
    rows = []
    for r in range(G.shape[0]):
        if g[r] <= 0:
            raise DesignError(f"{what}: the origin is not in its interior (row {r} has bound {g[r]:.4g} <= 0)")
        row = G[r] @ K if K is not None else G[r]
        if np.any(row != 0):
            rows.append(row / g[r])
    return np.array(rows).reshape(len(rows), K.shape[1] if K is not None else G.shape[1])


def closed_loop(system: CoupledSystem, K: list[np.ndarray]) -> sp.csr_matrix:
    """A_K = A + B diag(K_i) of ``system`` with the gains K (K_i per subsystem), sparse, shape (n, n)."""
    return sp.csr_matrix(system.A) + sp.csr_matrix(system.B) @ sp.block_diag(K, format="csr")


LOCAL_ABOVE = 64
"""With more state variables than this, redundancy is decided on each row's neighbourhood by default."""


def maximal_admissible_set(system: CoupledSystem, K: list[np.ndarray], max_t: int = 500,
                           local: bool | None = None) -> TerminalSet:
    """Gilbert-Tan maximal admissible set of A + BK under the system's constraints.

    Parameters
    ----------
    system : CoupledSystem
    K : list of ndarray, shapes (m_i, n_i)
    max_t : int
        Give up (DesignError) if the recursion has not stopped after this many powers.
    local : bool, optional
        Decide each redundancy test on the variables near the row, or with one LP over the whole
        set (the plain method: the same answers, in time growing about as M^2). By default the
        first above ``LOCAL_ABOVE`` state variables, the second up to it (where it is faster).
    """
    if local is None:
        local = system.n > LOCAL_ABOVE
    AK = closed_loop(system, K)
    base = admissible_rows(system, K)
    omega = _drop_duplicates(base)
    power = base
    for t in range(1, max_t + 1):
        power = (power @ AK).tocsr()
        current = SparseRows(omega, local)
        candidates = _drop_duplicates(power)
        implied = current.implied([candidates[l] for l in range(candidates.shape[0])])
        new_rows = [l for l, redundant in enumerate(implied) if not redundant]
        if not new_rows:
            kept = SparseRows(omega, local).irredundant()
            return TerminalSet(omega=omega[kept].toarray(), t_star=t - 1)
        omega = sp.vstack([omega, candidates[new_rows]], format="csr")
    raise DesignError(f"terminal set: the Gilbert-Tan recursion did not stop within t = {max_t} "
                      f"({omega.shape[0]} rows); is A+BK stable and (A+BK, constraints) observable?")


def _drop_duplicates(rows: sp.csr_matrix) -> sp.csr_matrix:
    """The rows, each kept only at its first occurrence (compared rounded to 12 decimals)."""
    rows = sp.csr_matrix(rows)
    rows.sort_indices()
    seen, keep = set(), []
    for l in range(rows.shape[0]):
        start, end = rows.indptr[l], rows.indptr[l + 1]
        values = np.round(rows.data[start:end], 12)
        nonzero = values != 0
        key = (rows.indices[start:end][nonzero].tobytes(), (values[nonzero] + 0.0).tobytes())
        if key not in seen:
            seen.add(key)
            keep.append(l)
    return rows[keep]
