"""An agent's terminal constraint lower <= T z_i(N) <= upper, from the two numbers it is released.

Every release carries a centre alpha_i (n_i,) and a size (one float). What they mean is the
method's business: the box methods read them as ||z_i(N) - alpha_i||_inf <= beta, the ellipsoid
methods as z_i(N)' P_i z_i(N) <= r_i (centre zero). The agent's QP only sees the rows T, fixed
at set-up, and the bounds, recomputed per release.
"""
from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np


class AgentTerminal(ABC):
    """The terminal rows of one agent.

    Attributes
    ----------
    T : ndarray, shape (r_f, n_i)
    """

    T: np.ndarray

    @abstractmethod
    def bounds(self, centre: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper bounds on T z(N), each shape (r_f,), for a released centre and size."""


class BoxTerminal(AgentTerminal):
    """|z(N) - alpha_i| <= beta - m_f elementwise, on the n = n_i states of the agent (m_f: ``margin``,
    the tube's terminal margin, shape (n_i,))."""

    def __init__(self, n: int, margin: np.ndarray) -> None:
        self.T = np.eye(n)
        self._margin = margin

    def bounds(self, centre: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray]:
        radius = size - self._margin
        return centre - radius, centre + radius


class InscribedTerminal(AgentTerminal):
    """T z(N) <= sqrt(r_i) h - |T| m_f: a polytope inside the ellipsoid z' P_i z <= r_i.

    With a tube, each row is tightened by its support over the error box {|e| <= m_f}, which
    contains the error set because the margins are its support in the coordinate directions.

    Parameters
    ----------
    T : ndarray, shape (p, n_i)
    h : ndarray, shape (p,)
        From :func:`dmpc.methods.inscribed.inscribed_rows`.
    margin : ndarray, shape (n_i,)
    """

    def __init__(self, T: np.ndarray, h: np.ndarray, margin: np.ndarray) -> None:
        self.T = T
        self._h = h
        self._tightening = np.abs(T) @ margin
        self._lower = np.full(h.size, -np.inf)

    def bounds(self, centre: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray]:
        return self._lower, np.sqrt(max(size, 0.0)) * self._h - self._tightening
