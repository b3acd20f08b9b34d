"""The coupled linear system: subsystems, couplings, constraint sets and the graph.

Everything here is pure data with derived global matrices; no I/O.
Subsystems are indexed 0..M-1 internally; ``Subsystem.name`` keeps the user's id.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import scipy.sparse as sp


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
    def box(cls, lower, upper) -> "LinearSet":
        lo = np.asarray(lower, dtype=float)
        hi = np.asarray(upper, dtype=float)
        return cls(np.eye(lo.size), lo, hi)

    @classmethod
    def polytope(cls, H, h) -> "LinearSet":
        h = np.asarray(h, dtype=float)
        return cls(np.atleast_2d(np.asarray(H, dtype=float)), np.full(h.size, -np.inf), h)

    @property
    def dim(self) -> int:
        return self.H.shape[1]

    @property
    def is_box(self) -> bool:
        return self.H.shape[0] == self.H.shape[1] and np.array_equal(self.H, np.eye(self.H.shape[0]))

    def one_sided(self) -> tuple[np.ndarray, np.ndarray]:
        """The set as ``G x <= g`` with only finite rows.

        Returns
        -------
        G : ndarray, shape (q, n)
        g : ndarray, shape (q,)
        """
        rows, rhs = [], []
        for r in range(self.H.shape[0]):
            if np.isfinite(self.upper[r]):
                rows.append(self.H[r])
                rhs.append(self.upper[r])
            if np.isfinite(self.lower[r]):
                rows.append(-self.H[r])
                rhs.append(-self.lower[r])
        if not rows:
            return np.zeros((0, self.dim)), np.zeros(0)
        return np.array(rows), np.array(rhs)

    def box_radius(self) -> np.ndarray:
        """Half-widths ``ubar`` such that ``{|x| <= ubar}`` contains the set (boxes only).

        Returns
        -------
        ndarray, shape (n,)
        """
        if not self.is_box:
            raise ValueError("box_radius is defined for box sets only")
        return np.maximum(np.abs(self.lower), np.abs(self.upper))

    def contains(self, x: np.ndarray, tol: float = 1e-9) -> bool:
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
    """

    name: str
    A: np.ndarray
    B: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    x0: np.ndarray
    input_set: LinearSet
    state_set: LinearSet | None = None

    @property
    def n(self) -> int:
        return self.A.shape[0]

    @property
    def m(self) -> int:
        return self.B.shape[1]


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
        return slice(self.state_offsets[i], self.state_offsets[i + 1])

    def us(self, i: int) -> slice:
        return slice(self.input_offsets[i], self.input_offsets[i + 1])

    @property
    def n(self) -> int:
        return int(self.state_offsets[-1])

    @property
    def m(self) -> int:
        return int(self.input_offsets[-1])

    def coupling(self, target: int, source: int) -> tuple[np.ndarray, np.ndarray]:
        """``(A_ij, B_ij)`` with zeros where there is no coupling."""
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

    def split_state(self, x: np.ndarray) -> list[np.ndarray]:
        return [x[self.xs(i)] for i in range(self.M)]

    def split_input(self, u: np.ndarray) -> list[np.ndarray]:
        return [u[self.us(i)] for i in range(self.M)]

    def spread(self, x: np.ndarray) -> float:
        """S(x) = sum_i ||x_i||^2 / |N_i| (|N_i| counts i itself) for the global state x (n,)."""
        parts = self.split_state(x)
        return float(sum(parts[i] @ parts[i] / len(self.neighbours[i]) for i in range(self.M)))




def block_diag(*blocks: np.ndarray) -> np.ndarray:
    """Dense block-diagonal matrix.

    Built with scipy.sparse (already loaded for OSQP) so that agent processes do not import
    scipy.linalg, which costs about 8 MB per process.
    """
    return sp.block_diag(blocks, format="csr").toarray() if blocks else np.zeros((0, 0))


def project_onto(linear_set: LinearSet, u: np.ndarray) -> np.ndarray:
    """Euclidean projection of u onto a LinearSet (clip for boxes, a small QP otherwise)."""
    if linear_set.is_box:
        return np.clip(u, linear_set.lower, linear_set.upper)
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
