"""The paper's example written out by hand (docs/algorithm.md, "The paper's example, corrected"), independent of dmpc.

Nothing here imports dmpc: the tests compare the package's results with these matrices
and with the small independent computations below (LPs with scipy, explicit loops).
"""
from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
from scipy.optimize import linprog

ROOT = Path(__file__).resolve().parents[2]
SCENARIOS = ROOT / "scenarios"
PAPER = SCENARIOS / "paper.yaml"
PAPER_LMI = SCENARIOS / "paper-lmi.yaml"
CHAIN = SCENARIOS / "chain.yaml"

A_II = np.array([[1.1, 1.0], [0.0, 1.3]])
B_II = np.array([[1.0], [1.0]])
A_IJ = np.array([[0.0, 0.1], [0.2, 0.2]])
Q_I = np.eye(2)
R_I = np.array([[0.01]])
U_BAR = 2.5
K_PAPER = [np.array([[-0.6939, -1.056]]), np.array([[-0.7452, -1.113]]),
           np.array([[-0.7312, -1.084]]), np.array([[-0.7312, -1.084]])]
P_PAPER = [np.array([[4.294, 0.3814], [0.3814, 2.267]]), np.array([[8.062, 0.8835], [0.8835, 4.362]]),
           np.array([[6.306, -0.6004], [-0.6004, 3.340]]), np.array([[6.306, -0.6004], [-0.6004, 3.340]])]
X0_CYCLE = [np.array([2.794, 2.5]), np.array([2.08, 2.2]), np.array([2.194, -2.305]), np.array([-2.8, 2.5])]


def chain_matrices(M: int) -> tuple[np.ndarray, np.ndarray]:
    """Global A (2M x 2M) and B (2M x M) of a chain of M paper subsystems, B_ij = 0."""
    A = np.zeros((2 * M, 2 * M))
    B = np.zeros((2 * M, M))
    for i in range(M):
        A[2 * i:2 * i + 2, 2 * i:2 * i + 2] = A_II
        B[2 * i:2 * i + 2, i] = B_II[:, 0]
        for j in (i - 1, i + 1):
            if 0 <= j < M:
                A[2 * i:2 * i + 2, 2 * j:2 * j + 2] = A_IJ
    return A, B


def chain_x0(M: int) -> np.ndarray:
    return np.concatenate([X0_CYCLE[i % 4] for i in range(M)])


def block_diag(blocks: list[np.ndarray]) -> np.ndarray:
    rows = sum(b.shape[0] for b in blocks)
    cols = sum(b.shape[1] for b in blocks)
    out = np.zeros((rows, cols))
    r = c = 0
    for b in blocks:
        out[r:r + b.shape[0], c:c + b.shape[1]] = b
        r += b.shape[0]
        c += b.shape[1]
    return out


def lp_max(c: np.ndarray, A_ub: np.ndarray, b_ub: np.ndarray) -> float:
    """max c x s.t. A_ub x <= b_ub (x free); +inf if unbounded; fails loudly otherwise."""
    for kwargs in ({"method": "highs"}, {"method": "highs-ds", "options": {"presolve": False}},
                   {"method": "highs-ipm", "options": {"presolve": False}}):
        res = linprog(-np.asarray(c, float), A_ub=A_ub, b_ub=b_ub, bounds=(None, None), **kwargs)
        if res.status == 0:
            return float(-res.fun)
        if res.status == 3:
            return np.inf
    raise AssertionError(f"LP failed: {res.message}")


def sigma_lp(omega: np.ndarray, alpha: np.ndarray) -> float:
    """max theta s.t. Omega_l alpha + theta ||Omega_l||_1 <= 1 for every row l (an LP in theta)."""
    norms = np.abs(omega).sum(axis=1)
    # HiGHS's default feasibility tolerance (1e-7) is looser than the 1e-9 the tests compare at.
    tight = {"primal_feasibility_tolerance": 1e-10, "dual_feasibility_tolerance": 1e-10}
    res = linprog([-1.0], A_ub=norms[:, None], b_ub=1.0 - omega @ alpha, bounds=[(None, None)], method="highs",
                  options=tight)
    assert res.status == 0, res.message
    return float(res.x[0])


def cube_vertices(alpha: np.ndarray, radius: float) -> np.ndarray:
    """The 2^n vertices of {x : ||x - alpha||_inf <= radius}, shape (2^n, n)."""
    signs = np.array(list(itertools.product((-1.0, 1.0), repeat=alpha.size)))
    return alpha[None, :] + radius * signs
