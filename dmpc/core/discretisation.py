"""Zero-order-hold discretisation of a continuous-time coupled system (``time: continuous``).

The continuous model is dx_i/dt = A_ii x_i + B_ii u_i + sum_j (A_ij x_j + B_ij u_j), held in a
:class:`~dmpc.core.system.CoupledSystem` whose matrices are the continuous ones. Two discrete models:

- ``local-zoh``: each subsystem's exact zero-order hold, with its neighbours' states x_j and
  inputs u_j treated as further inputs held constant over the period. With
  ``Gamma_i = int_0^dt exp(A_ii s) ds``:
  ``A_ii^d = exp(A_ii dt)``, ``B_ii^d = Gamma_i B_ii``, ``A_ij^d = Gamma_i A_ij``,
  ``B_ij^d = Gamma_i B_ij``. The coupling graph is kept. The approximation is that x_j moves
  during the period: the result differs from the exact discretisation by O(dt^2) in the
  coupling blocks (the neighbours' own dynamics acting within the period), and it has no
  entries between subsystems two links apart.
- ``exact-zoh``: ``exp([[A, B], [0, 0]] dt)`` of the whole system. It is exact, but the
  exponential spreads the coupling along paths of the graph: subsystems two links apart get
  entries of order dt^2 (the "fill-in"). The controllers can only use blocks inside the graph,
  so the fill-in is measured and, when accepted, dropped (:func:`restrict_to_graph`).

Pure numerics: no I/O.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, TypedDict

import numpy as np

from dmpc.core.errors import DmpcError
from dmpc.core.system import CoupledSystem, Coupling, Subsystem

METHODS = ("local-zoh", "exact-zoh")


def zoh(A: np.ndarray, B: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact zero-order hold of dx/dt = A x + B u over ``dt``.

    Parameters
    ----------
    A : ndarray, shape (n, n)
    B : ndarray, shape (n, q)
    dt : float
        Seconds, > 0.

    Returns
    -------
    Ad : ndarray, shape (n, n)
        exp(A dt).
    Bd : ndarray, shape (n, q)
        int_0^dt exp(A s) ds B.
    """
    n, q = B.shape
    block = np.zeros((n + q, n + q))
    block[:n, :n] = A
    block[:n, n:] = B
    from scipy.linalg import expm  # here: only continuous-time models need it, and scipy.linalg costs memory

    E = expm(block * dt)
    return E[:n, :n], E[:n, n:]


def local_zoh(system: CoupledSystem, dt: float) -> CoupledSystem:
    """The ``local-zoh`` discrete model of a continuous-time system (same subsystems, couplings, graph).

    Parameters
    ----------
    system : CoupledSystem
        Continuous-time matrices.
    dt : float

    Returns
    -------
    CoupledSystem
        Discrete-time matrices; names, sets, weights and x0 unchanged.
    """
    subsystems, couplings = [], []
    for i, s in enumerate(system.subsystems):
        incoming = [c for c in system.couplings if c.target == i]
        held = np.hstack([s.B] + [np.hstack([c.A, c.B]) for c in incoming])
        Ad, Gd = zoh(s.A, held, dt)
        subsystems.append(_with_matrices(s, Ad, Gd[:, :s.m]))
        col = s.m
        for c in incoming:
            n_j, m_j = c.A.shape[1], c.B.shape[1]
            couplings.append((c, Gd[:, col:col + n_j], Gd[:, col + n_j:col + n_j + m_j]))
            col += n_j + m_j
    order = {(c.target, c.source): k for k, c in enumerate(system.couplings)}
    couplings.sort(key=lambda item: order[(item[0].target, item[0].source)])
    return CoupledSystem(subsystems=tuple(subsystems),
                         couplings=tuple(Coupling(c.target, c.source, A, B) for c, A, B in couplings),
                         edges=system.edges)


def exact_zoh(system: CoupledSystem, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """The exact zero-order hold of the whole coupled ``system`` with sampling period ``dt``.

    Returns
    -------
    A : ndarray, shape (n, n)
    B : ndarray, shape (n, m)
    """
    return zoh(system.A, system.B, dt)


def allowed_pairs(system: CoupledSystem) -> set[tuple[int, int]]:
    """Ordered pairs (target, source) whose blocks the controllers of ``system`` can use: the
    couplings and both directions of every communication edge (agents on an edge exchange plans)."""
    pairs = {(c.target, c.source) for c in system.couplings}
    for i, j in system.edges:
        pairs |= {(i, j), (j, i)}
    return pairs


class FillInBlock(TypedDict):
    """One block of :class:`FillIn`: ``matrix`` ("A" or "B") of subsystem ``target`` (row) and
    ``source`` (column), and its ``largest`` absolute entry."""

    target: str
    source: str
    matrix: str
    largest: float


@dataclass(frozen=True)
class FillIn:
    """Entries of a discrete [A B] outside the coupling graph.

    Attributes
    ----------
    largest : float
        The largest absolute entry outside the graph (0 if none).
    relative : float
        ``largest`` over the largest absolute entry of [A B].
    blocks : list of dict
        One per block with a nonzero entry, largest first: ``target``, ``source`` (names),
        ``matrix`` ("A" or "B") and ``largest``.
    """

    largest: float
    relative: float
    blocks: list[FillInBlock]

    def to_json(self) -> dict[str, Any]:
        return {"largest": self.largest, "relative": self.relative, "blocks": self.blocks}


def fill_in(system: CoupledSystem, A: np.ndarray, B: np.ndarray) -> FillIn:
    """The entries of the global ``A`` (n x n) and ``B`` (n x m) outside ``system``'s graph."""
    pairs = allowed_pairs(system)
    blocks: list[FillInBlock] = []
    for i, t in enumerate(system.subsystems):
        for j, s in enumerate(system.subsystems):
            if i == j or (i, j) in pairs:
                continue
            for name, mat, cols in (("A", A, system.xs(j)), ("B", B, system.us(j))):
                big = float(np.max(np.abs(mat[system.xs(i), cols]), initial=0.0))
                if big > 0:
                    blocks.append({"target": t.name, "source": s.name, "matrix": name, "largest": big})
    blocks.sort(key=lambda b: -b["largest"])
    largest = blocks[0]["largest"] if blocks else 0.0
    scale = float(max(np.max(np.abs(A), initial=0.0), np.max(np.abs(B), initial=0.0)))
    return FillIn(largest=largest, relative=largest / scale if scale > 0 else 0.0, blocks=blocks)


def restrict_to_graph(system: CoupledSystem, A: np.ndarray, B: np.ndarray) -> CoupledSystem:
    """The discrete system made of the blocks of global ``A``, ``B`` inside ``system``'s graph.

    Parameters
    ----------
    system : CoupledSystem
        Gives the subsystems (names, sets, weights, x0), the couplings and the edges.
    A : ndarray, shape (n, n)
    B : ndarray, shape (n, m)

    Returns
    -------
    CoupledSystem
        A coupling for every allowed pair (:func:`allowed_pairs`) whose blocks are not all zero.
    """
    subsystems = tuple(_with_matrices(s, A[system.xs(i), system.xs(i)], B[system.xs(i), system.us(i)])
                       for i, s in enumerate(system.subsystems))
    couplings = []
    for i, j in sorted(allowed_pairs(system)):
        Aij, Bij = A[system.xs(i), system.xs(j)], B[system.xs(i), system.us(j)]
        if np.any(Aij) or np.any(Bij):
            couplings.append(Coupling(i, j, Aij.copy(), Bij.copy()))
    return CoupledSystem(subsystems=subsystems, couplings=tuple(couplings), edges=system.edges)


def largest_difference(system: CoupledSystem, A: np.ndarray, B: np.ndarray) -> float:
    """The largest absolute entry of ``[system.A - A, system.B - B]``: how far a discrete model is
    from the exact one (global ``A`` n x n, ``B`` n x m)."""
    return float(max(np.max(np.abs(system.A - A), initial=0.0), np.max(np.abs(system.B - B), initial=0.0)))


def _with_matrices(s: Subsystem, A: np.ndarray, B: np.ndarray) -> Subsystem:
    return dataclasses.replace(s, A=np.array(A), B=np.array(B))


class FillInRefused(DmpcError, ValueError):
    """``exact-zoh``: the fill-in outside the coupling graph exceeds the tolerance."""


@dataclass(frozen=True)
class DiscreteModel:
    """A continuous-time system discretised for the controllers, and the exact model beside it.

    Attributes
    ----------
    continuous : CoupledSystem
        The continuous-time matrices as written.
    system : CoupledSystem
        The controllers' discrete model (``method``).
    A_exact : ndarray, shape (n, n)
    B_exact : ndarray, shape (n, m)
        The exact zero-order hold of the whole system (``plant.model: exact`` simulates it).
    method : str
        ``local-zoh`` or ``exact-zoh``.
    dt : float
    fill_in : FillIn
        The exact model's entries outside the graph: dropped by ``exact-zoh``, absent from ``local-zoh``.
    model_error : float
        The largest absolute entry of the controllers' [A B] minus the exact one.
    """

    continuous: CoupledSystem
    system: CoupledSystem
    A_exact: np.ndarray
    B_exact: np.ndarray
    method: str
    dt: float
    fill_in: FillIn
    model_error: float

    def to_json(self) -> dict[str, Any]:
        """The discrete matrices used and how far they are from the exact ones (for ``design.json``)."""
        s = self.system
        return {
            "time": "continuous", "dt": self.dt, "method": self.method,
            "subsystems": [{"name": sub.name, "A": sub.A.tolist(), "B": sub.B.tolist()} for sub in s.subsystems],
            "couplings": [{"target": s.subsystems[c.target].name, "source": s.subsystems[c.source].name,
                           "A": c.A.tolist(), "B": c.B.tolist()} for c in s.couplings],
            "fill_in": self.fill_in.to_json(),
            "model_error": self.model_error,
            "exact": {"A": self.A_exact.tolist(), "B": self.B_exact.tolist()},
        }


def discretise(continuous: CoupledSystem, dt: float, method: str = "local-zoh", truncate: bool = False,
               tolerance: float = 1e-9) -> DiscreteModel:
    """Discretise a continuous-time coupled system with zero-order hold.

    Parameters
    ----------
    continuous : CoupledSystem
        Continuous-time matrices.
    dt : float
        Sampling period, seconds.
    method : {"local-zoh", "exact-zoh"}
    truncate : bool
        ``exact-zoh``: drop a fill-in above ``tolerance`` instead of refusing it.
    tolerance : float
        ``exact-zoh``: the largest fill-in accepted, relative to the largest entry of [A B].

    Raises
    ------
    FillInRefused
        ``exact-zoh`` with a relative fill-in above ``tolerance`` and ``truncate`` false.
    """
    if method not in METHODS:
        raise ValueError(f"unknown discretisation {method!r} (expected {' or '.join(METHODS)})")
    A, B = exact_zoh(continuous, dt)
    spread = fill_in(continuous, A, B)
    if method == "local-zoh":
        system = local_zoh(continuous, dt)
    else:
        if spread.relative > tolerance and not truncate:
            top = spread.blocks[0]
            raise FillInRefused(
                f"the exact discretisation couples subsystems outside the coupling graph: entries up to "
                f"{spread.largest:.3g} ({spread.relative:.3g} of the largest entry, above the tolerance "
                f"{tolerance:.3g}), the largest in {top['matrix']}_{top['target']},{top['source']}; set "
                "truncate: true to drop them, or use local-zoh")
        system = restrict_to_graph(continuous, A, B)
    return DiscreteModel(continuous=continuous, system=system, A_exact=A, B_exact=B, method=method, dt=dt,
                         fill_in=spread, model_error=largest_difference(system, A, B))
