"""The coordinator's estimates of the state and the disturbances (docs/algorithm.md, "Offset-free tracking").

With ``estimation`` in the scenario the controllers do not see the plant's state: each step the
plant's outputs y(k) = C x(k) (+ the scenario's measurement noise) update every subsystem's observer
(:class:`dmpc.estimation.observer.Observer`: each subsystem's own gain on its own outputs, the
coupling through its neighbours' previous estimates and inputs), and the step is released with the
estimate x^(k) in place of x(k); the disturbance estimate d^(k) moves the setpoint targets.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

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
        # block diagonal: sparse, so that y = C x costs what the measured rows cost (3 us, not 0.4 ms, at
        # M = 1024); each row sums its own nonzero entries, as C_i x_i does
        self._C = sp.csr_matrix(design.model.C)

    def measure(self, k: int, x: np.ndarray, outputs: Mapping[str, np.ndarray] | None = None) -> np.ndarray:
        """The outputs y(k) = C x(k) (+ v(k)) of step ``k`` from the plant's state ``x`` (n,), shape (p,).

        ``outputs``: the outputs y_i (p_i,) a plant outside measured itself, by subsystem name, in
        place of those subsystems' states (NaN in ``x``): taken as they are.
        """
        if not outputs:
            y = np.asarray(self._C @ x, dtype=float)
            return y + self.noise(k) if self.noise is not None else y
        y = np.asarray(self._C @ np.where(np.isnan(x), 0.0, x), dtype=float)
        if self.noise is not None:
            y = y + self.noise(k)
        model = self.design.model
        for i, part in enumerate(model.parts):
            if part.name in outputs:
                y[model.ys(i)] = outputs[part.name]
        return y

    def recorded(self, x: np.ndarray, estimate: Estimate) -> np.ndarray:
        """The state (n,) recorded of a step whose plant reported some subsystems' outputs, not their
        states (NaN in ``x``): there, the ``estimate`` x^_i moved by the least change that makes its
        outputs the measured ones, x^_i + pinv(C_i) (y_i - C_i x^_i), so that the records' outputs
        C_i x_i are what the plant measured; elsewhere ``x`` as it is."""
        missing = np.isnan(x)
        if not missing.any():
            return x
        out = np.array(x, dtype=float)
        model, system = self.design.model, self.design.model.system
        for i, part in enumerate(model.parts):
            xs = system.xs(i)
            if not missing[xs].any():
                continue
            x_hat = estimate.x_hat[xs]
            out[xs] = x_hat + np.linalg.pinv(part.C) @ (estimate.y[model.ys(i)] - part.C @ x_hat)
        return out

    def update(self, k: int, u_previous: np.ndarray | None, y: np.ndarray) -> Estimate:
        """The estimate of step ``k`` from ``u_previous``, the inputs of step k - 1 (m,) (None at
        k = 0), and the outputs ``y`` = y(k) (p,)."""
        x_hat, d_hat = self.observer.update(u_previous, y)
        return Estimate(np.array(y, dtype=float), np.array(x_hat, dtype=float), np.array(d_hat, dtype=float),
                        float(np.max(np.abs(self.observer.innovation), initial=0.0)))
