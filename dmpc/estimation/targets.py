"""Offset-free steady-state targets, an affine map of the disturbance estimate.

Requested values r for some outputs (``H`` selects q of the p rows of y = C x + C_d d; the others
are free) and the disturbance estimate d^ (n_d,) give the target (x_s, u_s) of the coupled system:

    min  w' D w,   w = [x_s; u_s],   D = diag(Q, R) + eps I
    s.t. (I - A) x_s - B u_s = B_d d^
         H (C x_s + C_d d^) = r

(the target equations of Maeder, Borrelli & Morari 2009; docs/algorithm.md, "Offset-free tracking"): a steady state of
the model with the disturbance estimate whose tracked outputs, as the model predicts them, are the
request. If the loop converges, x^ -> x_s with the estimate's innovation at zero, so the measured
H y equals r: zero offset, whatever the constant disturbance or model mismatch. That argument needs
n_d = p (a constant d^ then means a zero innovation, L_d being square and invertible): the output
kind always has it, the input kind where m_i = p_i; with fewer disturbances than outputs zero
offset is not guaranteed in general. The free
components are the least x_s' Q x_s + u_s' R u_s (eps = ``REGULARISATION`` times the largest
diagonal entry makes the target unique where Q is only semidefinite, as dmpc.tracking.targets does).

**Affine, factored once.** Without active bounds the target solves the KKT system

    [[2 D, E'], [E, 0]] [w; lambda] = [0; f],   E = [[I - A, -B], [H C, 0]],   f = [B_d d^; r - H C_d d^],

linear in (r, d^). :class:`TargetMap` factors it once per request pattern (which outputs are pinned:
sparse LU, scipy.sparse.linalg.splu), and each step only builds f and back-substitutes: no QP on
the step's path. A pattern is factored on its first use; the patterns a scenario's setpoints name
can be factored ahead, at design time (:meth:`OffsetFreeTargets.pattern`). It needs E of full row
rank n + q (a DesignError says why not otherwise: more pinned outputs than inputs, an integrating
mode the inputs cannot reach, or pinned outputs that are not independent at steady state).

**Bounds.** The affine target ignores the state and input bounds. As in dmpc.tracking.targets, a
target must keep gauge_X(x_s) <= 1 - margin and gauge_U(u_s) <= 1 - margin, where gauge_S(v) =
min {t >= 0 : v in t S}; :attr:`SteadyTarget.inside` says whether the affine target does. When it
does not, the caller falls back to :meth:`OffsetFreeTargets.bounded`, the same problem with those
bounds as a QP (Clarabel).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike

from dmpc.core.errors import DesignError
from dmpc.core.system import LinearSet, stack_sets
from dmpc.estimation.model import AugmentedSystem, as_operator, numerical_rank

DEFAULT_MARGIN = 0.05
"""A target keeps this fraction of the way from the origin to every finite bound free (the
setpoint targets' margin, dmpc.tracking.targets.DEFAULT_MARGIN)."""

REGULARISATION = 1e-9
"""Added to the weights (times their largest diagonal entry, at least 1): the target is unique."""

DENSE_RANK_LIMIT = 500
"""Up to this many variables (n + m) the rank of E is checked by an SVD (milliseconds), which names
the cause of a failure; above it the factorisation is checked by the residual of one solve."""

SOLVE_TOLERANCE = 1e-8
"""A factorisation whose test solve leaves a larger relative residual counts as singular."""


def gauge_rows(linear_set: LinearSet | None, dim: int) -> sp.csr_matrix:
    """Rows a_p with gauge(v) = max(0, max_p a_p v) for ``linear_set`` = ``{lower <= H v <= upper}``.

    Each finite, nonzero side of each row gives H_r / upper_r or H_r / lower_r (the setpoint targets
    of dmpc.tracking use the same rows).

    Parameters
    ----------
    linear_set : LinearSet or None
        It must hold the origin in its interior; None adds no rows.
    dim : int
        The set's dimension.

    Returns
    -------
    scipy.sparse.csr_matrix, shape (rows, dim)
    """
    if linear_set is None:
        return sp.csr_matrix((0, dim))
    H = sp.csr_matrix(linear_set.H)
    parts = []
    for bound in (linear_set.upper, linear_set.lower):
        finite = np.isfinite(bound) & (bound != 0)
        if finite.any():
            parts.append(sp.diags(1.0 / bound[finite]) @ H[np.flatnonzero(finite)])
    return sp.vstack(parts, format="csr") if parts else sp.csr_matrix((0, dim))


@dataclass(frozen=True, eq=False)
class SteadyTarget:
    """A steady state of the model with a disturbance estimate.

    Attributes
    ----------
    x : ndarray, shape (n,)
        x_s, with x_s = A x_s + B u_s + B_d d^.
    u : ndarray, shape (m,)
        u_s.
    gauge : float
        max(gauge_X(x_s), gauge_U(u_s)): 0 at the origin, 1 on the boundary of the bounds.
    inside : bool
        gauge <= 1 - margin: the target keeps the margin to every bound.
    """

    x: np.ndarray
    u: np.ndarray
    gauge: float
    inside: bool


class TargetMap:
    """The factored KKT system of one request pattern: the target as an affine map of (r, d^).

    Parameters
    ----------
    model : AugmentedSystem
    pinned : array_like of bool, shape (p,)
        Which outputs are requested.
    weights : scipy.sparse matrix, shape (n + m, n + m)
        D, symmetric positive definite.

    Raises
    ------
    DesignError
        When E = [[I - A, -B], [H C, 0]] is not of full row rank (see the module's text).
    """

    def __init__(self, model: AugmentedSystem, pinned: ArrayLike, weights: sp.spmatrix) -> None:
        import scipy.sparse.linalg as spla  # loaded by who computes targets (it loads scipy.linalg)

        self.model = model
        self.pinned = np.asarray(pinned, dtype=bool).reshape(-1)
        if self.pinned.size != model.p:
            raise ValueError(f"a request pattern needs {model.p} entries, got {self.pinned.size}")
        self.rows = np.flatnonzero(self.pinned)
        n, m, q = model.n, model.m, self.rows.size
        self.n, self.m, self.q = n, m, q
        system = model.system
        HC = sp.csr_matrix(model.C[self.rows])
        self._HCd = as_operator(model.Cd[self.rows])
        self._Bd = as_operator(model.Bd)
        E = sp.vstack([sp.hstack([sp.eye(n) - sp.csr_matrix(system.A), -sp.csr_matrix(system.B)]),
                       sp.hstack([HC, sp.csr_matrix((q, m))])], format="csc")
        self._check_rank(E)
        K = sp.bmat([[2.0 * sp.csc_matrix(weights), E.T], [E, None]], format="csc")
        try:
            self._lu = spla.splu(K)
        except RuntimeError as exc:  # exactly singular
            raise DesignError(self._rank_message(None) + f" ({exc})") from None
        probe = np.random.default_rng(0).standard_normal(K.shape[0])
        residual = np.linalg.norm(K @ self._lu.solve(probe) - probe) / np.linalg.norm(probe)
        if not residual <= SOLVE_TOLERANCE:
            raise DesignError(self._rank_message(None) + f" (the factorisation's residual is {residual:.2g})")

    def _outputs(self, rows: np.ndarray) -> str:
        model = self.model
        names = []
        for r in rows[:6]:
            i = int(np.searchsorted(model.output_offsets, r, side="right") - 1)
            names.append(f"y{int(r - model.output_offsets[i])} of {model.parts[i].name}")
        return ", ".join(names) + (f" and {rows.size - 6} more" if rows.size > 6 else "")

    def _rank_message(self, rank: int | None) -> str:
        shown = f" = {rank}" if rank is not None else ""
        return (f"estimation: targets: the pinned outputs ({self._outputs(self.rows) or 'none'}) cannot be held at "
                f"independent values at steady state: rank [[I - A, -B], [H C, 0]]{shown} < n + q = "
                f"{self.n + self.q}; pin fewer outputs, or others")

    def _check_rank(self, E: sp.csc_matrix) -> None:
        n, m, q = self.n, self.m, self.q
        if q > m:
            raise DesignError(f"estimation: targets: {q} outputs pinned ({self._outputs(self.rows)}) but the system "
                              f"has {m} input(s): at most {m} outputs can be held at independent values; pin fewer")
        if n + m > DENSE_RANK_LIMIT:
            return
        dense = E.toarray()
        steady = numerical_rank(dense[:n])
        if steady < n:
            raise DesignError(
                f"estimation: targets: the model has no steady state for some disturbance estimates: rank "
                f"[I - A, -B] = {steady} < n = {n} (an integrating mode the inputs cannot reach)")
        rank = numerical_rank(dense)
        if rank < n + q:
            raise DesignError(self._rank_message(rank))

    def solve(self, r: ArrayLike, d_hat: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """The target by back-substitution.

        Parameters
        ----------
        r : array_like, shape (q,)
            The requested values of the pinned outputs, in output order.
        d_hat : array_like, shape (n_d,)
            The disturbance estimate.

        Returns
        -------
        x_s : ndarray, shape (n,)
        u_s : ndarray, shape (m,)
        """
        d = np.asarray(d_hat, dtype=float).reshape(-1)
        rhs = np.zeros(2 * self.n + self.m + self.q)
        rhs[self.n + self.m: 2 * self.n + self.m] = self._Bd @ d
        rhs[2 * self.n + self.m:] = np.asarray(r, dtype=float).reshape(-1) - self._HCd @ d
        w = self._lu.solve(rhs)
        return w[: self.n], w[self.n: self.n + self.m]

    def affine(self) -> tuple[np.ndarray, np.ndarray]:
        """The map's matrices: [x_s; u_s] = G_r r + G_d d^.

        Returns
        -------
        G_r : ndarray, shape (n + m, q)
        G_d : ndarray, shape (n + m, n_d)
        """
        nv, n = self.n + self.m, self.n
        size = 2 * n + self.m + self.q
        R = np.zeros((size, self.q))
        R[nv + n:] = np.eye(self.q)
        Dm = np.zeros((size, self.model.nd))
        Dm[nv: nv + n] = self.model.Bd
        Dm[nv + n:] = -self.model.Cd[self.rows]
        Gr = self._lu.solve(R) if self.q else np.zeros((size, 0))
        Gd = self._lu.solve(Dm) if self.model.nd else np.zeros((size, 0))
        return Gr[:nv], Gd[:nv]


class OffsetFreeTargets:
    """The offset-free targets of one augmented system: a factored map per request pattern, and the bounds.

    Parameters
    ----------
    model : AugmentedSystem
    margin : float
        In (0, 1): a target keeps gauge <= 1 - margin in X and U.
    """

    def __init__(self, model: AugmentedSystem, margin: float = DEFAULT_MARGIN) -> None:
        if not 0.0 < margin < 1.0:
            raise ValueError(f"the target margin must lie in (0, 1), got {margin}")
        self.model = model
        self.margin = float(margin)
        system = model.system
        X = stack_sets([s.state_set for s in system.subsystems], [s.n for s in system.subsystems], sparse=True)
        U = stack_sets([s.input_set for s in system.subsystems], [s.m for s in system.subsystems], sparse=True)
        self._gx = as_operator(gauge_rows(X, model.n))
        self._gu = as_operator(gauge_rows(U, model.m))
        self._maps: dict[bytes, TargetMap] = {}

    @cached_property
    def weights(self) -> sp.csc_matrix:
        """D = diag(Q, R) + eps I, shape (n + m, n + m) (the module's text)."""
        system = self.model.system
        D = sp.block_diag([sp.csr_matrix(s.Q) for s in system.subsystems]
                          + [sp.csr_matrix(s.R) for s in system.subsystems], format="csc")
        top = max(float(np.abs(D.diagonal()).max(initial=0.0)), 1.0)
        out: sp.csc_matrix = (D + D.T) / 2.0 + REGULARISATION * top * sp.eye(D.shape[0], format="csc")
        return out

    def pattern(self, pinned: ArrayLike) -> TargetMap:
        """The factored map of a request pattern (factored on first use, then kept).

        Parameters
        ----------
        pinned : array_like of bool, shape (p,)
            Which outputs are requested.
        """
        key = np.asarray(pinned, dtype=bool).reshape(-1)
        found = self._maps.get(key.tobytes())
        if found is None:
            found = self._maps[key.tobytes()] = TargetMap(self.model, key, self.weights)
        return found

    def _request(self, request: ArrayLike, d_hat: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        r = np.asarray(request, dtype=float).reshape(-1)
        d = np.asarray(d_hat, dtype=float).reshape(-1)
        if r.size != self.model.p or d.size != self.model.nd:
            raise ValueError(f"a request needs {self.model.p} output entries (NaN where free) and a disturbance "
                             f"estimate of {self.model.nd}, got {r.size} and {d.size}")
        if np.isinf(r).any() or not np.isfinite(d).all():
            raise ValueError("a requested output is infinite or the disturbance estimate is not finite")
        return r, d

    def target(self, request: ArrayLike, d_hat: ArrayLike) -> SteadyTarget:
        """The affine target of a request (no bounds; :attr:`SteadyTarget.inside` says whether it keeps them).

        Parameters
        ----------
        request : array_like, shape (p,)
            The requested outputs, NaN where free.
        d_hat : array_like, shape (n_d,)
            The disturbance estimate.

        Raises
        ------
        ValueError
            A request or estimate of the wrong size, an infinite request, a non-finite estimate.
        DesignError
            A request pattern that cannot be met (:class:`TargetMap`).
        """
        r, d = self._request(request, d_hat)
        pinned = ~np.isnan(r)
        x, u = self.pattern(pinned).solve(r[pinned], d)
        return self._steady(x, u)

    def gauge(self, x: np.ndarray, u: np.ndarray) -> float:
        """max(gauge_X(x), gauge_U(u)) for x (n,), u (m,): 0 at the origin, 1 on the bounds' boundary."""
        top = 0.0
        if self._gx.shape[0]:
            top = max(top, float((self._gx @ x).max()))
        if self._gu.shape[0]:
            top = max(top, float((self._gu @ u).max()))
        return top

    def _steady(self, x: np.ndarray, u: np.ndarray) -> SteadyTarget:
        g = self.gauge(x, u)
        return SteadyTarget(x, u, g, g <= 1.0 - self.margin)

    def bounded(self, request: ArrayLike, d_hat: ArrayLike) -> SteadyTarget | None:
        """The target with the bounds: the module's QP with gauge <= 1 - margin in X and U (Clarabel).

        The fallback when the affine target is not ``inside``; not for the step's critical path.

        Parameters
        ----------
        request : array_like, shape (p,)
            The requested outputs, NaN where free.
        d_hat : array_like, shape (n_d,)
            The disturbance estimate.

        Returns
        -------
        SteadyTarget or None
            None when no steady state meets the request within the bounds (the caller chooses
            what to do then, e.g. the nearest admissible target).
        """
        import clarabel

        r, d = self._request(request, d_hat)
        pinned = np.flatnonzero(~np.isnan(r))
        model, system = self.model, self.model.system
        n, m = model.n, model.m
        steady = sp.hstack([sp.eye(n) - sp.csr_matrix(system.A), -sp.csr_matrix(system.B)], format="csr")
        HC = sp.hstack([sp.csr_matrix(model.C[pinned]), sp.csr_matrix((pinned.size, m))], format="csr")
        G = sp.block_diag([sp.csr_matrix(self._gx), sp.csr_matrix(self._gu)], format="csr")
        A = sp.vstack([steady, HC, G], format="csc")
        b = np.concatenate([model.Bd @ d, r[pinned] - model.Cd[pinned] @ d, np.full(G.shape[0], 1.0 - self.margin)])
        cones: list[Any] = [clarabel.ZeroConeT(n + pinned.size)]
        if G.shape[0]:
            cones.append(clarabel.NonnegativeConeT(G.shape[0]))
        settings = clarabel.DefaultSettings()
        settings.verbose = False
        settings.tol_gap_abs = settings.tol_gap_rel = settings.tol_feas = 1e-10
        P = sp.triu(2.0 * self.weights, format="csc")  # Clarabel minimises w'Pw / 2 + q'w, P upper triangular
        result = clarabel.DefaultSolver(P, np.zeros(n + m), A, b, cones, settings).solve()
        if str(result.status) not in ("Solved", "AlmostSolved"):
            return None
        w = np.asarray(result.x, float)
        return self._steady(w[:n], w[n:])


__all__ = ["DEFAULT_MARGIN", "OffsetFreeTargets", "SteadyTarget", "TargetMap", "gauge_rows"]
