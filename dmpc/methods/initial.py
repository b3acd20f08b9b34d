"""An initial terminal box chosen by optimisation at k = 0 (``tv-box-opt``).

The paper starts every run from alpha(0) = 0, beta(0) = 0.5: the plans must end in one fixed
cube around the origin, wherever x(0) is. Instead, solve the centralised MPC QP from x(0) with
the terminal constraint "z(N) is the centre of a cube of radius beta_min inside X^f":

    Omega_l z(N) + beta_min ||Omega_l||_1 <= 1   for every row l    (i.e. sigma(z(N)) >= beta_min)

and take alpha(0) = z*(N), beta(0) = sigma(alpha(0)) >= beta_min. The union of these cubes over
all admissible centres is X^f shrunk by beta_min in the infinity norm, which contains the fixed
cube whenever beta_min <= sigma(0) / 2; so wherever the fixed start is feasible this one is too,
and the first plans end in the middle of their box instead of on its edge. beta_min is the
scenario's beta(0).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from dmpc.core.system import CoupledSystem
from dmpc.offline import ControllerDesign

if TYPE_CHECKING:
    from dmpc.core.central_qp import CentralQP


@dataclass(frozen=True)
class InitialBox:
    """alpha(0) (n,), beta(0), and whether the optimisation succeeded (``optimized``; else the design's box)."""

    alpha: np.ndarray
    beta: float
    optimized: bool


class BoxOptimizer:
    """Chooses alpha(0), beta(0) for a given x(0); the centralised QP is set up once.

    Parameters
    ----------
    system : CoupledSystem
    design : ControllerDesign
    """

    def __init__(self, system: CoupledSystem, design: ControllerDesign) -> None:
        self._design = design
        self._system = system
        self._qp: CentralQP | None = None

    def __call__(self, x0: np.ndarray) -> InitialBox:
        from dmpc.core.central_qp import CentralQP  # lazy: agent processes never need it

        d = self._design
        if self._qp is None:
            self._qp = CentralQP(self._system, d.gains.P_global(), d.horizon, terminal="omega", omega=d.terminal.omega)
        sol = self._qp.solve(np.asarray(x0, float), shrink=d.beta0)
        if not sol.status.feasible:
            return InitialBox(np.array(d.alpha0, float), float(d.beta0), False)
        alpha = sol.z[-1].copy()
        return InitialBox(alpha, d.terminal.sigma(alpha), True)
