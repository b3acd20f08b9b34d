"""The unconstrained optimum of one agent's QP: a lower bound of its cost, without solving it.

QP_i without its inequality rows (input, state and terminal sets) is a least-squares problem in
the inputs alone once the dynamics are substituted:

    z = Phi x + Gamma v + Psi c,   J(v) = z' Qbar z + v' Rbar v,

so its optimum is s' Qbar s - g' H^-1 g with s = Phi x + Psi c, g = Gamma' Qbar s and
H = Gamma' Qbar Gamma + Rbar. Dropping constraints can only lower the optimum, so this is a
lower bound of what the solve would find: an agent that keeps a plan within a margin of it knows
what keeping may cost at most. The optimum is a quadratic form in x and c, formed once; a bound costs one small matrix product.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Condensed:
    """One agent's QP with the dynamics substituted: z = Phi x + Gamma v + Psi c over t = 0..N.

    Attributes
    ----------
    phi : ndarray, shape ((N+1) n, n)
        z(t) from x.
    gamma : ndarray, shape ((N+1) n, N m)
        z(t) from v(s), s < t.
    psi : ndarray, shape ((N+1) n, N n)
        z(t) from c(s), s < t.
    weights : ndarray, shape ((N+1) n, (N+1) n)
        Qbar = blockdiag(Q, ..., Q, P).
    weighted_gamma : ndarray, shape ((N+1) n, N m)
        Qbar Gamma.
    hessian : ndarray, shape (N m, N m)
        H = Gamma' Qbar Gamma + Rbar.
    """

    phi: np.ndarray
    gamma: np.ndarray
    psi: np.ndarray
    weights: np.ndarray
    weighted_gamma: np.ndarray
    hessian: np.ndarray


def condensed(A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray, P: np.ndarray, horizon: int) -> Condensed:
    """The :class:`Condensed` form of the QP with dynamics ``A`` (n, n), ``B`` (n, m), weights ``Q``
    (n, n), ``R`` (m, m), ``P`` (n, n) over ``horizon`` N steps."""
    n, m, N = B.shape[0], B.shape[1], horizon
    powers = [np.eye(n)]
    for _ in range(N):
        powers.append(A @ powers[-1])
    phi = np.vstack(powers)
    gamma = np.zeros(((N + 1) * n, N * m))
    psi = np.zeros(((N + 1) * n, N * n))
    for t in range(1, N + 1):
        for s in range(t):
            gamma[t * n:(t + 1) * n, s * m:(s + 1) * m] = powers[t - 1 - s] @ B
            psi[t * n:(t + 1) * n, s * n:(s + 1) * n] = powers[t - 1 - s]
    weights = np.zeros(((N + 1) * n, (N + 1) * n))
    weights[:N * n, :N * n] = np.kron(np.eye(N), Q)
    weights[N * n:, N * n:] = P
    weighted_gamma = weights @ gamma
    hessian = gamma.T @ weighted_gamma + np.kron(np.eye(N), R)
    return Condensed(phi, gamma, psi, weights, weighted_gamma, hessian)


class UnconstrainedBound:
    """min over v of sum_{t<N} z(t)'Q z(t) + v(t)'R v(t) + z(N)'P z(N) subject to
    z(0) = x, z(t+1) = A z(t) + B v(t) + c(t) only.

    Parameters
    ----------
    A : ndarray, shape (n, n)
    B : ndarray, shape (n, m)
    Q, R, P : ndarray
        Stage and terminal weights, (n, n), (m, m), (n, n).
    horizon : int
        N.
    """

    def __init__(self, A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray, P: np.ndarray,
                 horizon: int) -> None:
        n = B.shape[0]
        qp = condensed(A, B, Q, R, P, horizon)
        # the optimum is a quadratic form in w = [x; c]: s = L w, J* = s'(Qbar - Qbar Gamma H^-1 Gamma' Qbar) s
        lift = np.hstack([qp.phi, qp.psi])
        reduced = qp.weights - qp.weighted_gamma @ np.linalg.solve(qp.hessian, qp.weighted_gamma.T)
        form = lift.T @ reduced @ lift
        self._form = 0.5 * (form + form.T)
        self._n = n

    def cost(self, x: np.ndarray, coupling: np.ndarray | None) -> float:
        """The unconstrained optimum from x (n,) with the feed-forward ``coupling`` c (N, n) (None: zeros)."""
        if coupling is None:
            head = self._form[:self._n, :self._n]
            return float(x @ head @ x)
        w = np.concatenate((x, coupling.reshape(-1)))
        return float(w @ self._form @ w)
