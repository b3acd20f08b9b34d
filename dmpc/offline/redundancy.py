"""Is a row implied by the other rows of a sparse polytope? LPs on the part of it the row can see.

For P = {x : G x <= 1} and a row r, r is redundant in P when max r x over P is at most 1. When G is
sparse (the rows of a coupled system's terminal set reach a few subsystems each), a small LP over
the variables V around r's support usually gives the same answer: maximise r x over the rows
that touch V, with the variables outside V fixed at 0 (a slice of P). Its solution is a point of
P (every row that does not touch V is 0 there), so its value is a lower bound of the LP over P;
and when its dual multipliers vanish on every row that reaches outside V, they are multipliers
of the LP over P too, so the two LPs have the same optimum (to the solver's tolerances) and the
small one's value decides. A value above 1 + TOLERANCE decides in any case: the point shows that
r is not redundant. Otherwise V grows by the supports of the rows that touch it; once V holds
every variable the LP is the one over all of P.

Every LP maximises ``r x`` with the cap ``r x <= CAP`` added, which keeps it bounded and does not
change the answer. Many tests are solved as one LP: the small LPs side by side (block-diagonal),
whose solution is optimal in every block. LPs with scipy's HiGHS (dual simplex).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

CAP = 2.0
TOLERANCE = 1e-9
"""A row is redundant when its maximum over the others is at most 1 + TOLERANCE."""
MULTIPLIER = 1e-9
"""Multipliers at most this large count as zero (HiGHS's own tolerances are about 1e-7)."""
BATCH_COLUMNS = 4000
"""About this many variables per LP of side-by-side tests."""
_ATTEMPTS = ({"method": "highs-ds"}, {"method": "highs-ds", "options": {"presolve": False}},
             {"method": "highs-ipm"}, {"method": "highs"})


def _linprog(c: np.ndarray, A_ub, b_ub: np.ndarray):
    """max c x s.t. A_ub x <= b_ub (x free): (x, multipliers >= 0), or None if HiGHS cannot solve it."""
    from scipy.optimize import linprog  # offline only: keeps agent processes small

    for kwargs in _ATTEMPTS:
        res = linprog(-c, A_ub=A_ub, b_ub=b_ub, bounds=(None, None), **kwargs)
        if res.status == 0:
            return res.x, -res.ineqlin.marginals
        # x = 0 is feasible and the caps bound the objective, so any other status is HiGHS's
        # trouble (it mislabels some problems with presolve on): try the next method
    return None


def _solve_one(A: np.ndarray, c: np.ndarray):
    """(value, x, multipliers of A's rows) of max c x s.t. A x <= 1, c x <= CAP; None on failure."""
    out = _linprog(c, np.vstack([A, c]), np.append(np.ones(A.shape[0]), CAP))
    if out is None:
        return None
    x, duals = out
    return float(c @ x), x, duals[:-1]


def _solve_batch(problems: list[tuple[np.ndarray, np.ndarray]]) -> list:
    """:func:`_solve_one` of each (A, c), side by side as one LP."""
    if len(problems) == 1:
        return [_solve_one(*problems[0])]
    A_ub = sp.block_diag([np.vstack([A, c]) for A, c in problems], format="csr")
    b_ub = np.concatenate([np.append(np.ones(A.shape[0]), CAP) for A, _ in problems])
    out = _linprog(np.concatenate([c for _, c in problems]), A_ub, b_ub)
    if out is None:
        return [_solve_one(A, c) for A, c in problems]
    x, duals = out
    results, col, row = [], 0, 0
    for A, c in problems:
        xb = x[col:col + c.size]
        results.append((float(c @ xb), xb, duals[row:row + A.shape[0]]))
        col += c.size
        row += A.shape[0] + 1
    return results


def _solve(problems: list[tuple[np.ndarray, np.ndarray]]) -> list:
    results: list = []
    chunk: list = []
    size = 0
    for problem in problems:
        chunk.append(problem)
        size += problem[1].size
        if size >= BATCH_COLUMNS:
            results += _solve_batch(chunk)
            chunk, size = [], 0
    return results + (_solve_batch(chunk) if chunk else [])


def _gather(indptr: np.ndarray, indices: np.ndarray, lines: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For compressed lines (rows of CSR, columns of CSC): (which of ``lines``, position in data)."""
    lengths = indptr[lines + 1] - indptr[lines]
    ends = np.cumsum(lengths)
    total = int(ends[-1]) if ends.size else 0
    positions = np.arange(total) - np.repeat(ends - lengths, lengths) + np.repeat(indptr[lines], lengths)
    return np.repeat(np.arange(lines.size), lengths), positions


class SparseRows:
    """The rows of a polytope ``G x <= 1``, for redundancy tests.

    Parameters
    ----------
    G : sparse matrix, shape (rows, n)
    local : bool
        Decide each test on the variables around its row (the default), or always with one LP
        over the whole polytope.
    """

    def __init__(self, G, local: bool = True) -> None:
        self.G = sp.csr_matrix(G, dtype=float)
        self.G.eliminate_zeros()
        self.G.sort_indices()
        self.local = local
        self._columns = self.G.tocsc()

    @property
    def n(self) -> int:
        return self.G.shape[1]

    def _touching(self, cols: np.ndarray, active: np.ndarray) -> np.ndarray:
        """The active rows with an entry in ``cols``, ascending."""
        _, positions = _gather(self._columns.indptr, self._columns.indices, cols)
        rows = np.unique(self._columns.indices[positions])
        return rows[active[rows]]

    def _grow(self, cols: np.ndarray, active: np.ndarray) -> np.ndarray:
        """``cols`` and every variable of the active rows that touch them."""
        rows = self._touching(cols, active)
        _, positions = _gather(self.G.indptr, self.G.indices, rows)
        return np.union1d(cols, self.G.indices[positions])

    def _problem(self, r: np.ndarray, cols: np.ndarray, active: np.ndarray) -> tuple:
        """The LP of a test on the variables ``cols``: (A, c), and which of its rows reach outside them."""
        rows = self._touching(cols, active)
        which, positions = _gather(self.G.indptr, self.G.indices, rows)
        where = np.full(self.n, -1)
        where[cols] = np.arange(cols.size)
        local = where[self.G.indices[positions]]
        inside = local >= 0
        A = np.zeros((rows.size, cols.size))
        A[which[inside], local[inside]] = self.G.data[positions[inside]]
        outward = np.bincount(which[~inside], minlength=rows.size) > 0
        return (A, r[cols]), outward

    def _verdict(self, cols: np.ndarray, problem: tuple, outward: np.ndarray, result) -> float | None:
        """The test's value if its LP decides the test, else None."""
        if result is None:
            return None
        value, x, duals = result
        if cols.size == self.n or not np.any(duals[outward] > MULTIPLIER):
            return value  # the LP over all of P has the same optimum
        A, _ = problem
        if value > 1.0 + TOLERANCE:
            scale = max(1.0, float(np.max(A @ x, initial=0.0)))  # back inside P if the solver left it
            return value / scale if value / scale > 1.0 + TOLERANCE else None
        return None

    def supports(self, rows: list, active=None) -> list[float]:
        """max r x over the active rows' polytope, capped at CAP, for each r in ``rows``.

        Each value decides like the exact one whether it is at most ``1 + TOLERANCE``; it is the
        exact one when the LP had to cover every variable.

        Parameters
        ----------
        rows : list of sparse rows, each shape (1, n)
        active : ndarray of bool, shape (rows of G,), or a list of them (one per row); optional
            The rows of G that make the polytope (all by default).
        """
        if active is None:
            active = np.ones(self.G.shape[0], dtype=bool)
        actives = active if isinstance(active, list) else [active] * len(rows)
        everything = np.arange(self.n)
        tests = []
        for r, mask in zip(rows, actives):
            r = sp.csr_matrix(r)
            cols = self._grow(np.unique(r.indices), mask) if self.local else everything
            tests.append((r.toarray().ravel(), cols, mask))
        values: list[float] = [CAP] * len(tests)
        pending = list(range(len(tests)))
        while pending:
            built = [self._problem(*tests[t]) for t in pending]
            results = _solve([problem for problem, _ in built])
            undecided = []
            for t, (problem, outward), result in zip(pending, built, results):
                r, cols, mask = tests[t]
                value = self._verdict(cols, problem, outward, result)
                if value is not None:
                    values[t] = value
                    continue
                grown = self._grow(cols, mask)
                tests[t] = (r, everything if grown.size == cols.size else grown, mask)
                undecided.append(t)
            pending = undecided
        return values

    def implied(self, rows: list, active=None) -> list[bool]:
        """For each r in ``rows``: does ``r x <= 1`` hold on the polytope of the active rows?"""
        return [value <= 1.0 + TOLERANCE for value in self.supports(rows, active)]

    def irredundant(self, batch: int = 256) -> np.ndarray:
        """Indices of the rows kept when, in order, each row implied by the others still kept is
        dropped.

        Rows are tested ``batch`` at a time against the same kept rows (less the row itself);
        the answers hold up to the first row dropped, and the rows after it are tested again.
        """
        count = self.G.shape[0]
        keep = np.ones(count, dtype=bool)
        start = 0
        while start < count:
            block = list(range(start, min(count, start + batch)))
            masks = []
            for l in block:
                mask = keep.copy()
                mask[l] = False
                masks.append(mask)
            answers = self.implied([self.G[l] for l in block], masks)
            start = block[-1] + 1
            for l, implied in zip(block, answers):
                if implied and keep.sum() > 1:
                    keep[l] = False
                    start = l + 1
                    break
        return np.flatnonzero(keep)
