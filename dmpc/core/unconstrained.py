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

import numpy as np


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
        n, m, N = B.shape[0], B.shape[1], horizon
        powers = [np.eye(n)]
        for _ in range(N):
            powers.append(A @ powers[-1])
        phi = np.vstack(powers)  # ((N+1) n, n): z(t) from x
        gamma = np.zeros(((N + 1) * n, N * m))  # z(t) from v(s), s < t
        psi = np.zeros(((N + 1) * n, N * n))  # z(t) from c(s), s < t
        for t in range(1, N + 1):
            for s in range(t):
                gamma[t * n:(t + 1) * n, s * m:(s + 1) * m] = powers[t - 1 - s] @ B
                psi[t * n:(t + 1) * n, s * n:(s + 1) * n] = powers[t - 1 - s]
        weights = np.zeros(((N + 1) * n, (N + 1) * n))  # blockdiag(Q, ..., Q, P)
        weights[:N * n, :N * n] = np.kron(np.eye(N), Q)
        weights[N * n:, N * n:] = P
        weighted_gamma = weights @ gamma  # Qbar Gamma
        H = gamma.T @ weighted_gamma + np.kron(np.eye(N), R)
        # the optimum is a quadratic form in w = [x; c]: s = L w, J* = s'(Qbar - Qbar Gamma H^-1 Gamma' Qbar) s
        lift = np.hstack([phi, psi])
        reduced = weights - weighted_gamma @ np.linalg.solve(H, weighted_gamma.T)
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
