"""The true coupled plant x(k+1) = A x(k) + B u(k) (+ an optional disturbance)."""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from dmpc.core.system import CoupledSystem


class Plant:
    """Owns the true state and the step index.

    Parameters
    ----------
    system : CoupledSystem
    x0 : ndarray, shape (n,), optional
        Initial state (the scenario's x0 by default).
    disturbance : callable k -> ndarray (n,), optional
        Added to the state update of step k.
    """

    def __init__(self, system: CoupledSystem, x0: np.ndarray | None = None,
                 disturbance: Callable[[int], np.ndarray] | None = None) -> None:
        self.system = system
        self.x = np.array(system.x0 if x0 is None else x0, dtype=float)
        self.k = 0
        self._disturbance = disturbance

    def step(self, u: np.ndarray) -> np.ndarray:
        """Apply u(k) (shape (m,)) and return x(k+1) (shape (n,))."""
        x_next = self.system.A @ self.x + self.system.B @ u
        if self._disturbance is not None:
            x_next = x_next + self._disturbance(self.k)
        self.x = x_next
        self.k += 1
        return x_next
