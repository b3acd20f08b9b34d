"""Resolving ``terminal.beta0: auto`` and ``horizon: auto``, and checking that the start is feasible.

- ``beta0: auto`` is ``BETA0_FRACTION`` x sigma(alpha0): the largest box around alpha0 inside
  X^f, less a margin from its boundary.
- A given horizon N is checked with one LP (:func:`dmpc.design.start.start_feasible`): the start
  must be feasible for the centralised problem with the method's k = 0 terminal constraint.
  If it is not, the error names the smallest N that is (searched up to ``HORIZON_CAP``).
- ``horizon: auto`` takes the smallest N for which the distributed k = 0 step itself finds a
  plan for every agent (no fallback), searched upwards from the smallest centrally feasible N,
  plus a margin of ``max(MIN_MARGIN, ceil(MARGIN_FRACTION * N))`` steps: a start near the edge of
  the feasible region at the minimal N leaves the plans no room.
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from dmpc.design import Design, DesignError, GainDesign, RevisionBound, TerminalSet, assemble
from dmpc.design.start import HORIZON_CAP, smallest_feasible_horizon, start_feasible
from dmpc.methods import terminal_policy
from dmpc.qp_status import SOLVED
from dmpc.runtime.direct import DirectLoop
from dmpc.steps import ProtocolOptions
from dmpc.system import CoupledSystem, LinearSet

BETA0_FRACTION = 0.9
"""``beta0: auto`` = this fraction of sigma(alpha0)."""
MARGIN_FRACTION = 0.2
MIN_MARGIN = 2
"""``horizon: auto`` adds max(MIN_MARGIN, ceil(MARGIN_FRACTION * N_min)) to the smallest feasible N."""


def auto_beta0(terminal: TerminalSet, alpha0: np.ndarray) -> float:
    """BETA0_FRACTION * sigma(alpha0); DesignError if alpha0 is not inside X^f."""
    sigma0 = terminal.sigma(alpha0)
    if not sigma0 > 0:
        raise DesignError(f"terminal: beta0 auto: alpha0 is not inside X^f (sigma(alpha0) = {sigma0:.4g}); move alpha0")
    return BETA0_FRACTION * sigma0


def horizon_margin(n_min: int) -> int:
    """Steps added to the smallest feasible horizon by ``horizon: auto``."""
    return max(MIN_MARGIN, math.ceil(MARGIN_FRACTION * n_min))


def k0_terminal(design: Design, system: CoupledSystem, method: str) -> LinearSet:
    """The method's terminal constraint at k = 0 on the global state.

    The box methods impose the box around alpha0; ``tv-box-opt`` and ``centralized`` may use all
    of X^f; the ellipsoid methods their inscribed polytopes.
    """
    if method in ("tv-box-opt", "centralized"):
        omega = design.terminal.omega
        return LinearSet.polytope(omega, np.ones(omega.shape[0]))
    policy = terminal_policy(method, system, design)
    T, lower, upper = policy.joint_terminal(policy.initial(system.x0))
    return LinearSet(T, lower, upper)


def _dmpc_k0_feasible(system: CoupledSystem, design: Design, method: str, coupling: str,
                      protocol: ProtocolOptions) -> bool:
    """True if the distributed k = 0 step gives every agent a plan (no fallback) from a QP that
    was feasible in the last round."""
    if method == "centralized":
        return True  # one QP: central feasibility is the whole story
    records = []
    DirectLoop(system, design, replace(protocol, steps=1), method, coupling).run(1, records.append)
    # an agent whose QP failed in a later Jacobi round keeps an earlier plan (no fallback), but
    # its problem from the final assumptions was infeasible: that counts as infeasible too
    return bool(records) and not any(records[0].fallback) and all(s in SOLVED for s in records[0].status)


class StartCheck:
    """The start checks of one system, gains and terminal set, for any horizon.

    Parameters
    ----------
    system : CoupledSystem
    gains : GainDesign
    terminal : TerminalSet
    alpha0 : ndarray, shape (n,)
    beta0 : float
    method, coupling, tube : str
    revision_bounds : dict, optional
    disturbance_bounds : dict, optional
        Per subsystem index, the bound (n_i,) of an additive plant disturbance (for the tube).
    protocol : ProtocolOptions
        The Jacobi settings the k = 0 step runs with.
    """

    def __init__(self, system: CoupledSystem, gains: GainDesign, terminal: TerminalSet, *, alpha0: np.ndarray,
                 beta0: float, method: str, coupling: str, tube: str, protocol: ProtocolOptions,
                 revision_bounds: dict[int, RevisionBound] | None = None,
                 disturbance_bounds: dict[int, np.ndarray] | None = None) -> None:
        self.system = system
        self.method = method
        self.coupling = coupling
        self.protocol = protocol
        self._make = lambda N: assemble(system, gains, terminal, horizon=N, alpha0=alpha0, beta0=beta0, tube=tube,
                                        revision_bounds=revision_bounds, disturbance_bounds=disturbance_bounds)
        self._terminal_rows: LinearSet | None = None

    def design(self, N: int) -> Design:
        return self._make(N)

    def central_feasible(self, N: int) -> bool | None:
        """The LP test at horizon N (None: undecided)."""
        if self._terminal_rows is None:
            self._terminal_rows = k0_terminal(self._make(N), self.system, self.method)
        return start_feasible(self.system, self.system.x0, N, self._terminal_rows)

    def smallest_central(self, cap: int = HORIZON_CAP) -> int | None:
        """The smallest centrally feasible horizon up to ``cap`` (:func:`smallest_feasible_horizon`)."""
        return smallest_feasible_horizon(lambda N: bool(self.central_feasible(N)), cap)

    def dmpc_feasible(self, N: int) -> bool:
        return _dmpc_k0_feasible(self.system, self._make(N), self.method, self.coupling, self.protocol)

    # ------------------------------------------------------------------ the two uses
    def checked(self, N: int) -> Design:
        """The design at a given horizon N, refused (DesignError) if the start is centrally infeasible."""
        ok = self.central_feasible(N)
        if ok is None:
            return self._make(N).with_start({"horizon": "given", "centrally_feasible": None,
                                             "note": "the LP solver could not decide feasibility"})
        if not ok:
            smallest = self.smallest_central()
            hint = (f"the smallest horizon for which it is feasible is N = {smallest}: set horizon: {smallest} "
                    f"or larger, or horizon: auto" if smallest is not None else
                    f"no horizon up to N = {HORIZON_CAP} makes it feasible: the start is too far out for the "
                    "constraints (move x0, widen U_i or X_i, or check the model)")
            raise DesignError(f"horizon: the start x(0) is infeasible for the centralised problem at N = {N} "
                              f"(constraints and the {self.method} terminal set at k = 0); {hint}")
        return self._make(N).with_start({"horizon": "given", "centrally_feasible": True})

    def auto(self) -> Design:
        """The design at ``horizon: auto``: the smallest N whose distributed k = 0 step is feasible, plus a margin."""
        n_central = self.smallest_central()
        if n_central is None:
            raise DesignError(f"horizon: auto: no horizon up to N = {HORIZON_CAP} makes the start x(0) feasible "
                              "for the centralised problem: the start is too far out for the constraints (move x0, "
                              "widen U_i or X_i, or check the model)")
        n_min = next((N for N in range(n_central, HORIZON_CAP + 1) if self.dmpc_feasible(N)), None)
        if n_min is None:
            raise DesignError(f"horizon: auto: the start is centrally feasible from N = {n_central}, but the "
                              f"distributed k = 0 step finds no plan for every agent up to N = {HORIZON_CAP}")
        margin = horizon_margin(n_min)
        chosen = n_min + margin
        while chosen <= HORIZON_CAP and not self.dmpc_feasible(chosen):
            chosen += 1
        if chosen > HORIZON_CAP:
            chosen = n_min
        return self._make(chosen).with_start({"horizon": "auto", "chosen": chosen, "smallest_feasible": n_min,
                                              "smallest_centrally_feasible": n_central, "margin": chosen - n_min})
