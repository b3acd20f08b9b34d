"""Steady-state targets of the coupled system and the scale of the terminal set around them.

A target is a steady state (x_s, u_s) of the whole coupled system, x_s = A x_s + B u_s, that
meets the requested components and lies strictly inside X and U:

    gauge_X(x_s) <= 1 - margin  and  gauge_U(u_s) <= 1 - margin,

where gauge_S(v) = min {t >= 0 : v in t S} is the gauge (Minkowski functional) of a constraint
set that holds the origin in its interior. In deviation coordinates dx = x - x_s, du = u - u_s
the dynamics, weights and gains are unchanged and only the constraint sets move, to X - x_s and
U - u_s. Both contain lambda X and lambda U with

    lambda = 1 - max(gauge_X(x_s), gauge_U(u_s))   (>= margin),

because x_s in (1 - lambda) X and X is convex. So lambda X^f, the origin's terminal set scaled by
lambda, is positively invariant under A + BK and admissible for the shifted constraints: it is the
terminal set of the target, with no new LP, and sigma(alpha) becomes
min_l (lambda - Omega_l alpha) / ||Omega_l||_1.

The free components follow one rule: among the admissible steady states that meet the request,
the one nearest the origin in the weights of the cost, x_s' Q x_s + u_s' R u_s. A request with no
admissible steady state is replaced by the nearest admissible one (requested components weighted
by the diagonals of Q and R), and its gap is reported.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from dmpc.core.system import CoupledSystem, stack_sets
from dmpc.estimation.targets import gauge_rows

DEFAULT_MARGIN = 0.05
"""A target keeps this fraction of the way from the origin to every finite bound free: lambda >= it."""

REGULARISATION = 1e-9
"""Added to the weights of the steady-state QPs (times their largest diagonal entry), so that the
target is unique where Q is only semidefinite on directions the request leaves free."""

MARGIN_ROOM = 1e-6
"""The steady-state QPs keep targets this much further inside than the margin: an interior-point
solution meets its constraints only to its tolerance, so the margin holds as stated."""

STEADY_TOLERANCE = 1e-13
"""A target leaves x = A x + B u by at most this (relative to its largest entry)."""

MET_TOLERANCE = 1e-7
"""A requested component counts as met when the target is within this (relative) of it."""

PIN_TOLERANCE = 1e-9
"""How far (relative) the second stage may move a component the first stage settled."""

SOLVER_TOLERANCE = 1e-10
"""Clarabel's tolerances in the steady-state QPs (duality gap, absolute and relative, and feasibility).
The nearest admissible target minimises a weighted squared distance to the request, settled to
SOLVER_TOLERANCE times max(1, the objective's size): a request on the margin is met to about its
square root (dmpc.records.tracking.gap_tolerance)."""


class TargetError(ValueError):
    """A request that cannot be read (wrong length, non-finite value, unknown component)."""


@dataclass(frozen=True, eq=False)
class Request:
    """Requested components of the global state and input; NaN marks a free component.

    Attributes
    ----------
    x : ndarray, shape (n,)
    u : ndarray, shape (m,)
    y : ndarray, shape (p,), or None
        Requested outputs, with estimation (docs/algorithm.md, "Offset-free tracking"): ``x`` is
        then all free. None without.
    """

    x: np.ndarray
    u: np.ndarray
    y: np.ndarray | None = None

    @classmethod
    def free(cls, n: int, m: int) -> "Request":
        """Nothing requested on n states and m inputs: the target is the origin."""
        return cls(np.full(n, np.nan), np.full(m, np.nan))

    @property
    def is_free(self) -> bool:
        return bool(np.isnan(self.x).all() and np.isnan(self.u).all()
                    and (self.y is None or np.isnan(self.y).all()))

    def same_as(self, other: "Request") -> bool:
        """Whether ``other`` asks for the same setpoint (NaN entries, "free", count as equal)."""
        same_y = (self.y is None and other.y is None) or (
            self.y is not None and other.y is not None and np.array_equal(self.y, other.y, equal_nan=True))
        return same_y and np.array_equal(self.x, other.x, equal_nan=True) and np.array_equal(self.u, other.u,
                                                                                            equal_nan=True)


@dataclass(frozen=True, eq=False)
class Target:
    """A steady state of the coupled system and what it took to reach it.

    Attributes
    ----------
    x : ndarray, shape (n,)
        x_s, with x_s = A x_s + B u_s.
    u : ndarray, shape (m,)
        u_s.
    scale : float
        lambda in (0, 1]: the terminal set around the target is x_s + lambda X^f.
    gap_x : ndarray, shape (n,)
        x_s - requested, NaN where nothing was requested; zero (to the solver's accuracy) where
        the request was met.
    gap_u : ndarray, shape (m,)
    reachable : bool
        The request was met exactly (no gap beyond the solver's accuracy).
    """

    x: np.ndarray
    u: np.ndarray
    scale: float
    gap_x: np.ndarray = field(repr=False)
    gap_u: np.ndarray = field(repr=False)
    reachable: bool = True

    @classmethod
    def origin(cls, n: int, m: int) -> "Target":
        """The origin as a target of n states and m inputs (scale 1, nothing requested)."""
        return cls(np.zeros(n), np.zeros(m), 1.0, np.full(n, np.nan), np.full(m, np.nan), True)

    @property
    def is_origin(self) -> bool:
        return not self.x.any() and not self.u.any()

    def towards(self, other: "Target", theta: float, space: "TargetSpace") -> "Target":
        """The steady state a fraction ``theta`` in [0, 1] of the way to ``other`` (a steady state too,
        since steady states form a subspace), with the scale ``space`` gives it; its gaps are ``other``'s."""
        if theta >= 1.0:
            return other
        if theta <= 0.0:
            return self
        x = self.x + theta * (other.x - self.x)
        u = self.u + theta * (other.u - self.u)
        return Target(x, u, space.scale(x, u), other.gap_x, other.gap_u, other.reachable)


class TargetSpace:
    """The steady states of one coupled system and the sets they must stay in.

    Parameters
    ----------
    system : CoupledSystem
    margin : float
        In (0, 1): targets satisfy gauge <= 1 - margin in X and U, so lambda >= margin.
    """

    def __init__(self, system: CoupledSystem, margin: float = DEFAULT_MARGIN) -> None:
        if not 0.0 < margin < 1.0:
            raise ValueError(f"setpoint margin must lie in (0, 1), got {margin}")
        self.system = system
        self.margin = float(margin)
        self.n, self.m = system.n, system.m
        X = stack_sets([s.state_set for s in system.subsystems], [s.n for s in system.subsystems], sparse=True)
        U = stack_sets([s.input_set for s in system.subsystems], [s.m for s in system.subsystems], sparse=True)
        self._gx = gauge_rows(X, self.n)
        self._gu = gauge_rows(U, self.m)

    def gauge(self, x: np.ndarray, u: np.ndarray) -> float:
        """max(gauge_X(x), gauge_U(u)) for x (n,), u (m,): 0 at the origin, 1 on the boundary."""
        top = 0.0
        if self._gx.shape[0]:
            top = max(top, float((self._gx @ x).max()))
        if self._gu.shape[0]:
            top = max(top, float((self._gu @ u).max()))
        return top

    def input_gauge(self, u: np.ndarray) -> float:
        """gauge_U(u) for u (m,): 0 at the origin, 1 on the boundary of U."""
        return max(0.0, float((self._gu @ u).max())) if self._gu.shape[0] else 0.0

    def scale(self, x: np.ndarray, u: np.ndarray) -> float:
        """lambda = 1 - gauge: the terminal set around (x, u) is x + lambda X^f."""
        return 1.0 - self.gauge(x, u)

    @cached_property
    def _steady(self) -> sp.csc_matrix:
        """[(I - A), -B], shape (n, n + m): steady states are its null space."""
        A = sp.csr_matrix(self.system.A)
        B = sp.csr_matrix(self.system.B)
        return sp.hstack([sp.eye(self.n, format="csr") - A, -B], format="csc")

    @cached_property
    def _inside(self) -> tuple[sp.csc_matrix, np.ndarray]:
        """Rows G w <= g for gauge <= 1 - margin on w = [x, u], less MARGIN_ROOM for the solver's
        accuracy and the projection onto the steady states that follows."""
        G = sp.block_diag([self._gx, self._gu], format="csc")
        return G, np.full(G.shape[0], 1.0 - self.margin - MARGIN_ROOM)

    @cached_property
    def _weights(self) -> tuple[np.ndarray, float]:
        """diag of [Q, R] (n + m,), and the regularisation added to every weight."""
        d = np.concatenate([np.diag(self.system.Q), np.diag(self.system.R)]).astype(float)
        return d, REGULARISATION * max(float(d.max(initial=0.0)), 1.0)

    def target(self, request: Request) -> Target:
        """The target of ``request`` (see the module's text).

        Raises
        ------
        TargetError
            For a request of the wrong size or with an infinite value.
        RuntimeError
            If the solver fails on a problem that always has a solution (the origin is admissible).
        """
        x_req, u_req = np.asarray(request.x, float), np.asarray(request.u, float)
        if x_req.shape != (self.n,) or u_req.shape != (self.m,):
            raise TargetError(f"a request needs {self.n} state and {self.m} input entries, "
                              f"got {x_req.size} and {u_req.size}")
        if np.isinf(x_req).any() or np.isinf(u_req).any():
            raise TargetError("a requested component is infinite")
        if request.is_free:
            return Target.origin(self.n, self.m)
        wanted = np.concatenate([x_req, u_req])
        pinned = ~np.isnan(wanted)
        w = self._solve(pinned, wanted, exact=True)
        if w is not None and np.any(np.abs(w[pinned] - wanted[pinned]) > MET_TOLERANCE * np.maximum(1.0, np.abs(wanted[pinned]))):
            w = None  # the solver's answer misses the request: no steady state meets it exactly
        reachable = w is not None
        if w is None:
            nearest = self._solve(pinned, wanted, exact=False)
            if nearest is None:
                raise RuntimeError("the steady-state QP failed on the nearest admissible target")
            w = self._solve(pinned, nearest, exact=True, tolerance=PIN_TOLERANCE)
            if w is None:  # the pinned band is too thin for the solver: keep the nearest one
                w = nearest
        w = self._onto_steady_states(w)
        x, u = w[: self.n], w[self.n:]
        gap = np.where(pinned, w - np.where(pinned, wanted, 0.0), np.nan)
        return Target(x, u, self.scale(x, u), gap[: self.n], gap[self.n:], reachable)

    def load(self) -> None:
        """Load the solvers and build the steady-state QPs' matrices now: what the first target would
        do (tens of milliseconds for the imports alone), done ahead of it."""
        import clarabel  # noqa: F401 - loaded here, ahead of the first target
        import scipy.sparse.linalg  # noqa: F401 - the projection onto the steady states

        _ = self._steady, self._inside, self._weights
        pinned = np.zeros(self.n + self.m, dtype=bool)
        pinned[0] = True
        self._solve(pinned, np.zeros(self.n + self.m), exact=True)  # the solver's first solve, at the origin

    def _onto_steady_states(self, w: np.ndarray) -> np.ndarray:
        """w = [x, u] (n + m,) moved by the least amount onto x = A x + B u exactly: an interior-point
        solution meets the equality only to its tolerance, and the controllers treat the target as an
        exact steady state (an error there is an offset of the tracking)."""
        residual = self._steady @ w
        if not np.any(np.abs(residual) > STEADY_TOLERANCE * max(1.0, float(np.abs(w).max()))):
            return w
        import scipy.sparse.linalg as spla  # here: loaded only by who computes a target

        correction = spla.lsqr(self._steady, residual, atol=1e-15, btol=1e-15, iter_lim=10 * w.size)[0]
        moved: np.ndarray = w - correction
        return moved

    def _solve(self, pinned: np.ndarray, values: np.ndarray, exact: bool, tolerance: float = 0.0) -> np.ndarray | None:
        """One steady-state QP over w = [x, u] (n + m,); None when it is infeasible.

        ``exact``: the pinned components equal ``values`` (within ``tolerance`` relative), the
        objective is w' diag(Q, R) w. Otherwise the objective is the weighted distance of the
        pinned components to ``values`` (nearest admissible target).
        """
        import clarabel

        nv = self.n + self.m
        d, reg = self._weights
        if exact:
            diag = d + reg
            q = np.zeros(nv)
        else:
            weight = np.where(d > 0, d, 1.0)
            diag = np.where(pinned, weight, 0.0) + reg
            q = -2.0 * np.where(pinned, weight * np.nan_to_num(values), 0.0)
        P = sp.diags(2.0 * diag, format="csc")  # Clarabel minimises w'Pw / 2 + q'w
        blocks, rhs, cones = [self._steady], [np.zeros(self.n)], [clarabel.ZeroConeT(self.n)]
        idx = np.flatnonzero(pinned)
        sel = sp.csr_matrix((np.ones(idx.size), (np.arange(idx.size), idx)), shape=(idx.size, nv))
        G, g = self._inside
        if exact and tolerance == 0.0:
            blocks.append(sel)
            rhs.append(values[idx])
            cones.append(clarabel.ZeroConeT(idx.size))
        elif exact:
            band = tolerance * np.maximum(1.0, np.abs(values[idx]))
            blocks += [sel, -sel]
            rhs += [values[idx] + band, -(values[idx] - band)]
            cones.append(clarabel.NonnegativeConeT(2 * idx.size))
        if G.shape[0]:
            blocks.append(G)
            rhs.append(g)
            cones.append(clarabel.NonnegativeConeT(G.shape[0]))
        A = sp.vstack(blocks, format="csc")
        b = np.concatenate(rhs)
        settings = clarabel.DefaultSettings()
        settings.verbose = False
        settings.tol_gap_abs = settings.tol_gap_rel = settings.tol_feas = SOLVER_TOLERANCE
        solver = clarabel.DefaultSolver(P, q, A, b, cones, settings)
        result = solver.solve()
        status = str(result.status)
        if status in ("Solved", "AlmostSolved"):
            return np.asarray(result.x, float)
        if exact:  # infeasible, or too close to it for the solver to settle: the request is not met as asked
            return None
        raise RuntimeError(f"the steady-state QP ended with status {status}")

