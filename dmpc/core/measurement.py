"""Measurement noise: what the plant adds to the outputs y = C x it reports (scenario field
``plant.measurement_noise``).

Gaussian, zero mean, one standard deviation per output, and deterministic: the noise of step k
is drawn from a generator seeded by (seed, k) alone, so every process that reports or replays
the measurements of a run (the plant process, ``dmpc simulate``, an outside plant) adds the same
numbers whatever the order or number of calls.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class MeasurementNoise:
    """v(k), added to the global output y(k) = C x(k): ``noise(k)`` is v(k).

    Attributes
    ----------
    std : ndarray, shape (p,)
        The standard deviation of each output's noise, in the outputs' order (>= 0; 0: that
        output is exact).
    seed : int
        The draws' seed (>= 0).
    """

    std: np.ndarray
    seed: int

    def __call__(self, k: int) -> np.ndarray:
        """The noise v(k) of step ``k``, shape (p,).

        Parameters
        ----------
        k : int
            The step index (>= 0): v(k) depends on ``seed`` and ``k`` only.
        """
        if k < 0:
            raise ValueError(f"the step index must be >= 0, got {k}")
        draws = np.random.default_rng((int(self.seed), int(k))).standard_normal(self.std.size)
        noise: np.ndarray = draws * self.std
        return noise


__all__ = ["MeasurementNoise"]
