"""Integrating disturbance models of the subsystems and their detectability.

Subsystem i measures y_i = C_i x_i (C_i of shape (p_i, n_i); the identity when every state is
measured) and carries n_d,i integrating disturbances d_i:

    x_i+ = A_ii x_i + B_ii u_i + sum_{j != i} (A_ij x_j + B_ij u_j) + B_d,i d_i
    d_i+ = d_i
    y_i  = C_i x_i + C_d,i d_i

Two kinds of disturbance model:

- ``output`` (the default): n_d,i = p_i, B_d,i = 0, C_d,i = I, one constant bias per measured
  output;
- ``input``: n_d,i = m_i, B_d,i = B_ii, C_d,i = 0, a constant offset on each of the subsystem's
  own inputs.

The disturbances are local, so the global B_d, C_d (and C) are block diagonal; the coupled
augmented model is x+ = A x + B u + B_d d with the coupled A, B (couplings included).

**Detectability** (Pannocchia & Rawlings 2003; Maeder, Borrelli & Morari 2009): the augmented
pair ([[A, B_d], [0, I]], [C, C_d]) is detectable if and only if (A, C) is detectable and

    rank [[I - A, -B_d], [C, C_d]] = n + n_d,

which needs n_d <= p. With output disturbances the rank is p + rank(I - A): an integrating mode
(an eigenvalue 1 of A) makes them undetectable whatever is measured. :func:`check_detectable`
checks both conditions per subsystem (with A_ii: agent i's own filter needs them) and for the
coupled system (with the global A), and raises :class:`~dmpc.core.errors.DesignError` with the
figures and what to change.

The coupled system's check is dense (SVDs of n x n and (n + p) x (n + n_d) matrices: 5 s at
n = 2048 on a quiet two-core machine, a minute under load). Above :data:`COUPLED_DENSE_LIMIT`
states (n + n_d) :func:`check_detectable` first looks for a proof that needs none: block-diagonal
filter gains whose coupled error dynamics are stable
(:func:`dmpc.estimation.kalman.certify_detectable`), which no undetectable mode allows; the dense
check runs only where none is found.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike

from dmpc.core.errors import DesignError
from dmpc.core.system import CoupledSystem

KINDS: tuple[str, ...] = ("output", "input")
"""The disturbance models: one disturbance per measured output, or one per own input."""

DEFAULT_KIND = "output"
"""One disturbance per measured output (B_d = 0, C_d = I): detectable whenever A has no eigenvalue 1."""

RANK_TOLERANCE = 1e-9
"""A singular value counts as zero below this times the largest, each row scaled to unit norm
first (the rows of I - A and of C are in different units)."""

UNIT_CIRCLE_TOLERANCE = 1e-9
"""A mode with |lambda| >= 1 - this must be seen by the outputs for (A, C) to be detectable."""

COUPLED_DENSE_LIMIT = 500
"""Coupled augmented models (n + n_d states) up to this size are checked densely; larger ones by a
certificate first (the module's text, :mod:`dmpc.estimation.kalman`)."""

DENSE_LIMIT = 65536
"""Matrices of the step's path with at most this many entries are kept dense (a dense product is
faster than a sparse one at that size); larger ones as CSR, whose products cost their nonzeros."""


def as_operator(matrix: np.ndarray | sp.spmatrix) -> np.ndarray | sp.csr_matrix:
    """``matrix`` (r, c) as a step multiplies it: a dense array up to ``DENSE_LIMIT`` entries, CSR above."""
    rows, cols = matrix.shape
    if rows * cols > DENSE_LIMIT:
        return sp.csr_matrix(matrix)
    if isinstance(matrix, np.ndarray):
        return np.asarray(matrix, dtype=float)
    return np.asarray(matrix.toarray(), dtype=float)


@dataclass(frozen=True, eq=False)
class LocalModel:
    """One subsystem's model with its measurements and disturbances.

    Attributes
    ----------
    name : str
        The subsystem's name.
    kind : str
        ``output`` or ``input`` (see the module's text).
    A : ndarray, shape (n_i, n_i)
        A_ii.
    B : ndarray, shape (n_i, m_i)
        B_ii.
    C : ndarray, shape (p_i, n_i)
    Bd : ndarray, shape (n_i, n_d,i)
    Cd : ndarray, shape (p_i, n_d,i)
    """

    name: str
    kind: str
    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    Bd: np.ndarray
    Cd: np.ndarray

    @property
    def n(self) -> int:
        return int(self.A.shape[0])

    @property
    def m(self) -> int:
        return int(self.B.shape[1])

    @property
    def p(self) -> int:
        return int(self.C.shape[0])

    @property
    def nd(self) -> int:
        return int(self.Bd.shape[1])

    def augmented(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The subsystem's own augmented model, without its couplings.

        Returns
        -------
        A_aug : ndarray, shape (n_i + n_d,i, n_i + n_d,i)
            [[A_ii, B_d,i], [0, I]].
        B_aug : ndarray, shape (n_i + n_d,i, m_i)
            [[B_ii], [0]].
        C_aug : ndarray, shape (p_i, n_i + n_d,i)
            [C_i, C_d,i].
        """
        return augmented_matrices(self.A, self.B, self.C, self.Bd, self.Cd)


def augmented_matrices(A: np.ndarray, B: np.ndarray, C: np.ndarray, Bd: np.ndarray,
                       Cd: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The model x+ = A x + B u + B_d d, d+ = d, y = C x + C_d d as one state [x; d].

    Parameters
    ----------
    A : ndarray, shape (n, n)
    B : ndarray, shape (n, m)
    C : ndarray, shape (p, n)
    Bd : ndarray, shape (n, n_d)
    Cd : ndarray, shape (p, n_d)

    Returns
    -------
    A_aug : ndarray, shape (n + n_d, n + n_d)
    B_aug : ndarray, shape (n + n_d, m)
    C_aug : ndarray, shape (p, n + n_d)
    """
    n, nd = A.shape[0], Bd.shape[1]
    A_aug = np.block([[A, Bd], [np.zeros((nd, n)), np.eye(nd)]])
    B_aug = np.vstack([B, np.zeros((nd, B.shape[1]))])
    C_aug = np.hstack([C, Cd])
    return A_aug, B_aug, C_aug


def disturbance_matrices(kind: str, B: np.ndarray, p: int) -> tuple[np.ndarray, np.ndarray]:
    """B_d and C_d of one subsystem for a disturbance model ``kind``.

    Parameters
    ----------
    kind : str
        ``output`` (B_d = 0, C_d = I_p) or ``input`` (B_d = B, C_d = 0).
    B : ndarray, shape (n_i, m_i)
        The subsystem's own B_ii.
    p : int
        Its number of measured outputs p_i.

    Returns
    -------
    Bd : ndarray, shape (n_i, n_d,i)
    Cd : ndarray, shape (p_i, n_d,i)

    Raises
    ------
    DesignError
        For an unknown kind.
    """
    n, m = B.shape
    if kind == "output":
        return np.zeros((n, p)), np.eye(p)
    if kind == "input":
        return np.array(B, dtype=float), np.zeros((p, m))
    raise DesignError(f"estimation: unknown disturbance model {kind!r} (expected one of {', '.join(KINDS)})")


@dataclass(frozen=True, eq=False)
class AugmentedSystem:
    """The coupled system with every subsystem's measurements and disturbances.

    The global state of the estimator is [x; d]: the system's states (n,), then the disturbances
    (n_d,) in subsystem order; the outputs (p,) are in subsystem order too.

    Attributes
    ----------
    system : CoupledSystem
    parts : tuple of LocalModel
        One per subsystem, in order.
    """

    system: CoupledSystem
    parts: tuple[LocalModel, ...]

    @property
    def M(self) -> int:
        return self.system.M

    @property
    def n(self) -> int:
        return self.system.n

    @property
    def m(self) -> int:
        return self.system.m

    @cached_property
    def output_offsets(self) -> np.ndarray:
        """Start of each subsystem's block in the global output, shape (M+1,)."""
        return np.concatenate([[0], np.cumsum([part.p for part in self.parts])]).astype(int)

    @cached_property
    def disturbance_offsets(self) -> np.ndarray:
        """Start of each subsystem's block in the global disturbance, shape (M+1,)."""
        return np.concatenate([[0], np.cumsum([part.nd for part in self.parts])]).astype(int)

    @property
    def p(self) -> int:
        return int(self.output_offsets[-1])

    @property
    def nd(self) -> int:
        return int(self.disturbance_offsets[-1])

    def ys(self, i: int) -> slice:
        """The slice of subsystem i's outputs in the global output."""
        return slice(int(self.output_offsets[i]), int(self.output_offsets[i + 1]))

    def ds(self, i: int) -> slice:
        """The slice of subsystem i's disturbances in the global disturbance."""
        return slice(int(self.disturbance_offsets[i]), int(self.disturbance_offsets[i + 1]))

    @cached_property
    def C(self) -> np.ndarray:
        """Global measurement matrix, block diagonal, shape (p, n)."""
        return _blocks([part.C for part in self.parts], self.p, self.n)

    @cached_property
    def Bd(self) -> np.ndarray:
        """Global disturbance input matrix, block diagonal, shape (n, n_d)."""
        return _blocks([part.Bd for part in self.parts], self.n, self.nd)

    @cached_property
    def Cd(self) -> np.ndarray:
        """Global disturbance output matrix, block diagonal, shape (p, n_d)."""
        return _blocks([part.Cd for part in self.parts], self.p, self.nd)

    def augmented(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The coupled augmented model: A_aug (n + n_d, n + n_d) = [[A, B_d], [0, I]] with the
        coupled A, B_aug (n + n_d, m) = [[B], [0]] with the coupled B, C_aug (p, n + n_d) = [C, C_d]."""
        return augmented_matrices(self.system.A, self.system.B, self.C, self.Bd, self.Cd)

    def outputs(self, x: np.ndarray, d: np.ndarray) -> np.ndarray:
        """y = C x + C_d d (p,) for the global state x (n,) and disturbance d (n_d,)."""
        y: np.ndarray = self.C @ x + self.Cd @ d
        return y


def _blocks(blocks: list[np.ndarray], rows: int, cols: int) -> np.ndarray:
    """Block-diagonal stack of ``blocks`` with the given total shape (also when blocks are empty)."""
    if rows == 0 or cols == 0:
        return np.zeros((rows, cols))
    out = np.zeros((rows, cols))
    r = c = 0
    for b in blocks:
        out[r:r + b.shape[0], c:c + b.shape[1]] = b
        r += b.shape[0]
        c += b.shape[1]
    return out


def augment(system: CoupledSystem, C: Sequence[ArrayLike | None] | None = None,
            kind: str | Sequence[str] = DEFAULT_KIND) -> AugmentedSystem:
    """Every subsystem's measurements and disturbance model.

    Parameters
    ----------
    system : CoupledSystem
    C : sequence of array_like or None, optional
        Per subsystem, its measurement matrix C_i of shape (p_i, n_i) (p_i may be 0: nothing
        measured); None (the whole argument or an entry) is the identity, every state measured.
    kind : str or sequence of str
        ``output`` or ``input``, for every subsystem or one per subsystem.

    Returns
    -------
    AugmentedSystem
        Not yet checked: :func:`check_detectable` does that.

    Raises
    ------
    DesignError
        A C of the wrong shape or with a non-finite entry, an unknown kind, or lists of the wrong length.
    """
    M = system.M
    given = [None] * M if C is None else list(C)
    kinds = [kind] * M if isinstance(kind, str) else list(kind)
    if len(given) != M or len(kinds) != M:
        raise DesignError(f"estimation: {M} subsystems but {len(given)} measurement matrices and {len(kinds)} "
                          "disturbance models")
    parts = []
    for sub, Ci, ki in zip(system.subsystems, given, kinds):
        Cm = np.eye(sub.n) if Ci is None else np.array(Ci, dtype=float)
        if Cm.ndim == 1 and Cm.size == 0:
            Cm = Cm.reshape(0, sub.n)
        if Cm.ndim != 2 or Cm.shape[1] != sub.n:
            raise DesignError(f"estimation: subsystem {sub.name}: C must have {sub.n} columns (one per state), "
                              f"got shape {Cm.shape}")
        if not np.isfinite(Cm).all():
            raise DesignError(f"estimation: subsystem {sub.name}: C has a non-finite entry")
        Bd, Cd = disturbance_matrices(ki, sub.B, Cm.shape[0])
        parts.append(LocalModel(sub.name, ki, np.asarray(sub.A, float), np.asarray(sub.B, float), Cm, Bd, Cd))
    return AugmentedSystem(system, tuple(parts))


# ---------------------------------------------------------------------------- detectability
def _unit_rows(M: np.ndarray) -> np.ndarray:
    """M with every nonzero row scaled to unit 2-norm."""
    norms = np.linalg.norm(M, axis=1)
    norms[norms == 0.0] = 1.0
    scaled: np.ndarray = M / norms[:, None]
    return scaled


def _null_basis(M: np.ndarray, tolerance: float) -> np.ndarray:
    """An orthonormal basis (k, dim) of the vectors v with ||M v|| <= ``tolerance`` ||v|| (absolute)."""
    cols = M.shape[1]
    if M.shape[0] == 0:
        return np.eye(cols)
    _, s, vh = np.linalg.svd(M, full_matrices=True)
    small = np.ones(cols, dtype=bool)
    small[: s.size] = s <= tolerance
    basis: np.ndarray = vh[small].T
    return basis


def unobservable_subspace(A: np.ndarray, C: np.ndarray) -> np.ndarray:
    """An orthonormal basis of the unobservable subspace of (A, C): the largest A-invariant
    subspace in the null space of C.

    Parameters
    ----------
    A : ndarray, shape (n, n)
    C : ndarray, shape (p, n)

    Returns
    -------
    ndarray, shape (n, k)
        k = 0 when (A, C) is observable.
    """
    n = A.shape[0]
    scale = max(1.0, float(np.abs(A).sum(axis=1).max(initial=0.0)))
    V = _null_basis(_unit_rows(C), RANK_TOLERANCE) if C.shape[0] else np.eye(n)
    while V.shape[1]:
        AV = A @ V
        outside = AV - V @ (V.T @ AV)  # the part of A V outside span(V)
        Z = _null_basis(outside, RANK_TOLERANCE * scale)
        if Z.shape[1] == V.shape[1]:
            break
        V = V @ Z
    return V


def undetectable_modes(A: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The modes of A that the outputs do not see and that do not decay (|lambda| >= 1).

    Parameters
    ----------
    A : ndarray, shape (n, n)
    C : ndarray, shape (p, n)

    Returns
    -------
    eigenvalues : ndarray of complex, shape (k,)
        Empty when (A, C) is detectable.
    directions : ndarray of complex, shape (n, k)
        An eigenvector of A for each.
    """
    V = unobservable_subspace(A, C)
    if V.shape[1] == 0:
        return np.zeros(0, dtype=complex), np.zeros((A.shape[0], 0), dtype=complex)
    values, vectors = np.linalg.eig(V.T @ A @ V)
    bad = np.abs(values) >= 1.0 - UNIT_CIRCLE_TOLERANCE
    return values[bad], V @ vectors[:, bad]


def rank_condition(A: np.ndarray, Bd: np.ndarray, C: np.ndarray, Cd: np.ndarray) -> tuple[int, int]:
    """rank [[I - A, -B_d], [C, C_d]] and the rank that detectability needs, n + n_d.

    Parameters
    ----------
    A : ndarray, shape (n, n)
    Bd : ndarray, shape (n, n_d)
    C : ndarray, shape (p, n)
    Cd : ndarray, shape (p, n_d)

    Returns
    -------
    rank, needed : int
    """
    matrix = np.block([[np.eye(A.shape[0]) - A, -Bd], [C, Cd]])
    return numerical_rank(matrix), A.shape[0] + Bd.shape[1]


def numerical_rank(M: np.ndarray) -> int:
    """The rank of M (r, c): singular values above ``RANK_TOLERANCE`` times the largest, rows scaled
    to unit norm first."""
    if M.size == 0:
        return 0
    s = np.linalg.svd(_unit_rows(M), compute_uv=False)
    return int(np.sum(s > RANK_TOLERANCE * s[0])) if s[0] > 0 else 0


@dataclass(frozen=True)
class Detectability:
    """The figures of one detectability check (for the design record).

    Attributes
    ----------
    where : str
        ``subsystem <name>`` or ``the coupled system``.
    n, nd, p : int
        States, disturbances and outputs.
    rank : int
        rank [[I - A, -B_d], [C, C_d]]; it equals n + nd.
    """

    where: str
    n: int
    nd: int
    p: int
    rank: int


def _own(name: str) -> str:
    """A_ii written with the subsystem's name: A_bb, or A_(tank1) for longer names."""
    return f"A_{name}{name}" if len(name) == 1 else f"A_({name})"


def _modes(values: np.ndarray) -> str:
    shown = [f"{v.real:.6g}" if abs(v.imag) < 1e-12 else f"{v.real:.4g}{v.imag:+.4g}j" for v in values[:4]]
    return ", ".join(shown) + (f" and {values.size - 4} more" if values.size > 4 else "")


def _involved(aug: AugmentedSystem, x_part: np.ndarray, d_part: np.ndarray | None = None) -> str:
    """The subsystems a direction (its state part (n,) and disturbance part (n_d,)) lives in."""
    weights = np.array([np.linalg.norm(x_part[aug.system.xs(i)])
                        + (np.linalg.norm(d_part[aug.ds(i)]) if d_part is not None else 0.0)
                        for i in range(aug.M)])
    top = float(weights.max(initial=0.0))
    names = [aug.parts[i].name for i in range(aug.M) if weights[i] > 0.1 * top] if top > 0 else []
    return ", ".join(names)


def check_subsystem(part: LocalModel) -> Detectability:
    """Both conditions for one subsystem's own augmented model (with A_ii, without couplings).

    Parameters
    ----------
    part : LocalModel

    Returns
    -------
    Detectability

    Raises
    ------
    DesignError
        (A_ii, C_i) not detectable, more disturbances than outputs, or the rank condition fails;
        the message names the subsystem, the condition, the figures and what to change.
    """
    name, n, nd, p = part.name, part.n, part.nd, part.p
    where = f"estimation: subsystem {name}"
    values, _ = undetectable_modes(part.A, part.C)
    if values.size:
        raise DesignError(
            f"{where}: (A, C) is not detectable: its {p} output(s) do not see the mode(s) of {_own(name)} at "
            f"eigenvalue(s) {_modes(values)} (|lambda| >= 1), so no observer can estimate them; measure a state "
            f"that mode moves (a row of C for subsystem {name})")
    if nd > p:
        raise DesignError(
            f"{where}: {nd} {part.kind} disturbance(s) but only {p} measured output(s): at most {p} can be "
            f"detected (the augmented model's rank is at most n + p = {n + p} < {n + nd}); measure {nd - p} more "
            f"output(s), or use estimation.disturbance: output")
    rank, needed = rank_condition(part.A, part.Bd, part.C, part.Cd)
    if rank < needed:
        other = "input" if part.kind == "output" else "output"
        Bd, Cd = disturbance_matrices(other, part.B, p)
        other_ok = Bd.shape[1] <= p and rank_condition(part.A, Bd, part.C, Cd)[0] == n + Bd.shape[1]
        head = (f"{where}: {nd} {part.kind} disturbance(s) but the augmented model's rank is {rank} < {needed} "
                f"(rank [[I - A, -B_d], [C, C_d]], n = {n}, n_d = {nd})")
        if part.kind == "output":
            why = (f"with an integrating mode (an eigenvalue 1 of {_own(name)}) an output disturbance is not "
                   "detectable, whatever is measured")
            fix = ("use estimation.disturbance: input" if other_ok else
                   "input disturbances fail too: measure another state, so that input disturbances become detectable")
        else:
            why = ("some constant input disturbance leaves the measured outputs unchanged at steady state (the "
                   "steady-state gain from u to y is singular: a zero at 1, or dependent columns of B)")
            fix = ("use estimation.disturbance: output, or measure another state" if other_ok
                   else "measure another state (a row of C)")
        raise DesignError(f"{head}: {why}; {fix}")
    return Detectability(f"subsystem {name}", n, nd, p, rank)


def check_coupled(aug: AugmentedSystem) -> Detectability:
    """Both conditions for the coupled augmented model (the global A with its couplings).

    Parameters
    ----------
    aug : AugmentedSystem

    Returns
    -------
    Detectability

    Raises
    ------
    DesignError
        The message names the condition, the figures and the subsystems involved.
    """
    A, C = aug.system.A, aug.C
    n, nd, p = aug.n, aug.nd, aug.p
    values, directions = undetectable_modes(A, C)
    if values.size:
        raise DesignError(
            f"estimation: the coupled system: (A, C) is not detectable: the outputs do not see the mode(s) at "
            f"eigenvalue(s) {_modes(values)} (|lambda| >= 1) of the coupled A, which move(s) subsystem(s) "
            f"{_involved(aug, np.abs(directions).sum(axis=1))}; measure a state that mode moves")
    if nd > p:  # cannot happen when every subsystem passed; kept for systems checked on their own
        raise DesignError(f"estimation: the coupled system: {nd} disturbances but only {p} outputs")
    matrix = np.block([[np.eye(n) - A, -aug.Bd], [C, aug.Cd]])
    rank = numerical_rank(matrix)
    if rank < n + nd:
        _, _, vh = np.linalg.svd(_unit_rows(matrix))
        direction = np.abs(vh[-1])
        kinds = sorted({part.kind for part in aug.parts})
        integrating = numerical_rank(np.eye(n) - A) < n
        why = ("the coupled A has an eigenvalue 1 (an integrating mode through the couplings), which output "
               "disturbances cannot see; use estimation.disturbance: input on those subsystems, or measure another "
               "state" if integrating and "output" in kinds else
               "the subsystems' disturbances cannot be told apart at steady state through the couplings; change "
               "estimation.disturbance of one of them, or measure another state")
        raise DesignError(
            f"estimation: the coupled system: the augmented model's rank is {rank} < {n + nd} (rank [[I - A, -B_d], "
            f"[C, C_d]] with the coupled A, n = {n}, n_d = {nd}), though every subsystem passes on its own; the "
            f"deficient direction involves subsystem(s) {_involved(aug, direction[:n], direction[n:])}: {why}")
    return Detectability("the coupled system", n, nd, p, rank)


def check_detectable(aug: AugmentedSystem) -> tuple[Detectability, ...]:
    """The detectability conditions, per subsystem and then for the coupled system.

    Parameters
    ----------
    aug : AugmentedSystem

    Returns
    -------
    tuple of Detectability
        One per subsystem, then the coupled system's.

    Raises
    ------
    DesignError
        At the first failure (:func:`check_subsystem`, :func:`check_coupled`).

    Notes
    -----
    Above :data:`COUPLED_DENSE_LIMIT` states the coupled system's figures come from a stable coupled
    estimator where one is found (its rank is then n + n_d, implied); :func:`check_coupled` runs
    otherwise.
    """
    local = tuple(check_subsystem(part) for part in aug.parts)
    if aug.n + aug.nd > COUPLED_DENSE_LIMIT:
        from dmpc.estimation.kalman import certify_detectable  # the gains' module builds on this one

        if certify_detectable(aug):
            return local + (Detectability("the coupled system", aug.n, aug.nd, aug.p, aug.n + aug.nd),)
    return local + (check_coupled(aug),)


__all__ = ["AugmentedSystem", "as_operator", "COUPLED_DENSE_LIMIT", "DEFAULT_KIND", "Detectability", "KINDS", "LocalModel", "augment", "augmented_matrices",
           "check_coupled", "check_detectable", "check_subsystem", "disturbance_matrices",
           "numerical_rank", "rank_condition", "undetectable_modes", "unobservable_subspace"]
