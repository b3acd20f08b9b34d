"""Resolving ``terminal.beta0: auto`` and ``horizon: auto``, and checking that the start is feasible.

- ``beta0: auto`` is ``BETA0_FRACTION`` x sigma(alpha0): the largest box around alpha0 inside
  X^f, less a margin from its boundary.
- A given horizon N is checked with one LP (:func:`dmpc.offline.start.start_feasible`): the start
  must be feasible for the centralised problem with the method's k = 0 terminal constraint.
  If it is not, the error names the smallest N for which the distributed k = 0 step finds a plan
  for every agent (searched up to ``HORIZON_CAP``), which may exceed the smallest centrally
  feasible N.
- ``horizon: auto`` takes the smallest N for which the distributed k = 0 step itself finds a
  plan for every agent (no fallback), searched upwards from the smallest centrally feasible N,
  plus a margin of ``max(MIN_MARGIN, ceil(MARGIN_FRACTION * N))`` steps: a start near the edge of
  the feasible region at the minimal N leaves the plans no room.

What the method contributes, its terminal constraint at k = 0 and its distributed first step,
comes in as a :class:`StartProblem` (:class:`dmpc.setup.start.MethodStart` builds it from the
methods and the distributed loop, which sit above the design).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from dmpc.core.system import CoupledSystem, LinearSet
from dmpc.offline import ControllerDesign, DesignError, GainDesign, RevisionBound, TerminalSet, assemble
from dmpc.offline.start import HORIZON_CAP, smallest_feasible_horizon, start_feasible

BETA0_FRACTION = 0.9
"""``beta0: auto`` = this fraction of sigma(alpha0)."""
MARGIN_FRACTION = 0.2
MIN_MARGIN = 2
"""``horizon: auto`` adds max(MIN_MARGIN, ceil(MARGIN_FRACTION * N_min)) to the smallest feasible N."""


def auto_beta0(terminal: TerminalSet, alpha0: np.ndarray) -> float:
    """BETA0_FRACTION * sigma(alpha0) of the ``terminal`` set X^f; DesignError if alpha0 is not inside it."""
    sigma0 = terminal.sigma(alpha0)
    if not sigma0 > 0:
        raise DesignError(f"terminal: beta0 auto: alpha0 is not inside X^f (sigma(alpha0) = {sigma0:.4g}); move alpha0")
    return BETA0_FRACTION * sigma0


def horizon_margin(n_min: int) -> int:
    """Steps added to the smallest feasible horizon ``n_min`` by ``horizon: auto``."""
    return max(MIN_MARGIN, math.ceil(MARGIN_FRACTION * n_min))


class StartProblem(Protocol):
    """What the start checks ask of the control method a design is made for.

    Attributes
    ----------
    method : str
        The method's name, for the messages.
    """

    @property
    def method(self) -> str:
        ...

    def terminal_rows(self, design: ControllerDesign) -> LinearSet:
        """The method's terminal constraint at k = 0 on the global state (rows on z(N), dimension n),
        with the terminal set of ``design``."""
        ...

    def distributed_plans(self, design: ControllerDesign) -> bool:
        """True if the distributed k = 0 step with ``design`` gives every agent a plan (no fallback)
        from a QP that was feasible in the last round."""
        ...


class StartCheck:
    """The start checks of one system, gains and terminal set, for any horizon.

    Parameters
    ----------
    system : CoupledSystem
    gains : GainDesign
    terminal : TerminalSet
    alpha0 : ndarray, shape (n,)
    beta0 : float
    tube : str
    start : StartProblem
        The method's terminal constraint at k = 0 and its distributed first step.
    revision_bounds : dict, optional
    disturbance_bounds : dict, optional
        Per subsystem index, the bound (n_i,) of an additive plant disturbance (for the tube).
    """

    def __init__(self, system: CoupledSystem, gains: GainDesign, terminal: TerminalSet, *, alpha0: np.ndarray,
                 beta0: float, tube: str, start: StartProblem,
                 revision_bounds: dict[int, RevisionBound] | None = None,
                 disturbance_bounds: dict[int, np.ndarray] | None = None) -> None:
        self.system = system
        self.start = start
        self.method = start.method
        self._make = lambda N: assemble(system, gains, terminal, horizon=N, alpha0=alpha0, beta0=beta0, tube=tube,
                                        revision_bounds=revision_bounds, disturbance_bounds=disturbance_bounds)
        self._terminal_rows: LinearSet | None = None

    def design(self, N: int) -> ControllerDesign:
        """The design at horizon N, unchecked."""
        return self._make(N)

    def central_feasible(self, N: int) -> bool | None:
        """The LP test at horizon N (None: undecided)."""
        if self._terminal_rows is None:
            self._terminal_rows = self.start.terminal_rows(self._make(N))
        return start_feasible(self.system, self.system.x0, N, self._terminal_rows)

    def smallest_central(self, cap: int = HORIZON_CAP) -> int | None:
        """The smallest centrally feasible horizon up to ``cap`` (:func:`smallest_feasible_horizon`)."""
        return smallest_feasible_horizon(lambda N: bool(self.central_feasible(N)), cap)

    def dmpc_feasible(self, N: int) -> bool:
        """Whether the distributed k = 0 step finds a plan for every agent at horizon N."""
        return self.start.distributed_plans(self._make(N))

    def search(self) -> "HorizonSearch":
        """The smallest centrally feasible N, the smallest N whose distributed k = 0 step is feasible,
        and the horizon ``auto`` chooses (that N plus a margin); None where there is none up to the cap."""
        n_central = self.smallest_central()
        if n_central is None:
            return HorizonSearch(None, None, None)
        n_min = next((N for N in range(n_central, HORIZON_CAP + 1) if self.dmpc_feasible(N)), None)
        if n_min is None:
            return HorizonSearch(n_central, None, None)
        chosen = n_min + horizon_margin(n_min)
        while chosen <= HORIZON_CAP and not self.dmpc_feasible(chosen):
            chosen += 1
        return HorizonSearch(n_central, n_min, chosen if chosen <= HORIZON_CAP else n_min)

    # ------------------------------------------------------------------ the two uses
    def checked(self, N: int) -> ControllerDesign:
        """The design at a given horizon N, refused (DesignError) if the start is centrally infeasible.

        The refusal names the horizon the distributed k = 0 step needs (what ``horizon: auto``
        searches for), not only the smallest centrally feasible one, which may be too short for it.
        """
        ok = self.central_feasible(N)
        if ok is None:
            return self._make(N).with_start({"horizon": "given", "centrally_feasible": None,
                                             "note": "the LP solver could not decide feasibility"})
        if not ok:
            raise DesignError(f"horizon: the start x(0) is infeasible for the centralised problem at N = {N} "
                              f"(constraints and the {self.method} terminal set at k = 0); "
                              f"{_advice(self.search())}")
        return self._make(N).with_start({"horizon": "given", "centrally_feasible": True})

    def auto(self, check_start: bool = True) -> ControllerDesign:
        """The design at ``horizon: auto``: the smallest N whose distributed k = 0 step is feasible, plus a margin.

        ``check_start`` is the scenario's ``design.check_start``: ``auto`` needs a start it can
        plan from whatever it says, so when it is false a refusal says how to run anyway.
        """
        found = self.search()
        anyway = ("" if check_start else "; design.check_start: false does not apply to horizon: auto, which "
                  "needs a start it can plan from: set a number (horizon: N) to run anyway")
        if found.central is None:
            raise DesignError(f"horizon: auto: no horizon up to N = {HORIZON_CAP} makes the start x(0) feasible "
                              "for the centralised problem: the start is too far out for the constraints (move x0, "
                              f"widen U_i or X_i, or check the model){anyway}")
        if found.distributed is None or found.chosen is None:  # chosen is None exactly when distributed is
            raise DesignError(f"horizon: auto: the start is centrally feasible from N = {found.central}, but the "
                              f"distributed k = 0 step finds no plan for every agent up to N = {HORIZON_CAP}{anyway}")
        return self._make(found.chosen).with_start({
            "horizon": "auto", "chosen": found.chosen, "smallest_feasible": found.distributed,
            "smallest_centrally_feasible": found.central, "margin": found.chosen - found.distributed})


@dataclass(frozen=True)
class HorizonSearch:
    """What the horizon search found (None: no such horizon up to ``HORIZON_CAP``).

    Attributes
    ----------
    central : int or None
        The smallest N for which the start is feasible for the centralised problem.
    distributed : int or None
        The smallest N (>= central) for which the distributed k = 0 step gives every agent a plan.
    chosen : int or None
        What ``horizon: auto`` takes: ``distributed`` plus a margin.
    """

    central: int | None
    distributed: int | None
    chosen: int | None


def _advice(found: HorizonSearch) -> str:
    """What to set instead of a horizon at which the start is centrally infeasible."""
    if found.central is None:
        return (f"no horizon up to N = {HORIZON_CAP} makes it feasible: the start is too far out for the "
                "constraints (move x0, widen U_i or X_i, or check the model)")
    if found.distributed is None:
        return (f"the centralised problem is feasible from N = {found.central}, but the distributed k = 0 step "
                f"finds no plan for every agent up to N = {HORIZON_CAP}")
    central = ("" if found.central == found.distributed else
               f" (the centralised problem alone is feasible from N = {found.central})")
    return (f"the smallest horizon for which the distributed k = 0 step finds a plan for every agent is "
            f"N = {found.distributed}{central}: set horizon: {found.distributed} or larger, or horizon: auto "
            f"(N = {found.chosen} here, with a margin)")
