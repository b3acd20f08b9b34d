"""Is a start x(0) feasible for the centralised problem at horizon N? One LP (scipy's HiGHS).

The distributed QPs at k = 0 together form a plan of the centralised problem with the same
horizon, constraints and terminal set; so a start that is infeasible for the centralised problem
is infeasible for the DMPC too (a necessary condition, ALGORITHM notes, "Feasibility of a start").
The constraints are all linear, so feasibility is an LP with a zero objective, which HiGHS decides
exactly (up to its tolerances), unlike a first-order QP solver's infeasibility detection.

Decision vector ``[z(1), ..., z(N), v(0), ..., v(N-1)]``; z(0) = x(0) is fixed.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from dmpc.core.system import CoupledSystem, LinearSet, stack_sets

HORIZON_CAP = 200
"""The largest horizon the search for a feasible horizon tries."""
LP_SECONDS_PER_NONZERO = 2e-4
"""HiGHS may spend max(2 s, this times the LP's nonzeros) on one LP before the next method is tried
(its dual simplex can stall on badly scaled data, such as entries of 1e-300 beside entries of 1,
where its interior point method decides in milliseconds); after every method, undecided."""
_FEASIBLE, _INFEASIBLE = 0, 2  # scipy.optimize.linprog statuses


def start_feasible(system: CoupledSystem, x0: np.ndarray, horizon: int, terminal: LinearSet) -> bool | None:
    """Whether x0 (n,) admits a plan of ``system`` of ``horizon`` steps inside U, X and the terminal set
    (``terminal``: rows on the global state z(N), dimension n).

    Returns
    -------
    True or False, or None when HiGHS cannot decide (numerical trouble with every method tried).
    """
    from scipy.optimize import linprog

    n, m, N = system.n, system.m, horizon
    A, B = sp.csr_matrix(system.A), sp.csr_matrix(system.B)
    nz, nv = N * n, N * m
    # dynamics: z(1) - B v(0) = A x0;  z(t+1) - A z(t) - B v(t) = 0
    Z = sp.eye(nz, format="csr") - sp.kron(sp.eye(N, k=-1), A, format="csr")
    A_eq = sp.hstack([Z, -sp.kron(sp.eye(N), B, format="csr")], format="csr")
    b_eq = np.zeros(nz)
    b_eq[:n] = A @ np.asarray(x0, float)
    rows, rhs = [], []
    inputs = stack_sets([s.input_set for s in system.subsystems], [s.m for s in system.subsystems], sparse=True)
    assert inputs is not None  # every subsystem has an input set
    G, g = inputs.one_sided()
    rows.append(sp.hstack([sp.csr_matrix((N * G.shape[0], nz)), sp.kron(sp.eye(N), G)]))
    rhs.append(np.tile(g, N))
    states = stack_sets([s.state_set for s in system.subsystems], [s.n for s in system.subsystems], sparse=True)
    if states is not None:
        G, g = states.one_sided()
        rows.append(sp.hstack([sp.kron(sp.eye(N), G), sp.csr_matrix((N * G.shape[0], nv))]))
        rhs.append(np.tile(g, N))
    G, g = LinearSet(sp.csr_matrix(terminal.H), terminal.lower, terminal.upper).one_sided()
    last = sp.hstack([sp.csr_matrix((n, (N - 1) * n)), sp.eye(n)])
    rows.append(sp.hstack([G @ last, sp.csr_matrix((G.shape[0], nv))]))
    rhs.append(g)
    A_ub = sp.vstack(rows, format="csr")
    b_ub = np.concatenate(rhs)
    limit = max(2.0, LP_SECONDS_PER_NONZERO * (A_ub.nnz + A_eq.nnz))
    for method in ("highs", "highs-ipm", "highs-ds"):
        res = linprog(np.zeros(nz + nv), A_ub=A_ub, b_ub=b_ub, A_eq=A_eq, b_eq=b_eq, bounds=(None, None),
                      method=method, options={"time_limit": limit})
        if res.status == _FEASIBLE:
            return True
        if res.status == _INFEASIBLE:
            return False
    return None


def smallest_feasible_horizon(feasible, cap: int = HORIZON_CAP) -> int | None:
    """The smallest N in [1, cap] with ``feasible(N)`` true, or None.

    Doubles N (1, 2, 4, ..., then ``cap``) until ``feasible(N)``, then scans the last interval
    upwards: about 2 log2(cap) tests where a full scan takes ``cap``, which matters when none is
    feasible. It assumes that a start feasible at N stays feasible at longer horizons, which holds
    when the terminal set is invariant (X^f) and, for the terminal boxes, in every case we tried; the
    scan of the last interval still finds the smallest N there exactly.
    """
    low, N = 0, 1
    while True:
        if feasible(N):
            break
        if N >= cap:
            return None
        low, N = N, min(2 * N, cap)
    for candidate in range(low + 1, N):
        if feasible(candidate):
            return candidate
    return N
