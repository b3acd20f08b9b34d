"""Terminal policies: what the terminal sets of a distributed method are and how they move.

A policy has two sides, both pure:

- the **agent side** (:meth:`TerminalPolicy.agent_terminal`): the rows T_i of agent i's terminal
  constraint and how a release's (centre, size) turns into their bounds;
- the **coordinator side**: the terminal parameters at k = 0 (:meth:`~TerminalPolicy.initial`),
  after each step from the plans' terminal states eta (:meth:`~TerminalPolicy.update`), what
  agent i is released (:meth:`~TerminalPolicy.release`), and which terminal state stands for an
  agent that fell back (:meth:`~TerminalPolicy.fallback_terminal`).

The methods share everything else (design, QP, protocol, fallback); they differ only here.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from dmpc.core.system import CoupledSystem, block_diag
from dmpc.methods.inscribed import DEFAULT_FACETS, inscribed_rows
from dmpc.methods.levels import dual_norms, fit_levels, level_increments, static_level
from dmpc.methods.terminal_rows import AgentTerminal, BoxTerminal, InscribedTerminal
from dmpc.offline import ControllerDesign


@dataclass(frozen=True)
class TerminalState:
    """The terminal parameters of one step.

    Attributes
    ----------
    alpha : ndarray, shape (n,)
        Box centres alpha(k) (zeros for the ellipsoid methods, whose sets are centred at 0).
    beta : float
        Box radius beta(k) (NaN for the ellipsoid methods).
    r : ndarray, shape (M,), or None
        Ellipsoid levels r_i(k) (None for the box methods).
    note : str
        Something the records should say about how this state was reached ("" if nothing).
    """

    alpha: np.ndarray
    beta: float
    r: np.ndarray | None = None
    note: str = ""


class TerminalPolicy(ABC):
    """The terminal sets of one distributed method on one system and design."""

    name: str

    def __init__(self, system: CoupledSystem, design: ControllerDesign) -> None:
        self.system = system
        self.design = design

    @abstractmethod
    def agent_terminal(self, i: int) -> AgentTerminal:
        """Agent i's terminal rows (set up once per agent)."""

    @abstractmethod
    def initial(self, x0: np.ndarray) -> TerminalState:
        """The terminal parameters at k = 0 for the initial state x0 (n,)."""

    @abstractmethod
    def update(self, state: TerminalState, eta: np.ndarray, scale: float = 1.0) -> TerminalState:
        """The parameters of step k+1 from those of step k (``state``) and the terminal states eta (n,).

        With a setpoint target, eta is taken around the target of step k+1 and ``scale`` is that
        target's lambda: the terminal set is lambda X^f around it (dmpc.tracking.targets).
        """

    @abstractmethod
    def release(self, state: TerminalState, i: int) -> tuple[np.ndarray, float]:
        """The (centre (n_i,), size) released to agent i at the terminal parameters ``state``."""

    def release_all(self, state: TerminalState) -> tuple[np.ndarray, np.ndarray]:
        """Every agent's release at once at ``state``: centres (n,), agent i's on its own coordinates,
        and sizes (M,)."""
        parts = [self.release(state, i) for i in range(self.system.M)]
        return np.concatenate([c for c, _ in parts]), np.array([size for _, size in parts], dtype=float)

    @abstractmethod
    def fallback_terminal(self, state: TerminalState, i: int, candidate_end: np.ndarray) -> np.ndarray:
        """eta_i for agent i that fell back at ``state``; ``candidate_end`` (n_i,) ends its shifted candidate."""

    def joint_terminal(self, state: TerminalState) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The agents' terminal sets stacked on the global state: T (r, n), lower (r,), upper (r,)."""
        T, lower, upper = [], [], []
        for i in range(self.system.M):
            term = self.agent_terminal(i)
            centre, size = self.release(state, i)
            lo, hi = term.bounds(centre, size)
            T.append(term.T)
            lower.append(lo)
            upper.append(hi)
        return block_diag(*T), np.concatenate(lower), np.concatenate(upper)


class BoxPolicy(TerminalPolicy):
    """Terminal boxes ||z_i(N) - alpha_i||_inf <= beta, of the method ``name`` on ``system`` and ``design``.

    ``time_varying``: alpha(k+1) = (A+BK) eta, beta(k+1) = sigma(alpha(k+1)) (the paper's
    Theorem 1). Otherwise alpha and beta keep their values at k = 0.

    ``optimizer``: a :class:`dmpc.methods.initial.BoxOptimizer` choosing alpha(0), beta(0) from
    x(0); None keeps the design's (the scenario's ``terminal``).
    """

    def __init__(self, system: CoupledSystem, design: ControllerDesign, name: str, time_varying: bool,
                 optimizer=None) -> None:
        super().__init__(system, design)
        self.name = name
        self.time_varying = time_varying
        self._optimizer = optimizer
        self._terminals: dict[int, BoxTerminal] = {}

    @cached_property
    def closed_loop(self) -> np.ndarray:
        """A + BK, shape (n, n); only the coordinator updates the boxes: an agent never builds it."""
        return self.system.A + self.system.B @ self.design.gains.K_global()

    def agent_terminal(self, i: int) -> AgentTerminal:
        if i not in self._terminals:
            self._terminals[i] = BoxTerminal(self.system.subsystems[i].n, self.design.tightening[i].terminal_margin)
        return self._terminals[i]

    def initial(self, x0: np.ndarray) -> TerminalState:
        if self._optimizer is None:
            return TerminalState(np.array(self.design.alpha0, float), float(self.design.beta0))
        box = self._optimizer(x0)
        note = ("k=0: alpha(0), beta(0) chosen by the centralised QP" if box.optimized else
                "k=0: the optimisation of alpha(0) is infeasible; the scenario's alpha(0), beta(0) are used")
        return TerminalState(box.alpha, box.beta, note=note)

    def update(self, state: TerminalState, eta: np.ndarray, scale: float = 1.0) -> TerminalState:
        if not self.time_varying:
            return TerminalState(state.alpha.copy(), state.beta)
        alpha = self.closed_loop @ eta
        return TerminalState(alpha, self.design.terminal.sigma(alpha, scale))

    def release(self, state: TerminalState, i: int) -> tuple[np.ndarray, float]:
        return state.alpha[self.system.xs(i)].copy(), state.beta

    def release_all(self, state: TerminalState) -> tuple[np.ndarray, np.ndarray]:
        return state.alpha.copy(), np.full(self.system.M, state.beta)

    def fallback_terminal(self, state: TerminalState, i: int, candidate_end: np.ndarray) -> np.ndarray:
        # the shifted candidate ends at alpha_i(k) = ((A+BK) eta(k-1))_i
        # (docs/algorithm.md, "Online step k, agent i", item 7)
        return state.alpha[self.system.xs(i)].copy()

    def joint_terminal(self, state: TerminalState) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        # the centralised seed has always used the untightened box
        return np.eye(self.system.n), state.alpha - state.beta, state.alpha + state.beta


class EllipsoidPolicy(TerminalPolicy):
    """Terminal ellipsoids z_i(N)' P_i z_i(N) <= r_i, imposed through inscribed polytopes.

    The levels start at the static common level
    (docs/methods.md, "`ellipsoid` and `ellipsoid-adaptive`"). ``adaptive``: they
    move by r_i(k+1) = r_i(k) + eta' Gamma_i eta and are scaled back into X^f when needed
    (:mod:`dmpc.methods.levels`); otherwise they stay.

    Parameters
    ----------
    system : CoupledSystem
    design : ControllerDesign
    name : str
        The method's name (``ellipsoid`` or ``ellipsoid-adaptive``).
    adaptive : bool
    facets : int
        Sides of the polygon inscribed in each two-dimensional ellipse.
    """

    def __init__(self, system: CoupledSystem, design: ControllerDesign, name: str, adaptive: bool,
                 facets: int = DEFAULT_FACETS) -> None:
        super().__init__(system, design)
        self.name = name
        self.adaptive = adaptive
        self.facets = facets
        P = design.gains.P
        self.level0 = static_level(design.terminal.omega, system, P)
        self._norms = dual_norms(design.terminal.omega, system, P)
        self._gamma = level_increments(system, design.gains.K, P) if adaptive else None
        self._terminals: dict[int, InscribedTerminal] = {}

    def agent_terminal(self, i: int) -> AgentTerminal:
        if i not in self._terminals:
            T, h = inscribed_rows(self.design.gains.P[i], self.facets)
            self._terminals[i] = InscribedTerminal(T, h, self.design.tightening[i].terminal_margin)
        return self._terminals[i]

    def initial(self, x0: np.ndarray) -> TerminalState:
        return TerminalState(np.zeros(self.system.n), float("nan"), np.full(self.system.M, self.level0))

    def update(self, state: TerminalState, eta: np.ndarray, scale: float = 1.0) -> TerminalState:
        if not self.adaptive or self._gamma is None:  # the increments Gamma_i exist exactly when adaptive
            return TerminalState(state.alpha.copy(), state.beta, _levels(state).copy())
        raw = _levels(state) + np.array([eta @ G @ eta for G in self._gamma])
        levels, scaled = fit_levels(raw, self._norms)
        note = "levels scaled back into X^f" if scaled else ""
        return TerminalState(state.alpha.copy(), state.beta, levels, note)

    def release(self, state: TerminalState, i: int) -> tuple[np.ndarray, float]:
        return np.zeros(self.system.subsystems[i].n), float(_levels(state)[i])

    def release_all(self, state: TerminalState) -> tuple[np.ndarray, np.ndarray]:
        return np.zeros(self.system.n), np.array(state.r, dtype=float)

    def fallback_terminal(self, state: TerminalState, i: int, candidate_end: np.ndarray) -> np.ndarray:
        return np.asarray(candidate_end, float).copy()


def _levels(state: TerminalState) -> np.ndarray:
    """The ellipsoid levels r (M,) of a state that :class:`EllipsoidPolicy` made."""
    if state.r is None:
        raise ValueError("an ellipsoid method's terminal state has levels r; this one has none (a box method's?)")
    return state.r
