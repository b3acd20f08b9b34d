"""Stabilisability of each subsystem's own pair (A_ii, B_ii), checked before a gain design.

A block-diagonal gain K = diag(K_i) that meets (10) makes every A_ii + B_ii K_i a stable matrix
(the i-th diagonal block of (10) already holds for it), so an (A_ii, B_ii) with a mode that no
input can move is a dead end for the ``lmi`` and ``lqr`` designs. The PBH test names it: the pair
is stabilisable iff rank [A_ii - lambda I, B_ii] = n_i for every eigenvalue lambda of A_ii with
|lambda| >= 1.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dmpc.core.errors import DesignError
from dmpc.core.system import CoupledSystem

# relative to the norm of [A_ii, B_ii]: a singular value below this is a lost rank
RANK_TOLERANCE = 1e-9


@dataclass(frozen=True)
class StuckMode:
    """An eigenvalue of A_ii with |lambda| >= 1 that B_ii cannot move (one of a conjugate pair).

    Attributes
    ----------
    eigenvalue : complex
    rank : int
        Rank of [A_ii - lambda I, B_ii] (< n_i).
    """

    eigenvalue: complex
    rank: int

    def describe(self) -> str:
        lam = self.eigenvalue
        text = f"{lam.real:.4g}" if abs(lam.imag) < 1e-12 else f"{lam.real:.4g} +- {abs(lam.imag):.4g}j"
        return f"lambda = {text} (|lambda| = {abs(lam):.4g})"


def stuck_modes(A: np.ndarray, B: np.ndarray) -> list[StuckMode]:
    """The modes of A (n, n) with |lambda| >= 1 that fail the PBH rank test with B (n, m)."""
    n = A.shape[0]
    scale = max(1.0, float(np.linalg.norm(np.hstack([A, B]), 2)))
    stuck: list[StuckMode] = []
    for lam in np.linalg.eigvals(A):
        if abs(lam) < 1.0:
            continue
        pbh = np.hstack([A - lam * np.eye(n), B.astype(complex)])
        singular = np.linalg.svd(pbh, compute_uv=False)
        rank = int(np.sum(singular > RANK_TOLERANCE * scale))
        seen = any(min(abs(lam - s.eigenvalue), abs(lam.conjugate() - s.eigenvalue)) < 1e-9 * scale for s in stuck)
        if rank < n and not seen:
            stuck.append(StuckMode(complex(lam), rank))
    return stuck


def check_stabilisable(system: CoupledSystem, method: str) -> None:
    """Raise DesignError naming the first subsystem whose (A_ii, B_ii) is not stabilisable.

    Parameters
    ----------
    system : CoupledSystem
    method : str
        The gain design the check runs for (named in the message).
    """
    for s in system.subsystems:
        stuck = stuck_modes(s.A, s.B)
        if stuck:
            modes = ", ".join(m.describe() for m in stuck)
            raise DesignError(
                f"gains ({method}): (A_ii, B_ii) of subsystem {s.name} is not stabilisable: the mode(s) {modes} "
                f"of A_ii cannot be moved by its input (rank [A_ii - lambda I, B_ii] = {stuck[0].rank} < n_i = {s.n}), "
                "so no gain K_i makes A_ii + B_ii K_i stable; check B_ii (a zero column?) or A_ii")
