"""Additive plant disturbances w(k): seeded random sequences, a constant step, or a given array.

Pure numerics (reading a file is done by the caller, dmpc.setup.plant). A sequence is
drawn whole before the run, so that the plant process of ``dmpc run`` and ``dmpc simulate``
apply the same w(k), and the first K rows do not depend on how many steps were drawn.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def uniform_sequence(bound: np.ndarray, steps: int, seed: int) -> np.ndarray:
    """w(k) uniform in the box ``|w| <= bound``.

    Parameters
    ----------
    bound : ndarray, shape (n,)
        Half-widths, >= 0 (0: that state is not disturbed).
    steps : int
    seed : int

    Returns
    -------
    ndarray, shape (steps, n)
    """
    bound = np.asarray(bound, dtype=float)
    draws = np.random.default_rng(seed).uniform(-1.0, 1.0, size=(steps, bound.size))
    return draws * bound


def gaussian_sequence(std: np.ndarray, steps: int, seed: int) -> np.ndarray:
    """w(k) normal with zero mean and standard deviations ``std`` (shape (n,)), drawn from ``seed``;
    shape (steps, n)."""
    std = np.asarray(std, dtype=float)
    return np.random.default_rng(seed).standard_normal(size=(steps, std.size)) * std


def step_sequence(offset: np.ndarray, start: int, steps: int) -> np.ndarray:
    """w(k) = ``offset`` for k >= ``start``, zeros before: a constant disturbance that sets in at
    step ``start``.

    Parameters
    ----------
    offset : ndarray, shape (n,)
        The constant w added to x(k+1) from step ``start`` on.
    start : int
        The first step whose update it is added to (>= 0; at or past ``steps``: zeros throughout).
    steps : int
        The number of rows.

    Returns
    -------
    ndarray, shape (steps, n)
    """
    offset = np.asarray(offset, dtype=float)
    w = np.zeros((steps, offset.size))
    w[max(start, 0):] = offset
    return w


@dataclass(frozen=True)
class DisturbanceSequence:
    """w(k) read from an array: the callable ``Plant`` takes as its disturbance.

    Attributes
    ----------
    w : ndarray, shape (steps, n)
        Row k is added to x(k+1); steps past the last row get zeros.
    """

    w: np.ndarray

    def __call__(self, k: int) -> np.ndarray:
        if 0 <= k < self.w.shape[0]:
            return self.w[k]
        return np.zeros(self.w.shape[1])

    def bound(self) -> np.ndarray:
        """The largest |w| per state over the sequence, shape (n,)."""
        return np.max(np.abs(self.w), axis=0) if self.w.shape[0] else np.zeros(self.w.shape[1])
