"""How strongly each subsystem's inputs drive its neighbours, and whether the non-cooperative
methods' iteration and closed loop are stable (docs/algorithm.md, "Input coupling").

The distributed methods (``tv-box`` and the others with agents, ``tv-box-coop`` aside) are
non-cooperative: agent i minimises its own cost J_i over its own inputs, with its neighbours'
plans fixed. When B_ij != 0 that is a game whose Jacobi iteration can diverge and whose
equilibrium need not stabilise the plant. Three measures tell such systems apart:

- **Input drive.** For each ordered pair (i drives j, j != i) with B_ji != 0, the ratio
  ||Q_j^1/2 B_ji|| / ||Q_i^1/2 B_ii|| (spectral norms): how much u_i moves x_j in one step,
  against how much it moves x_i, in the cost's own scale (the Q weights make the ratio independent
  of the states' units; u_i's scale cancels). The same ratio of the steady-state gains
  G = (I - A)^-1 B of the whole system, when A is stable.
- **The Jacobi map.** Without its inequality rows, QP_i is least squares: with the prediction
  z_i = Phi_i x_i + Gamma_i v_i + Psi_i c_i (as in :mod:`dmpc.core.unconstrained`) and the
  feed-forward c_i(t) = sum_j A_ij zhat_j(t) + B_ij vhat_j(t), its optimum is

      v_i* = -H_i^-1 Gamma_i' Qbar_i (Phi_i x_i + Psi_i c_i),   H_i = Gamma_i' Qbar_i Gamma_i + Rbar_i,

  affine in c_i, hence in the neighbours' plans. A Jacobi round maps every agent's plan
  w_j = (z_j(1..N-1), v_j(0..N-1)) (what its neighbours' feed-forward reads: zhat_j(0) is the
  measured state) to the next: w^+ = T w + (terms in x). Its spectral radius rho(T) decides the
  iteration: rho < 1 converges (to the plans of the equilibrium of the unconstrained game),
  rho > 1 diverges from almost every start. With A_ij = 0 (the couplings only through the
  inputs) the state parts drop out and T is the map of the stacked input sequences.
- **The closed loop.** The state (x(k), every agent's plan of step k - 1) of the method without
  constraints evolves linearly, s(k+1) = L s(k) (:func:`closed_loop`, with the shifted plans of
  the first round and any further rounds per step): rho(L) >= 1 means the method does not
  stabilise the plant even where no constraint is active, whatever rho(T) is.

:attr:`InputCoupling.likely_to_fail`: some B_ij != 0, and rho(T) > 1 or rho(L) >= 1.

Everything here is numpy only and pure.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dmpc.core.system import CoupledSystem
from dmpc.core.unconstrained import condensed

DENSE_LIMIT = 1500
"""Largest dimension of T (sum_i (N-1) n_i + N m_i) whose eigenvalues are computed; above it the
spectral radius is bounded through the matrix of block norms (``radius_kind: bound``)."""
GAIN_COND_LIMIT = 1e12
"""I - A with a larger condition number is treated as singular (no steady-state gain)."""


@dataclass(frozen=True)
class PairDrive:
    """How subsystem ``source`` drives subsystem ``target`` through B_target,source.

    Attributes
    ----------
    source, target : int
        0-based indices, source != target.
    ratio : float
        ||Q_t^1/2 B_ts|| / ||Q_s^1/2 B_ss||: the one-step effect of u_source on x_target against
        its effect on x_source (inf when B_ss = 0).
    steady_ratio : float or None
        The same ratio of the steady-state gains (I - A)^-1 B; None when A is not stable.
    """

    source: int
    target: int
    ratio: float
    steady_ratio: float | None


@dataclass(frozen=True)
class InputCoupling:
    """The figures of :func:`input_coupling`.

    Attributes
    ----------
    pairs : tuple of PairDrive
        One per ordered pair with B_target,source != 0, in the order of the couplings.
    horizon : int
        The N of the maps.
    rounds : int
        The Jacobi rounds per step of the closed loop.
    radius : float
        rho(T), the spectral radius of the unconstrained Jacobi round (an upper bound of it when
        ``radius_kind`` is ``bound``).
    radius_kind : str
        ``exact`` (the eigenvalues of T) or ``bound`` (above DENSE_LIMIT: :func:`perron_bound` of
        the matrix of the block norms ||T_ij||_2, never below rho(T)).
    dimension : int
        The size of T.
    loop_radius : float or None
        rho(L), the spectral radius of the unconstrained closed loop of the non-cooperative method
        with ``rounds`` rounds per step (:func:`closed_loop`); None when L is larger than
        DENSE_LIMIT (not computed).
    loop_dimension : int
        The size of L.
    """

    pairs: tuple[PairDrive, ...]
    horizon: int
    rounds: int
    radius: float
    radius_kind: str
    dimension: int
    loop_radius: float | None
    loop_dimension: int

    @property
    def input_coupled(self) -> bool:
        """True if some B_ij != 0 (i != j)."""
        return bool(self.pairs)

    @property
    def strongest(self) -> PairDrive | None:
        """The pair with the largest one-step ratio (None without input coupling)."""
        return max(self.pairs, key=lambda p: p.ratio) if self.pairs else None

    @property
    def diverges(self) -> bool:
        """True if the Jacobi iteration diverges (rho(T) > 1; only when the radius is exact)."""
        return self.radius_kind == "exact" and self.radius > 1.0

    @property
    def unstable(self) -> bool:
        """True if the unconstrained closed loop is not stable (rho(L) >= 1)."""
        return self.loop_radius is not None and self.loop_radius >= 1.0

    @property
    def likely_to_fail(self) -> bool:
        """True if a non-cooperative method is likely to fail: the inputs couple the subsystems
        (some B_ij != 0) and its Jacobi iteration diverges or its closed loop without constraints
        is not stable. Where B_ij = 0 throughout, the time-varying terminal sets keep their
        guarantees whatever these figures are (docs/algorithm.md, "Input coupling")."""
        return self.input_coupled and (self.diverges or self.unstable)

    def to_json(self, names: list[str] | None = None) -> dict:
        """The figures for ``design.json`` (``input_coupling``); subsystems by their ``names`` (in
        subsystem order) when given, else by index."""
        def name(i: int) -> str | int:
            return names[i] if names is not None else i

        strongest = self.strongest
        return {
            "pairs": [{"source": name(p.source), "target": name(p.target), "ratio": _finite(p.ratio),
                       "steady_ratio": None if p.steady_ratio is None else _finite(p.steady_ratio)}
                      for p in self.pairs],
            "largest_ratio": _finite(strongest.ratio) if strongest is not None else 0.0,
            "horizon": self.horizon,
            "rounds": self.rounds,
            "jacobi_radius": _finite(self.radius),
            "jacobi_radius_kind": self.radius_kind,
            "jacobi_dimension": self.dimension,
            "loop_radius": None if self.loop_radius is None else _finite(self.loop_radius),
            "loop_dimension": self.loop_dimension,
            "likely_to_fail": self.likely_to_fail,
        }


def _finite(value: float) -> float | str:
    """A float for JSON: infinities as strings, as elsewhere in design.json."""
    return float(value) if np.isfinite(value) else ("inf" if value > 0 else "-inf")


def _sqrt_psd(Q: np.ndarray) -> np.ndarray:
    """The symmetric square root of a positive semidefinite Q (n, n)."""
    values, vectors = np.linalg.eigh(0.5 * (Q + Q.T))
    return (vectors * np.sqrt(np.maximum(values, 0.0))) @ vectors.T


def _ratio(numerator: np.ndarray, denominator: np.ndarray) -> float:
    top = float(np.linalg.norm(numerator, 2)) if numerator.size else 0.0
    bottom = float(np.linalg.norm(denominator, 2)) if denominator.size else 0.0
    if bottom == 0.0:
        return 0.0 if top == 0.0 else float("inf")
    return top / bottom


def steady_state_gain(system: CoupledSystem) -> np.ndarray | None:
    """G = (I - A)^-1 B, shape (n, m), of the whole ``system``: the steady-state change of x per
    constant change of u; None when A is not stable (the plant does not settle) or I - A is singular."""
    A = system.A
    if system.n == 0 or max(abs(np.linalg.eigvals(A))) >= 1.0:
        return None
    lhs = np.eye(system.n) - A
    if np.linalg.cond(lhs) > GAIN_COND_LIMIT:
        return None
    return np.linalg.solve(lhs, system.B)


def input_drives(system: CoupledSystem) -> tuple[PairDrive, ...]:
    """The pairs of ``system`` with B_ji != 0 and their ratios (:class:`PairDrive`)."""
    roots = [_sqrt_psd(s.Q) for s in system.subsystems]
    gain = None
    pairs = []
    for c in system.couplings:
        if not np.any(c.B):
            continue
        if gain is None:
            gain = steady_state_gain(system)
        i, j = c.source, c.target
        own = roots[i] @ system.subsystems[i].B
        ratio = _ratio(roots[j] @ c.B, own)
        steady = None
        if gain is not None:
            steady = _ratio(roots[j] @ gain[system.xs(j), system.us(i)], roots[i] @ gain[system.xs(i), system.us(i)])
        pairs.append(PairDrive(source=i, target=j, ratio=ratio, steady_ratio=steady))
    return tuple(pairs)


@dataclass(frozen=True)
class AgentResponse:
    """One agent's unconstrained optimal plan as a linear function of its state and feed-forward.

    For z(t+1) = A z(t) + B v(t) + c(t), z(0) = x, and the cost sum_{t<N} z'Qz + v'Rv + z(N)'P z(N),
    the optimum is z(1..N) = Zx x + Zc c, v(0..N-1) = Vx x + Vc c, with c = (c(0), ..., c(N-1))
    stacked and every sequence flattened time-major.

    Attributes
    ----------
    Zx : ndarray, shape (N n, n)
    Zc : ndarray, shape (N n, N n)
    Vx : ndarray, shape (N m, n)
    Vc : ndarray, shape (N m, N n)
    """

    Zx: np.ndarray
    Zc: np.ndarray
    Vx: np.ndarray
    Vc: np.ndarray


def agent_response(A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray, P: np.ndarray,
                   horizon: int) -> AgentResponse:
    """The :class:`AgentResponse` of QP_i without its inequality rows.

    Parameters
    ----------
    A : ndarray, shape (n, n)
    B : ndarray, shape (n, m)
    Q, R, P : ndarray, shapes (n, n), (m, m), (n, n)
    horizon : int
        N >= 1.
    """
    n = B.shape[0]
    qp = condensed(A, B, Q, R, P, horizon)
    weighted = qp.weighted_gamma.T  # Gamma' Qbar, (N m, (N+1) n)
    Vx = -np.linalg.solve(qp.hessian, weighted @ qp.phi)
    Vc = -np.linalg.solve(qp.hessian, weighted @ qp.psi)
    return AgentResponse(Zx=(qp.phi + qp.gamma @ Vx)[n:], Zc=(qp.psi + qp.gamma @ Vc)[n:], Vx=Vx, Vc=Vc)


def response_map(A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray, P: np.ndarray,
                 horizon: int) -> np.ndarray:
    """How one agent's unconstrained optimal plan moves with its feed-forward c (:class:`AgentResponse`).

    Parameters
    ----------
    A : ndarray, shape (n, n)
    B : ndarray, shape (n, m)
    Q, R, P : ndarray, shapes (n, n), (m, m), (n, n)
    horizon : int
        N >= 1.

    Returns
    -------
    ndarray, shape ((N-1) n + N m, N n)
        Rows: z(1), ..., z(N-1), then v(0), ..., v(N-1), each flattened; columns: c(0), ..., c(N-1).
    """
    r = agent_response(A, B, Q, R, P, horizon)
    n = A.shape[0]
    return np.vstack([r.Zc[:(horizon - 1) * n], r.Vc])


def feedforward_map(A_ij: np.ndarray, B_ij: np.ndarray, horizon: int) -> np.ndarray:
    """c_i from neighbour j's plan w_j: c_i(t) gets A_ij zhat_j(t) + B_ij vhat_j(t), t = 0..N-1.

    Parameters
    ----------
    A_ij : ndarray, shape (n_i, n_j)
    B_ij : ndarray, shape (n_i, m_j)
    horizon : int
        N >= 1.

    Returns
    -------
    ndarray, shape (N n_i, (N-1) n_j + N m_j)
        Columns as the rows of :func:`response_map` of agent j; zhat_j(0), the measured state, is
        not a column (it does not change over the rounds).
    """
    n_i, n_j, m_j, N = A_ij.shape[0], A_ij.shape[1], B_ij.shape[1], horizon
    out = np.zeros((N * n_i, (N - 1) * n_j + N * m_j))
    for t in range(N):
        if t >= 1:
            out[t * n_i:(t + 1) * n_i, (t - 1) * n_j:t * n_j] = A_ij
        col = (N - 1) * n_j + t * m_j
        out[t * n_i:(t + 1) * n_i, col:col + m_j] = B_ij
    return out


def _active(system: CoupledSystem) -> list:
    """The couplings with a nonzero A_ij or B_ij."""
    return [c for c in system.couplings if np.any(c.A) or np.any(c.B)]


def jacobi_blocks(system: CoupledSystem, P: list[np.ndarray], horizon: int) -> dict[tuple[int, int], np.ndarray]:
    """The nonzero blocks T_ij of the unconstrained Jacobi round w^+ = T w (+ terms in x).

    Parameters
    ----------
    system : CoupledSystem
    P : list of ndarray, shapes (n_i, n_i)
        The terminal weights, in subsystem order.
    horizon : int
        N >= 1.

    Returns
    -------
    dict (i, j) -> ndarray, shape (d_i, d_j), d_i = (N-1) n_i + N m_i
        One block per coupling (target i, source j).
    """
    responses: dict[int, np.ndarray] = {}
    blocks = {}
    for c in _active(system):
        i, j = c.target, c.source
        if i not in responses:
            s = system.subsystems[i]
            responses[i] = response_map(s.A, s.B, s.Q, s.R, P[i], horizon)
        blocks[(i, j)] = responses[i] @ feedforward_map(c.A, c.B, horizon)
    return blocks


def jacobi_dimension(system: CoupledSystem, horizon: int) -> int:
    """The size of T for ``system`` at N = ``horizon``: sum_i (N-1) n_i + N m_i."""
    return int(sum((horizon - 1) * s.n + horizon * s.m for s in system.subsystems))


def jacobi_radius(system: CoupledSystem, P: list[np.ndarray], horizon: int,
                  dense_limit: int = DENSE_LIMIT) -> tuple[float, str, int]:
    """rho(T) of the unconstrained Jacobi round (:func:`jacobi_blocks`).

    Parameters
    ----------
    system : CoupledSystem
    P : list of ndarray, shapes (n_i, n_i)
        The terminal weights, in subsystem order.
    horizon : int
        N >= 1.
    dense_limit : int
        The largest T whose eigenvalues are computed.

    Returns
    -------
    (radius, kind, dimension)
        ``kind`` is ``exact`` up to ``dense_limit`` rows, above it ``bound``: :func:`perron_bound`
        of the (M, M) matrix of block norms ||T_ij||_2, which bounds its spectral radius, which in
        turn bounds rho(T) (a block matrix's spectral radius is at most that of its block norms).
    """
    N = horizon
    sizes = [(N - 1) * s.n + N * s.m for s in system.subsystems]
    dimension = int(sum(sizes))
    blocks = jacobi_blocks(system, P, horizon)
    if not blocks:
        return 0.0, "exact", dimension
    if dimension <= dense_limit:
        offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
        T = np.zeros((dimension, dimension))
        for (i, j), block in blocks.items():
            T[offsets[i]:offsets[i + 1], offsets[j]:offsets[j + 1]] = block
        return float(max(abs(np.linalg.eigvals(T)))), "exact", dimension
    norms = np.zeros((system.M, system.M))
    for (i, j), block in blocks.items():
        norms[i, j] = np.linalg.norm(block, 2)
    return perron_bound(norms), "bound", dimension


def perron_bound(C: np.ndarray, iterations: int = 500) -> float:
    """An upper bound of the spectral radius of a nonnegative matrix C (M, M), tight as the
    iterations grow: the Collatz-Wielandt bound max_i ((C + I) v)_i / v_i - 1 >= rho(C) holds for
    every positive v, and the power iteration on C + I (whose eigenvalue rho(C) + 1 dominates)
    drives v toward the Perron vector, where the bound is rho(C). Matrix products only, so it
    stays cheap where the eigenvalues of C would not (M in the thousands)."""
    shifted = C + np.eye(C.shape[0])
    v = np.ones(C.shape[0])
    best = float("inf")
    for _ in range(iterations):
        w = shifted @ v
        best = min(best, float(np.max(w / v)) - 1.0)
        v = np.maximum(w / np.max(w), 1e-150)  # stays positive: parts that decay would underflow to 0
    return max(best, 0.0)


def closed_loop_dimension(system: CoupledSystem, horizon: int) -> int:
    """The size of the closed loop's state (:func:`closed_loop`) for ``system`` at N = ``horizon``:
    n + sum_i N (n_i + m_i)."""
    return int(system.n + sum(horizon * (s.n + s.m) for s in system.subsystems))


def closed_loop(system: CoupledSystem, K: list[np.ndarray], P: list[np.ndarray], horizon: int,
                rounds: int = 1) -> np.ndarray:
    """The closed loop of the non-cooperative method without its inequality rows, as one matrix.

    Its state at step k is s(k) = (x(k), and for every agent j the plan z_j(1..N | k-1),
    v_j(0..N-1 | k-1) it made at the step before). At step k the first round builds each agent's
    feed-forward from its neighbours' shifted plans (zhat_j(0) = x_j(k), zhat_j(t) = z_j(t+1 | k-1),
    vhat_j(t) = v_j(t+1 | k-1), vhat_j(N-1) = K_j z_j(N | k-1): docs/algorithm.md, "Online step k, agent i"),
    each further round from the plans of the round before; the plant applies u_i(k) = v_i(0 | k)
    of the last round: x(k+1) = A x(k) + B u(k). So s(k+1) = L s(k), and the unconstrained
    method is stable if and only if rho(L) < 1.

    Parameters
    ----------
    system : CoupledSystem
    K, P : lists of ndarray, shapes (m_i, n_i) and (n_i, n_i)
        The terminal gains and weights, in subsystem order.
    horizon : int
        N >= 1.
    rounds : int
        Jacobi rounds per step (``options.iterations``), >= 1; every round is run (no early stop).

    Returns
    -------
    ndarray, shape (D, D), D = n + sum_i N (n_i + m_i)
        L, with s ordered x, then per agent z_j(1..N), v_j(0..N-1), each flattened time-major.
    """
    N, subs = horizon, system.subsystems
    offsets = [system.n]
    for s in subs:
        offsets.append(offsets[-1] + N * (s.n + s.m))
    D = offsets[-1]
    responses = [agent_response(s.A, s.B, s.Q, s.R, P[i], N) for i, s in enumerate(subs)]
    couplings = _active(system)

    def own_state(i: int) -> np.ndarray:
        rows = np.zeros((subs[i].n, D))
        rows[:, system.xs(i)] = np.eye(subs[i].n)
        return rows

    def plan(i: int, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r, x = responses[i], own_state(i)
        return r.Zx @ x + r.Zc @ c, r.Vx @ x + r.Vc @ c

    # round 1: the neighbours' plans of step k-1, shifted
    feed = [np.zeros((N * s.n, D)) for s in subs]
    for cp in couplings:
        i, j = cp.target, cp.source
        n_i, n_j, m_j = subs[i].n, subs[j].n, subs[j].m
        z0, v0 = offsets[j], offsets[j] + N * n_j
        c = feed[i]
        c[:n_i, system.xs(j)] += cp.A
        for t in range(1, N):
            c[t * n_i:(t + 1) * n_i, z0 + t * n_j:z0 + (t + 1) * n_j] += cp.A
        for t in range(N - 1):
            c[t * n_i:(t + 1) * n_i, v0 + (t + 1) * m_j:v0 + (t + 2) * m_j] += cp.B
        c[(N - 1) * n_i:, z0 + (N - 1) * n_j:z0 + N * n_j] += cp.B @ K[j]
    plans = [plan(i, feed[i]) for i in range(system.M)]
    # further rounds: the neighbours' plans of this step, round before
    for _ in range(rounds - 1):
        feed = [np.zeros((N * s.n, D)) for s in subs]
        for cp in couplings:
            i, j = cp.target, cp.source
            n_i, n_j = subs[i].n, subs[j].n
            z_j, v_j = plans[j]
            c = feed[i]
            c[:n_i] += cp.A @ own_state(j)
            for t in range(1, N):
                c[t * n_i:(t + 1) * n_i] += cp.A @ z_j[(t - 1) * n_j:t * n_j]
            c += np.kron(np.eye(N), cp.B) @ v_j
        plans = [plan(i, feed[i]) for i in range(system.M)]
    L = np.zeros((D, D))
    L[:system.n, :system.n] = system.A
    for i, s in enumerate(subs):
        z_i, v_i = plans[i]
        L[:system.n] += system.B[:, system.us(i)] @ v_i[:s.m]
        L[offsets[i]:offsets[i] + N * s.n] = z_i
        L[offsets[i] + N * s.n:offsets[i + 1]] = v_i
    return L


def closed_loop_radius(system: CoupledSystem, K: list[np.ndarray], P: list[np.ndarray], horizon: int,
                       rounds: int = 1, dense_limit: int = DENSE_LIMIT) -> float | None:
    """rho(L) of :func:`closed_loop` (``system``, ``K``, ``P``, ``horizon``, ``rounds`` as there);
    None when L has more than ``dense_limit`` rows."""
    if closed_loop_dimension(system, horizon) > dense_limit:
        return None
    return float(max(abs(np.linalg.eigvals(closed_loop(system, K, P, horizon, rounds)))))


def input_coupling(system: CoupledSystem, K: list[np.ndarray], P: list[np.ndarray], horizon: int,
                   rounds: int = 1, dense_limit: int = DENSE_LIMIT) -> InputCoupling:
    """The input drives of every input-coupled pair, the Jacobi radius and the closed loop's.

    Parameters
    ----------
    system : CoupledSystem
        The controllers' (discrete) model.
    K, P : lists of ndarray, shapes (m_i, n_i) and (n_i, n_i)
        Terminal gains and weights in subsystem order (the design's K_i, P_i).
    horizon : int
        N >= 1.
    rounds : int
        Jacobi rounds per step (``options.iterations``).
    dense_limit : int
        The largest T and L whose eigenvalues are computed.
    """
    radius, kind, dimension = jacobi_radius(system, P, horizon, dense_limit)
    loop = closed_loop_radius(system, K, P, horizon, rounds, dense_limit)
    return InputCoupling(pairs=input_drives(system), horizon=horizon, rounds=rounds, radius=radius, radius_kind=kind,
                         dimension=dimension, loop_radius=loop, loop_dimension=closed_loop_dimension(system, horizon))
