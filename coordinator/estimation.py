"""The coordinator's estimates of the state and the disturbances (docs/algorithm.md, "Offset-free tracking").

With ``estimation`` in the scenario the controllers do not see the plant's state: each step the
plant's outputs y(k) = C x(k) (+ the scenario's measurement noise) update every subsystem's observer
(:class:`dmpc.estimation.observer.Observer`: each subsystem's own gain on its own outputs, the
coupling through its neighbours' previous estimates and inputs), and the step is released with the
estimate x^(k) in place of x(k); the disturbance estimate d^(k) moves the setpoint targets.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dmpc.core.measurement import MeasurementNoise
from dmpc.estimation.kalman import EstimatorDesign
from dmpc.estimation.observer import Observer


@dataclass(frozen=True)
class Estimate:
    """What the controllers saw of step k.

    Attributes
    ----------
    y : ndarray, shape (p,)
        The measured outputs.
    x_hat : ndarray, shape (n,)
        The state estimate x^(k|k).
    d_hat : ndarray, shape (n_d,)
        The disturbance estimate d^(k|k).
    innovation : float
        ||y - C x^(k|k-1) - C_d d^(k|k-1)||_inf, the measurement's surprise (it grows when the
        estimator diverges).
    """

    y: np.ndarray
    x_hat: np.ndarray
    d_hat: np.ndarray
    innovation: float


class Estimation:
    """Measure the plant's state and estimate, step by step.

    Parameters
    ----------
    design : EstimatorDesign
        The gains and the augmented model (C, B_d, C_d).
    noise : MeasurementNoise, optional
        Added to every measurement (deterministic in the step index).
    """

    def __init__(self, design: EstimatorDesign, noise: MeasurementNoise | None = None) -> None:
        self.design = design
        self.noise = noise
        self.observer = Observer(design)
        self._C = design.model.C

    def measure(self, k: int, x: np.ndarray) -> np.ndarray:
        """The outputs y(k) = C x(k) (+ v(k)) of step ``k`` from the plant's state ``x`` (n,), shape (p,)."""
        y = np.asarray(self._C @ x, dtype=float)
        return y + self.noise(k) if self.noise is not None else y

    def update(self, k: int, u_previous: np.ndarray | None, y: np.ndarray) -> Estimate:
        """The estimate of step ``k`` from ``u_previous``, the inputs of step k - 1 (m,) (None at
        k = 0), and the outputs ``y`` = y(k) (p,)."""
        x_hat, d_hat = self.observer.update(u_previous, y)
        return Estimate(np.array(y, dtype=float), np.array(x_hat, dtype=float), np.array(d_hat, dtype=float),
                        float(np.max(np.abs(self.observer.innovation), initial=0.0)))
