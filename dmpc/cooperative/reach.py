"""Which subsystems an agent's inputs reach within the horizon.

The inputs v_i(0..N-1) of agent i move the states z(1..N) of the subsystems j reached by a path
i -> j0 -> ... -> j of one input coupling (B_{j0 i} != 0) followed by at most N - 1 state
couplings (A_{j l} != 0). Every other subsystem's predicted states are the same whatever agent i
chooses, so the cost and the constraints of those subsystems are constants of agent i's problem.
"""
from __future__ import annotations

import numpy as np

from dmpc.core.system import CoupledSystem


def structure(system: CoupledSystem) -> tuple[np.ndarray, np.ndarray]:
    """The subsystem-level structure of the coupled dynamics.

    Parameters
    ----------
    system : CoupledSystem
        Its subsystems' A_jj, B_jj and its couplings' A_jl, B_jl.

    Returns
    -------
    state, input : ndarray of bool, shape (M, M)
        ``state[j, l]``: A_jl has a nonzero entry (l = j: A_jj); ``input[j, l]``: B_jl has one.
    """
    M = system.M
    state = np.zeros((M, M), dtype=bool)
    inputs = np.zeros((M, M), dtype=bool)
    for j, sub in enumerate(system.subsystems):
        state[j, j] = bool(np.any(sub.A))
        inputs[j, j] = bool(np.any(sub.B))
    for c in system.couplings:
        state[c.target, c.source] |= bool(np.any(c.A))
        inputs[c.target, c.source] |= bool(np.any(c.B))
    return state, inputs


def input_reach(system: CoupledSystem, horizon: int) -> tuple[tuple[int, ...], ...]:
    """Per agent i, the sorted subsystems whose predicted states z(1..N) depend on v_i.

    Parameters
    ----------
    system : CoupledSystem
    horizon : int
        N >= 1.

    Returns
    -------
    tuple of tuple of int
        ``reach[i]``; it holds i itself whenever B_ii != 0. Empty for an agent without inputs.
    """
    state, inputs = structure(system)
    reach = []
    for i in range(system.M):
        reached = inputs[:, i].copy()
        frontier = reached.copy()
        for _ in range(horizon - 1):
            if not frontier.any():
                break
            nxt = state[:, frontier].any(axis=1) & ~reached
            reached |= nxt
            frontier = nxt
        reach.append(tuple(int(j) for j in np.flatnonzero(reached)))
    return tuple(reach)

