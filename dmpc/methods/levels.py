"""Levels of the ellipsoid terminal sets {x_i : x_i' P_i x_i <= r_i}
(docs/methods.md, "`ellipsoid` and `ellipsoid-adaptive`").

Static common level: the product of the ellipsoids lies in X^f = {x : Omega x <= 1} if, for
every row l, sum_i sqrt(r_i) ||Omega_{l,i}||_{P_i^-1} <= 1 (the largest value of Omega_{l,i} x_i
over the ellipsoid is sqrt(r_i) ||Omega_{l,i}||_{P_i^-1}). With one level for all:
r = min_l 1 / (sum_i ||Omega_{l,i}||_{P_i^-1})^2.

Adaptive levels (Conte et al.): r_i(k+1) = r_i(k) + eta' Gamma_i eta, where eta is the stacked
terminal state of every agent's plan and Gamma_i the part of the Lyapunov inequality (10) that
belongs to subsystem i:

    eta' Gamma_i eta = ||(A_K eta)_i||^2_{P_i} - ||eta_i||^2_{P_i} + ||eta_i||^2_{Q_i + K_i' R_i K_i}.

Gamma_i involves only the blocks of N_i (A_K is zero elsewhere). Summed over i it is the left
side of (10), so sum_i Gamma_i <= 0: the levels can move between subsystems but their sum never
grows, and each subsystem's shifted terminal state (A_K eta)_i satisfies
||(A_K eta)_i||^2_{P_i} <= r_i(k) + eta' Gamma_i eta = r_i(k+1) whenever ||eta_i||^2_{P_i} <= r_i(k).
What the increments do not give is containment: one level can grow while others shrink, and
the product can leave X^f. :func:`fit_levels` then scales every level down by one factor.
"""
from __future__ import annotations

import numpy as np

from dmpc.core.system import CoupledSystem, block_diag


def dual_norms(omega: np.ndarray, system: CoupledSystem, P: list[np.ndarray]) -> np.ndarray:
    """||Omega_{l,i}||_{P_i^-1} = sqrt(Omega_{l,i} P_i^-1 Omega_{l,i}'), shape (rows, M), of the rows of
    ``omega`` (rows, n) split by the subsystems of ``system``, with each subsystem's P_i from ``P``."""
    out = np.zeros((omega.shape[0], system.M))
    for i in range(system.M):
        W = omega[:, system.xs(i)]
        out[:, i] = np.sqrt(np.einsum("lj,jk,lk->l", W, np.linalg.inv(P[i]), W))
    return out


def static_level(omega: np.ndarray, system: CoupledSystem, P: list[np.ndarray]) -> float:
    """The common level r = min_l 1 / (sum_i ||Omega_{l,i}||_{P_i^-1})^2 (product inside X^f), from
    ``omega`` (rows, n), the subsystems of ``system`` and their P_i in ``P``."""
    return float(np.min(1.0 / dual_norms(omega, system, P).sum(axis=1) ** 2))


def containment(levels: np.ndarray, norms: np.ndarray) -> float:
    """max_l sum_i sqrt(r_i) ||Omega_{l,i}||_{P_i^-1}: the product is inside X^f iff <= 1.

    Parameters
    ----------
    levels : ndarray, shape (M,)
    norms : ndarray, shape (rows, M)
        From :func:`dual_norms`.
    """
    return float(np.max(norms @ np.sqrt(np.maximum(levels, 0.0))))


def fit_levels(levels: np.ndarray, norms: np.ndarray) -> tuple[np.ndarray, bool]:
    """The ``levels`` (M,), scaled down by one common factor if their product leaves X^f, whose rows'
    :func:`dual_norms` are ``norms`` (rows, M).

    Returns
    -------
    levels : ndarray, shape (M,)
        Non-negative.
    scaled : bool
        Whether they had to be scaled.
    """
    levels = np.maximum(levels, 0.0)
    s = containment(levels, norms)
    if s <= 1.0:
        return levels, False
    return levels / s**2, True


def level_increments(system: CoupledSystem, K: list[np.ndarray], P: list[np.ndarray]) -> list[np.ndarray]:
    """Gamma_i of the adaptive levels, each on the global state (shape (n, n), zero outside N_i).

    Parameters
    ----------
    system : CoupledSystem
    K, P : list of ndarray
        The terminal gains K_i (m_i, n_i) and weights P_i (n_i, n_i).
    """
    AK = system.A + system.B @ block_diag(*K)
    out = []
    for i, sub in enumerate(system.subsystems):
        rows = AK[system.xs(i)]
        G = rows.T @ P[i] @ rows
        block = -P[i] + sub.Q + K[i].T @ sub.R @ K[i]
        G[system.xs(i), system.xs(i)] += block
        out.append(0.5 * (G + G.T))
    return out
