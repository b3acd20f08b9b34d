"""The reference governor: how far the applied target may move toward the requested one in one step.

At the end of step k the agents' plans end at eta (n,). Each agent's candidate for step k+1 (its
plan shifted, with the terminal controller around the target as its last input) is feasible for
QP_i around the target x_s, u_s of step k+1, with d = eta - x_s, when

    (a) u_s + K d lies in U                (the candidate's last input), and
    (b) sigma_lambda(alpha) >= 0 with alpha = (A + BK) d   (the candidates end at alpha, in the
        target's terminal set x_s + lambda X^f, which holds the box of radius sigma_lambda(alpha)
        around it: the terminal box of step k+1, and its states meet X).

The candidates' other states and inputs are those of the plans, which met X and U (constraint sets
in deviation coordinates are the same sets moved with the target). With x_s(theta) = a + theta (r - a)
between the applied target a and the requested r, both slacks are concave in theta (one minus a
gauge of an affine function of theta; lambda is one minus a gauge too), so the admissible thetas
form an interval [0, theta*], found by bisection. The tube of ``options.tube: robust`` tightens the
QPs beyond these sets: setpoints are refused with it (dmpc.scenario.schema).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from dmpc.offline.terminal_set import TerminalSet
from dmpc.tracking.targets import Target, TargetSpace

if TYPE_CHECKING:
    import scipy.sparse as sp

BISECTIONS = 40
"""Halvings of the interval for theta*: about 1e-12 of the way."""

RESERVE = 0.1
"""A move keeps the next terminal box at least this fraction of the full box around the applied
target (lambda sigma(0)), or as large as it is now if smaller: the largest move of all would leave
a box of radius zero, a terminal equality the plans can meet only to the solver's accuracy."""

SLACK_TOLERANCE = 1e-6
"""Plans solved to the QP solver's accuracy may end this far outside the terminal box: a step whose
applied target misses the test by less still moves, as long as it gets no worse."""


@dataclass(frozen=True)
class GovernorStep:
    """The target applied at the next step and how it was chosen.

    Attributes
    ----------
    target : Target
    theta : float
        The fraction of the way from the applied target to the requested one taken (1: reached).
    """

    target: Target
    theta: float


class ReferenceGovernor:
    """Chooses each step's applied target (see the module's text).

    Parameters
    ----------
    space : TargetSpace
    terminal : TerminalSet
        X^f = {x : Omega x <= 1} of the origin.
    closed_loop : ndarray or sparse matrix, shape (n, n)
        A + BK.
    gain : ndarray or sparse matrix, shape (m, n)
        K, block diagonal.
    """

    def __init__(self, space: TargetSpace, terminal: TerminalSet, closed_loop: np.ndarray | sp.spmatrix,
                 gain: np.ndarray | sp.spmatrix) -> None:
        self.space = space
        self.terminal = terminal
        self.closed_loop = closed_loop
        self.gain = gain
        self._sigma0 = terminal.sigma(np.zeros(space.n))

    def slacks(self, eta: np.ndarray, target: Target) -> tuple[float, float]:
        """How far the candidates ending at eta (n,) are inside the conditions for ``target``:
        (a) 1 - gauge_U of their last input, (b) sigma_lambda of their end, the radius of the next
        terminal box. Both >= 0 when they stay feasible."""
        d = eta - target.x
        tail = 1.0 - self.space.input_gauge(target.u + self.gain @ d)
        return tail, self.terminal.sigma(self.closed_loop @ d, target.scale)

    def slack(self, eta: np.ndarray, target: Target) -> float:
        """The smaller of :meth:`slacks` at the terminal states eta (n,): >= 0 when the candidates stay
        feasible for ``target``."""
        return min(self.slacks(eta, target))

    def step(self, eta: np.ndarray, applied: Target, requested: Target) -> GovernorStep:
        """The target for the next step, given the plans' terminal states eta (n,).

        The requested target itself when the candidates stay feasible for it and leave the next
        terminal box its reserve (``RESERVE``); else the largest fraction of the way that does.
        Where even the applied target fails the test by more than SLACK_TOLERANCE (plans that were
        not the QPs' own, such as fallbacks after lost messages), it stays.
        """
        if requested is applied:
            return GovernorStep(applied, 1.0)
        tail, box = self.slacks(eta, applied)
        if min(tail, box) < -SLACK_TOLERANCE:
            return GovernorStep(applied, 0.0)
        floors = (min(0.0, tail), min(RESERVE * applied.scale * self._sigma0, box))

        def admissible(target: Target) -> bool:
            return all(value >= floor for value, floor in zip(self.slacks(eta, target), floors))

        if admissible(requested):
            return GovernorStep(requested, 1.0)
        low, high = 0.0, 1.0
        for _ in range(BISECTIONS):
            mid = 0.5 * (low + high)
            if admissible(applied.towards(requested, mid, self.space)):
                low = mid
            else:
                high = mid
        return GovernorStep(applied.towards(requested, low, self.space), low)
