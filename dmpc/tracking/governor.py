"""The reference governor: how far the applied target may move toward the requested one in one step.

At the end of step k the agents' plans end at eta (n,). Each agent's candidate for step k+1 (its
plan shifted, with the terminal controller around the target as its last input) stays feasible
for the target x_s, u_s of step k+1 when

    (a) Omega (eta - x_s) <= lambda   (eta lies in the target's terminal set x_s + lambda X^f: the
        candidate's last input u_s + K (eta - x_s) is in U and eta in X), and
    (b) sigma_lambda(alpha) >= 0 with alpha = (A + BK)(eta - x_s) (the candidate ends at the centre
        of a non-empty terminal box; (a) implies it in exact arithmetic, as lambda X^f is invariant).

The candidate's other states and inputs are those of the plans, which met X and U. With
x_s(theta) = a + theta (r - a) between the applied target a and the requested r, both sides are
concave in theta (lambda is one minus a gauge, a convex function of an affine one), so the
admissible thetas form an interval [0, theta*]; theta* is found by bisection.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dmpc.offline.terminal_set import TerminalSet
from dmpc.tracking.targets import Target, TargetSpace

BISECTIONS = 40
"""Halvings of the interval for theta*: about 1e-12 of the way."""

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
    """

    def __init__(self, space: TargetSpace, terminal: TerminalSet, closed_loop) -> None:
        self.space = space
        self.terminal = terminal
        self.closed_loop = closed_loop

    def slack(self, eta: np.ndarray, target: Target) -> float:
        """How far the candidates ending at eta (n,) are inside the conditions (a) and (b) for
        ``target``, in units of the terminal set: >= 0 when they stay feasible."""
        d = eta - target.x
        return min(self.terminal.sigma(d, target.scale), self.terminal.sigma(self.closed_loop @ d, target.scale))

    def step(self, eta: np.ndarray, applied: Target, requested: Target) -> GovernorStep:
        """The target for the next step, given the plans' terminal states eta (n,).

        The requested target itself when the candidates stay feasible for it; else the largest
        admissible fraction of the way. Where even the applied target fails the test by more than
        SLACK_TOLERANCE (plans that were not the QPs' own, such as fallbacks after lost messages),
        it stays.
        """
        if requested is applied:
            return GovernorStep(applied, 1.0)
        now = self.slack(eta, applied)
        if now < -SLACK_TOLERANCE:
            return GovernorStep(applied, 0.0)
        floor = min(0.0, now)
        if self.slack(eta, requested) >= floor:
            return GovernorStep(requested, 1.0)
        low, high = 0.0, 1.0
        for _ in range(BISECTIONS):
            mid = 0.5 * (low + high)
            if self.slack(eta, applied.towards(requested, mid, self.space)) >= floor:
                low = mid
            else:
                high = mid
        return GovernorStep(applied.towards(requested, low, self.space), low)
