"""The coupled linear system: subsystems, couplings, constraint sets and the graph.

Everything here is pure data with derived global matrices; no I/O.
Subsystems are indexed 0..M-1 internally; ``Subsystem.name`` keeps the user's id.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike


@dataclass(frozen=True)
class LinearSet:
    """A two-sided polyhedron ``{x : lower <= H x <= upper}``.

    A box is ``H = I``; a one-sided polytope ``H x <= h`` has ``lower = -inf``.

    Attributes
    ----------
    H : ndarray, shape (r, n)
    lower, upper : ndarray, shape (r,)
        Entries may be infinite; ``lower <= upper`` row by row.
    """

    H: np.ndarray
    lower: np.ndarray
    upper: np.ndarray

    @classmethod
    def box(cls, lower: ArrayLike, upper: ArrayLike) -> "LinearSet":
        """The box ``lower <= x <= upper`` (each shape (d,); infinite entries for unbounded sides)."""
        lo = np.asarray(lower, dtype=float)
        hi = np.asarray(upper, dtype=float)
        return cls(np.eye(lo.size), lo, hi)

    @classmethod
    def polytope(cls, H: ArrayLike, h: ArrayLike) -> "LinearSet":
        """The polytope ``H x <= h``: H (r, d), h (r,)."""
        bounds = np.asarray(h, dtype=float)
        return cls(np.atleast_2d(np.asarray(H, dtype=float)), np.full(bounds.size, -np.inf), bounds)

    @property
    def dim(self) -> int:
        return int(self.H.shape[1])

    @property
    def is_box(self) -> bool:
        return self.H.shape[0] == self.H.shape[1] and np.array_equal(self.H, np.eye(self.H.shape[0]))

    def one_sided(self) -> tuple[np.ndarray, np.ndarray]:
        """The set as ``G x <= g`` with only the finite sides: row r's upper side, then its lower one.

        Returns
        -------
        G : ndarray, shape (q, n)
            A CSR matrix when H is sparse.
        g : ndarray, shape (q,)
        """
        r = self.H.shape[0]
        kept = np.column_stack([np.isfinite(self.upper), np.isfinite(self.lower)]).ravel()  # (2r,)
        rows = np.repeat(np.arange(r), 2)[kept]
        sign = np.tile([1.0, -1.0], r)[kept]
        g = np.column_stack([self.upper, -self.lower]).ravel()[kept]
        if sp.issparse(self.H):
            return (sp.diags(sign) @ sp.csr_matrix(self.H)[rows]).tocsr(), g
        return sign[:, None] * self.H[rows], g

    def excess(self, values: np.ndarray, tolerance: float = 0.0) -> np.ndarray:
        """How far each row of ``values`` lies outside the set.

        Each finite bound is first moved outwards by ``tolerance * max(1, |bound|)``; infinite
        bounds never bind.

        Parameters
        ----------
        values : ndarray, shape (K, d)
        tolerance : float

        Returns
        -------
        ndarray, shape (K,)
            max over the set's rows of (H v - upper, lower - H v): negative strictly inside, NaN
            for a row with a NaN value, -inf for a set without rows.
        """
        if values.shape[0] == 0:
            return np.zeros(0)
        return np.asarray(self._excess(values, tolerance, axis=1))

    def largest_excess(self, values: np.ndarray, tolerance: float = 0.0) -> float:
        """The largest entry of :meth:`excess` of ``values`` with ``tolerance`` (-inf when there are no
        values): one number, as the plant needs it for every plan it receives."""
        if values.shape[0] == 0:
            return -math.inf
        return float(self._excess(values, tolerance, axis=None))

    def _excess(self, values: np.ndarray, tolerance: float, axis: int | None) -> Any:
        """The rows' excess: an array (K,) for ``axis=1``, one number for ``axis=None``."""
        HT, lower, upper, finite = self._bounds(tolerance)
        if lower.size == 0:
            return np.full(values.shape[0], -np.inf) if axis else -math.inf
        Hv = values if HT is None else values @ HT
        if finite:
            return np.maximum(Hv - upper, lower - Hv).max(axis=axis)
        # an infinite value against an infinite bound gives NaN on that side only: fmax takes the other side
        with np.errstate(invalid="ignore"):
            return np.fmax(Hv - upper, lower - Hv).max(axis=axis)

    def _bounds(self, tolerance: float) -> tuple[np.ndarray | None, np.ndarray, np.ndarray, bool]:
        """H^T (None for a box), the bounds moved out by ``tolerance``, and whether all are
        finite; kept per tolerance, since the plant checks every plan against its input set."""
        entry = self._widened.get(tolerance)
        if entry is None:
            lower, upper = self.lower, self.upper
            if tolerance:
                lower = lower - tolerance * np.maximum(1.0, np.abs(lower))
                upper = upper + tolerance * np.maximum(1.0, np.abs(upper))
            finite = bool(np.isfinite(lower).all() and np.isfinite(upper).all())
            entry = self._widened[tolerance] = (None if self.is_box else self.H.T, lower, upper, finite)
        return entry

    @cached_property
    def _widened(self) -> dict[float, tuple[np.ndarray | None, np.ndarray, np.ndarray, bool]]:
        return {}

    def contains(self, x: np.ndarray, tol: float = 1e-9) -> bool:
        """Whether x (d,) meets every row of the set, up to ``tol``."""
        v = self.H @ x
        return bool(np.all(v <= self.upper + tol) and np.all(v >= self.lower - tol))


@dataclass(frozen=True)
class Subsystem:
    """One subsystem ``x_i+ = A x_i + B u_i + coupling``.

    Attributes
    ----------
    name : str
        The user's identifier (used in keys, CLI ``--id`` and records).
    A : ndarray, shape (n_i, n_i)
    B : ndarray, shape (n_i, m_i)
    Q : ndarray, shape (n_i, n_i)
    R : ndarray, shape (m_i, m_i)
    x0 : ndarray, shape (n_i,)
    input_set : LinearSet of dimension m_i
    state_set : LinearSet of dimension n_i, or None for R^n_i
    C : ndarray, shape (p_i, n_i), or None
        What the plant measures of the subsystem, y_i = C x_i; None (the default) is the identity:
        every state is measured, y_i = x_i.
    x_op : ndarray, shape (n_i,), or None
        The state of the operating point in the plant's own units: the model, x0 and the sets are in
        deviations from it, the records and the plant's own function in the plant's units
        (``x_op + x``). None (the default): the plant's units are the model's (zeros).
    u_op : ndarray, shape (m_i,), or None
        The operating point's inputs, the same way.
    state_margin : ndarray, shape (n_i,), or None
        Room kept for the estimation error (``estimation.margin``): ``state_set`` is the plant's
        state set moved in by it (what the controllers keep the estimate in), and
        :attr:`plant_state_set` the plant's own. None: no margin, the two are one.
    """

    name: str
    A: np.ndarray
    B: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    x0: np.ndarray
    input_set: LinearSet
    state_set: LinearSet | None = None
    C: np.ndarray | None = None
    x_op: np.ndarray | None = None
    u_op: np.ndarray | None = None
    state_margin: np.ndarray | None = None

    @property
    def n(self) -> int:
        return int(self.A.shape[0])

    @property
    def m(self) -> int:
        return int(self.B.shape[1])

    @property
    def p(self) -> int:
        """The number of measured outputs p_i (n_i when C is None)."""
        return self.n if self.C is None else int(self.C.shape[0])

    @property
    def output_matrix(self) -> np.ndarray:
        """C_i, shape (p_i, n_i): the identity when C is None."""
        return np.eye(self.n) if self.C is None else np.asarray(self.C, dtype=float)

    @property
    def plant_state_set(self) -> LinearSet | None:
        """The set the plant's state must stay in: ``state_set`` without the estimation margin (each row's
        bounds moved out by sum_j |H_rj| margin_j)."""
        if self.state_margin is None or self.state_set is None:
            return self.state_set
        widen = np.abs(np.asarray(self.state_set.H, dtype=float)) @ self.state_margin
        return LinearSet(self.state_set.H, self.state_set.lower - widen, self.state_set.upper + widen)

    @property
    def state_offset(self) -> np.ndarray:
        """x_op, shape (n_i,): the operating point's state in the plant's units (zeros without one)."""
        return np.zeros(self.n) if self.x_op is None else np.asarray(self.x_op, dtype=float)

    @property
    def input_offset(self) -> np.ndarray:
        """u_op, shape (m_i,): the operating point's inputs in the plant's units (zeros without one)."""
        return np.zeros(self.m) if self.u_op is None else np.asarray(self.u_op, dtype=float)

    @property
    def operating_output(self) -> np.ndarray:
        """C_i x_op, shape (p_i,): the operating point's outputs in the plant's units (zeros without one)."""
        y: np.ndarray = self.output_matrix @ self.state_offset
        return y


@dataclass(frozen=True)
class Coupling:
    """Influence of subsystem ``source`` on subsystem ``target``.

    ``x_target+ += A x_source + B u_source``.

    Attributes
    ----------
    target, source : int
        0-based subsystem indices, ``target != source``.
    A : ndarray, shape (n_target, n_source)
    B : ndarray, shape (n_target, m_source)
    """

    target: int
    source: int
    A: np.ndarray
    B: np.ndarray


@dataclass(frozen=True)
class CoupledSystem:
    """M subsystems, their couplings and the (undirected) communication graph.

    Attributes
    ----------
    subsystems : tuple of Subsystem
    couplings : tuple of Coupling
    edges : tuple of (int, int)
        Undirected graph edges (i < j). Every coupling is an edge; extra edges are allowed.
    """

    subsystems: tuple[Subsystem, ...]
    couplings: tuple[Coupling, ...] = ()
    edges: tuple[tuple[int, int], ...] = field(default=())

    def __post_init__(self) -> None:
        all_edges = {tuple(sorted(e)) for e in self.edges}
        all_edges |= {tuple(sorted((c.target, c.source))) for c in self.couplings}
        object.__setattr__(self, "edges", tuple(sorted(all_edges)))

    @property
    def M(self) -> int:
        return len(self.subsystems)

    @cached_property
    def neighbours(self) -> tuple[tuple[int, ...], ...]:
        """``N_i`` for each i, sorted, containing i itself."""
        nb = [{i} for i in range(self.M)]
        for i, j in self.edges:
            nb[i].add(j)
            nb[j].add(i)
        return tuple(tuple(sorted(s)) for s in nb)

    @cached_property
    def state_offsets(self) -> np.ndarray:
        """Start of each subsystem's block in the global state, shape (M+1,)."""
        return np.concatenate([[0], np.cumsum([s.n for s in self.subsystems])]).astype(int)

    @cached_property
    def input_offsets(self) -> np.ndarray:
        """Start of each subsystem's block in the global input, shape (M+1,)."""
        return np.concatenate([[0], np.cumsum([s.m for s in self.subsystems])]).astype(int)

    def xs(self, i: int) -> slice:
        """The slice of subsystem i's states in the global state."""
        return slice(self.state_offsets[i], self.state_offsets[i + 1])

    def us(self, i: int) -> slice:
        """The slice of subsystem i's inputs in the global input."""
        return slice(self.input_offsets[i], self.input_offsets[i + 1])

    @cached_property
    def output_offsets(self) -> np.ndarray:
        """Start of each subsystem's block in the global output y = C x, shape (M+1,)."""
        return np.concatenate([[0], np.cumsum([s.p for s in self.subsystems])]).astype(int)

    def ys(self, i: int) -> slice:
        """The slice of subsystem i's outputs in the global output."""
        return slice(int(self.output_offsets[i]), int(self.output_offsets[i + 1]))

    @property
    def p(self) -> int:
        """The number of measured outputs (n when every subsystem measures its whole state)."""
        return int(self.output_offsets[-1])

    @cached_property
    def C(self) -> np.ndarray:
        """Global measurement matrix, block diagonal, shape (p, n): y = C x."""
        return block_diag(*[s.output_matrix for s in self.subsystems])

    @property
    def n(self) -> int:
        return int(self.state_offsets[-1])

    @property
    def m(self) -> int:
        return int(self.input_offsets[-1])

    def coupling(self, target: int, source: int) -> tuple[np.ndarray, np.ndarray]:
        """``(A_ij, B_ij)`` of subsystem i = ``target`` from j = ``source``, with zeros where there is no coupling."""
        for c in self.couplings:
            if c.target == target and c.source == source:
                return c.A, c.B
        t, s = self.subsystems[target], self.subsystems[source]
        return np.zeros((t.n, s.n)), np.zeros((t.n, s.m))

    @cached_property
    def A(self) -> np.ndarray:
        """Global state matrix, shape (n, n)."""
        A = np.zeros((self.n, self.n))
        for i, s in enumerate(self.subsystems):
            A[self.xs(i), self.xs(i)] = s.A
        for c in self.couplings:
            A[self.xs(c.target), self.xs(c.source)] += c.A
        return A

    @cached_property
    def B(self) -> np.ndarray:
        """Global input matrix, shape (n, m)."""
        B = np.zeros((self.n, self.m))
        for i, s in enumerate(self.subsystems):
            B[self.xs(i), self.us(i)] = s.B
        for c in self.couplings:
            B[self.xs(c.target), self.us(c.source)] += c.B
        return B

    @cached_property
    def Q(self) -> np.ndarray:
        return block_diag(*[s.Q for s in self.subsystems])

    @cached_property
    def R(self) -> np.ndarray:
        return block_diag(*[s.R for s in self.subsystems])

    @cached_property
    def x0(self) -> np.ndarray:
        return np.concatenate([s.x0 for s in self.subsystems])

    @cached_property
    def has_operating_point(self) -> bool:
        """Some subsystem gives an operating point: the plant's units are not the model's."""
        return any(s.x_op is not None or s.u_op is not None for s in self.subsystems)

    @cached_property
    def state_offset(self) -> np.ndarray:
        """The stacked x_op, shape (n,): a state in the plant's units is ``state_offset + x``."""
        return np.concatenate([s.state_offset for s in self.subsystems])

    @cached_property
    def input_offset(self) -> np.ndarray:
        """The stacked u_op, shape (m,): an input in the plant's units is ``input_offset + u``."""
        return np.concatenate([s.input_offset for s in self.subsystems])

    @cached_property
    def _state_parts(self) -> tuple[slice, ...]:
        return tuple(self.xs(i) for i in range(self.M))

    @cached_property
    def _neighbour_counts(self) -> tuple[int, ...]:
        return tuple(len(self.neighbours[i]) for i in range(self.M))

    def split_state(self, x: np.ndarray) -> list[np.ndarray]:
        """The global state x (n,) as each subsystem's part, in order."""
        return [x[part] for part in self._state_parts]

    def split_input(self, u: np.ndarray) -> list[np.ndarray]:
        """The global input u (m,) as each subsystem's part, in order."""
        return [u[self.us(i)] for i in range(self.M)]

    def spread(self, x: np.ndarray) -> float:
        """S(x) = sum_i ||x_i||^2 / |N_i| (|N_i| counts i itself) for the global state x (n,)."""
        return float(sum(x[part] @ x[part] / count for part, count in zip(self._state_parts, self._neighbour_counts)))




def block_diag(*blocks: np.ndarray) -> np.ndarray:
    """Dense block-diagonal matrix.

    Built with scipy.sparse (already loaded for OSQP) so that agent processes do not import
    scipy.linalg, which costs about 8 MB per process.
    """
    return sp.block_diag(blocks, format="csr").toarray() if blocks else np.zeros((0, 0))


def stack_sets(sets: list[LinearSet | None], dims: list[int], sparse: bool = False) -> LinearSet | None:
    """The block-diagonal stack of per-subsystem sets, e.g. U = U_1 x ... x U_M.

    Parameters
    ----------
    sets : list of LinearSet or None
        None for a subsystem without a set: it adds no rows.
    dims : list of int
        The dimension of each subsystem's part (its set's ``dim``).
    sparse : bool
        H as a CSR matrix (for large systems) instead of a dense array.

    Returns
    -------
    LinearSet, with H of shape (sum of rows, sum of dims); None when no subsystem has a set.
    """
    if all(s is None for s in sets):
        return None
    full = [s if s is not None else LinearSet(np.zeros((0, d)), np.zeros(0), np.zeros(0)) for s, d in zip(sets, dims)]
    blocks = [s.H for s in full]
    H = sp.block_diag(blocks, format="csr") if sparse else block_diag(*blocks)
    return LinearSet(H, np.concatenate([s.lower for s in full]), np.concatenate([s.upper for s in full]))


def project_onto(linear_set: LinearSet, u: np.ndarray) -> np.ndarray:
    """Euclidean projection of u onto ``linear_set`` (clip for boxes, a small QP otherwise)."""
    if linear_set.is_box:
        clipped: np.ndarray = np.clip(u, linear_set.lower, linear_set.upper)
        return clipped
    if linear_set.contains(u):
        return np.asarray(u, float)
    import osqp
    import scipy.sparse as sp

    n = u.size
    solver = osqp.OSQP()
    solver.setup(P=sp.eye(n, format="csc"), q=-np.asarray(u, float), A=sp.csc_matrix(linear_set.H),
                 l=linear_set.lower, u=linear_set.upper, verbose=False, polishing=False,
                 eps_abs=1e-10, eps_rel=1e-10, max_iter=100000)
    return np.asarray(solver.solve().x, float)


def box_hull(H: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-coordinate bounds of ``{v : lower <= H v <= upper}`` (infinite where unbounded), by LPs.

    Parameters
    ----------
    H : ndarray, shape (r, d)
    lower, upper : ndarray, shape (r,)
        Entries may be infinite.

    Returns
    -------
    lo, hi : ndarray, shape (d,)
    """
    from scipy.optimize import linprog

    finite_up, finite_lo = np.isfinite(upper), np.isfinite(lower)
    A = np.vstack([H[finite_up], -H[finite_lo]])
    b = np.concatenate([upper[finite_up], -lower[finite_lo]])
    dim = H.shape[1]
    lo, hi = np.full(dim, -np.inf), np.full(dim, np.inf)
    for j in range(dim):
        for sign, target in ((1.0, lo), (-1.0, hi)):
            c = np.zeros(dim)
            c[j] = sign
            res = linprog(c, A_ub=A if A.size else None, b_ub=b if A.size else None,
                          bounds=[(None, None)] * dim, method="highs")
            if res.status == 0:
                target[j] = sign * res.fun
    return lo, hi
