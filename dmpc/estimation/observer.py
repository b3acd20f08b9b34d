"""The estimate of the whole system's states and disturbances, step by step.

At step k, with the input u(k-1) applied since the last estimate and the measurement y(k):

    predict (the coupled model):   x^- = A x^ + B u(k-1) + B_d d^,   d^- = d^
    innovation, per subsystem i:   e_i = y_i(k) - C_i x^-_i - C_d,i d^-_i
    correct, per subsystem i:      x^_i = x^-_i + L_x,i e_i,   d^_i = d^-_i + L_d,i e_i

The prediction of subsystem i uses its own rows of A, B: its neighbours' previous estimates x^_j
and inputs u_j enter through A_ij, B_ij. The correction is agent i's own (the gain is block
diagonal: :mod:`dmpc.estimation.kalman`), so the estimate at k uses y(k) (filter form).
:func:`local_update` is agent i's share of the step, and :class:`Observer` runs every agent's.

**Start.** x^(0) is the model's x0 (the scenario's, as the controllers assume today) unless given,
and d^(0) = 0: nothing is known about the disturbance before the first measurement. The first
:meth:`Observer.update` takes ``u_prev=None`` and only corrects x^(0), d^(0) with y(0).

**Innovation.** Each update keeps its innovation e (p,): it is the filter's one signal of a model
that does not explain the measurements. It settles to zero when the loop converges under a constant
disturbance (the disturbance estimate takes up the mismatch); a norm that keeps growing means the
estimator diverges (``innovation_norm``, per subsystem ``innovation_norms``).

Numpy and scipy.sparse only (no scipy.linalg on the step's path).
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from dmpc.estimation.kalman import EstimatorDesign
from dmpc.estimation.model import as_operator


def _vector(value: ArrayLike, size: int, label: str) -> np.ndarray:
    """``value`` as a finite float vector of ``size`` entries; ValueError otherwise."""
    v = np.asarray(value, dtype=float).reshape(-1)
    if v.size != size:
        raise ValueError(f"{label} needs {size} entries, got {v.size}")
    if not np.isfinite(v).all():
        raise ValueError(f"{label} has a non-finite entry")
    return v


class Observer:
    """The estimator of the whole system: every agent's filter, run together.

    Parameters
    ----------
    design : EstimatorDesign
        From :func:`dmpc.estimation.kalman.design_estimator`.
    x0 : array_like, shape (n,), optional
        The initial state estimate x^(0); default: the model's x0.
    d0 : array_like, shape (n_d,), optional
        The initial disturbance estimate d^(0); default: zero.

    Attributes
    ----------
    design : EstimatorDesign
    model : AugmentedSystem
        ``design.model``.
    steps : int
        How many updates have been made.
    """

    def __init__(self, design: EstimatorDesign, x0: ArrayLike | None = None, d0: ArrayLike | None = None) -> None:
        model = design.model
        self.design = design
        self.model = model
        self._A = as_operator(model.system.A)
        self._B = as_operator(model.system.B)
        self._Bd = as_operator(model.Bd)
        self._C = as_operator(model.C)
        self._Cd = as_operator(model.Cd)
        self._Lx = as_operator(design.Lx)
        self._Ld = as_operator(design.Ld)
        self._x = _vector(model.system.x0 if x0 is None else x0, model.n, "x0")
        self._d = np.zeros(model.nd) if d0 is None else _vector(d0, model.nd, "d0")
        self._innovation = np.zeros(model.p)
        self.steps = 0

    @property
    def x_hat(self) -> np.ndarray:
        """The state estimate x^ (n,) (a copy)."""
        return self._x.copy()

    @property
    def d_hat(self) -> np.ndarray:
        """The disturbance estimate d^ (n_d,) (a copy)."""
        return self._d.copy()

    @property
    def innovation(self) -> np.ndarray:
        """The last update's innovation y - C x^- - C_d d^- (p,) (a copy; zeros before the first update)."""
        return self._innovation.copy()

    @property
    def innovation_norm(self) -> float:
        """The 2-norm of the last update's innovation."""
        return float(np.linalg.norm(self._innovation))

    def innovation_norms(self) -> np.ndarray:
        """The 2-norm of each subsystem's part of the last innovation, shape (M,)."""
        return np.array([np.linalg.norm(self._innovation[self.model.ys(i)]) for i in range(self.model.M)])

    def state(self, i: int) -> np.ndarray:
        """Subsystem i's state estimate x^_i (n_i,) (a copy)."""
        return self._x[self.model.system.xs(i)].copy()

    def disturbance(self, i: int) -> np.ndarray:
        """Subsystem i's disturbance estimate d^_i (n_d,i) (a copy)."""
        return self._d[self.model.ds(i)].copy()

    def output_estimate(self) -> np.ndarray:
        """The outputs the estimate explains, C x^ + C_d d^ (p,)."""
        y: np.ndarray = self._C @ self._x + self._Cd @ self._d
        return y

    def predict(self, u_prev: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """The coupled model's prediction from the current estimate (the estimate is not changed).

        Parameters
        ----------
        u_prev : array_like, shape (m,)
            The input applied since the current estimate.

        Returns
        -------
        x_minus : ndarray, shape (n,)
            A x^ + B u_prev + B_d d^.
        d_minus : ndarray, shape (n_d,)
            d^.
        """
        u = _vector(u_prev, self.model.m, "u_prev")
        x_minus: np.ndarray = self._A @ self._x + self._B @ u + self._Bd @ self._d
        return x_minus, self._d.copy()

    def update(self, u_prev: ArrayLike | None, y: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """One step of the estimator: predict with ``u_prev``, then correct every subsystem with its own part of ``y``.

        Parameters
        ----------
        u_prev : array_like, shape (m,), or None
            The input applied since the last estimate; None for the first measurement (no prediction:
            the initial estimate is corrected).
        y : array_like, shape (p,)
            The measurements of every subsystem, in subsystem order.

        Returns
        -------
        x_hat : ndarray, shape (n,)
        d_hat : ndarray, shape (n_d,)
            The new estimates (copies).

        Raises
        ------
        ValueError
            An input or measurement of the wrong size or with a non-finite entry (the estimate is unchanged).
        """
        measured = _vector(y, self.model.p, "y")
        if u_prev is None:
            x_minus, d_minus = self._x, self._d
        else:
            x_minus, d_minus = self.predict(u_prev)
        innovation: np.ndarray = measured - self._C @ x_minus - self._Cd @ d_minus
        self._x = x_minus + self._Lx @ innovation
        self._d = d_minus + self._Ld @ innovation
        self._innovation = innovation
        self.steps += 1
        return self.x_hat, self.d_hat


def local_update(design: EstimatorDesign, i: int, x_hat: np.ndarray, d_hat: np.ndarray, u_prev: np.ndarray,
                 y_i: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Agent i's share of an estimator step: its own prediction and correction.

    Parameters
    ----------
    design : EstimatorDesign
    i : int
        The subsystem (0-based).
    x_hat : ndarray, shape (n,)
        The previous state estimates; only subsystem i's and its neighbours' entries are read
        (the rows of A for subsystem i are zero elsewhere).
    d_hat : ndarray, shape (n_d,)
        The previous disturbance estimates; only subsystem i's entries are read.
    u_prev : ndarray, shape (m,)
        The inputs applied since; only those of subsystem i and of the neighbours whose B_ij is
        nonzero are read.
    y_i : ndarray, shape (p_i,)
        Subsystem i's measurements.

    Returns
    -------
    x_i : ndarray, shape (n_i,)
    d_i : ndarray, shape (n_d,i)
    innovation_i : ndarray, shape (p_i,)
        The same numbers as subsystem i's part of :meth:`Observer.update`.
    """
    model = design.model
    system, part, gain = model.system, model.parts[i], design.gains[i]
    rows, ds = system.xs(i), model.ds(i)
    x_minus = system.A[rows] @ x_hat + system.B[rows] @ u_prev + part.Bd @ d_hat[ds]
    d_minus = d_hat[ds]
    innovation: np.ndarray = np.asarray(y_i, float) - part.C @ x_minus - part.Cd @ d_minus
    return x_minus + gain.Lx @ innovation, d_minus + gain.Ld @ innovation, innovation


__all__ = ["Observer", "local_update"]
