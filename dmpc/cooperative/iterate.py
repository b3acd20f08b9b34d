"""The cooperative iterate of the whole system and how the agents' proposals combine into the next.

An iterate is every subsystem's planned inputs v (N, m) over the horizon and the states z (N+1, n)
they give from the measured x(k) under the model: z(t+1) = A z(t) + B v(t), z(0) = x(k). Everything
here works in deviation coordinates around the step's target (x_s, u_s), a steady state of the
whole system, where the dynamics are the same and only the constraint sets move.

Agent l proposes new inputs v_l* with every other agent's inputs at the iterate's. The state
trajectory is affine in the inputs, so with the directions D_l = (v_l* - v_l, the states they move),
any iterate

    (z, v) + sum_l w_l D_l,   w_l >= 0,  sum_l w_l <= 1,

is a convex combination of the iterate and the proposals, each a feasible point of the
centralised problem when the iterate is: it is feasible, and by convexity its cost is at most the
weighted mean of theirs, so at most the iterate's (Stewart, Venkat, Rawlings & Wright, "Cooperative
distributed model predictive control", Syst. Control Lett. 59, 2010). :func:`combine` takes
w_l = s for every agent: ``equal`` with s = 1/M (the paper's weights), ``line`` with the s in
[0, 1] of least cost whose iterate still meets every constraint (found exactly: the cost is a
quadratic in s and every constraint row an affine function of it). s = 1/M meets them, so
``line`` is never worse than ``equal``, and it takes the whole of every proposal where the agents
do not interact. Proposals are solved to the QP solver's accuracy, not exactly: the rows are met
to ROW_TOLERANCE beyond what the iterate already does, and a step that would leave one by more
stops short (for either rule) — feasibility is never traded for the weights.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np
import scipy.sparse as sp

from dmpc.core.system import CoupledSystem, stack_sets

StepRule = Literal["line", "equal"]
"""How the proposals of a round combine (``options.cooperative_step``)."""
STEP_RULES: tuple[StepRule, ...] = get_args(StepRule)
DEFAULT_STEP_RULE: StepRule = "line"

ROW_TOLERANCE = 1e-9
"""A combined iterate may leave a constraint row by this much times max(1, |bound|) beyond what
the iterate and the equal-weight point already do (the proposals meet their rows to the QP
solver's accuracy, not exactly)."""


@dataclass(frozen=True)
class Iterate:
    """Planned inputs and the states they give, in deviation coordinates.

    Attributes
    ----------
    z : ndarray, shape (N + 1, n)
    v : ndarray, shape (N, m)
    """

    z: np.ndarray
    v: np.ndarray

    def moved(self, x_s: np.ndarray, u_s: np.ndarray) -> "Iterate":
        """The same plans with x_s (n,) added to the states and u_s (m,) to the inputs."""
        return Iterate(self.z + x_s, self.v + u_s)


@dataclass(frozen=True)
class Combination:
    """The next iterate of a round and how it was reached.

    Attributes
    ----------
    iterate : Iterate
    step : float
        The weight s every proposal was taken with (0 when no proposal moved anything).
    cost_before, cost_after : float
        The global cost V of the iterate before and after.
    change : float
        max |z' - z|, |v' - v| over the whole iterate.
    """

    iterate: Iterate
    step: float
    cost_before: float
    cost_after: float
    change: float


class GlobalModel:
    """The coupled system's model, weights and constraints as the coordinator's iterate needs them.

    Parameters
    ----------
    system : CoupledSystem
    K : list of ndarray
        K_i, shape (m_i, n_i): the terminal controller of the tail.
    P : list of ndarray
        P_i, shape (n_i, n_i): the terminal weights.
    horizon : int
    """

    def __init__(self, system: CoupledSystem, K: list[np.ndarray], P: list[np.ndarray], horizon: int) -> None:
        self.system = system
        self.N = horizon
        self.M = system.M
        self.A = sp.csr_matrix(system.A)
        self.B = sp.csr_matrix(system.B)
        self.K = sp.block_diag(K, format="csr")
        self.Q = sp.csr_matrix(system.Q)
        self.R = sp.csr_matrix(system.R)
        self.P = sp.block_diag(P, format="csr")
        subs = system.subsystems
        self.U = stack_sets([s.input_set for s in subs], [s.m for s in subs], sparse=True)
        self.X = stack_sets([s.state_set for s in subs], [s.n for s in subs], sparse=True)

    # ------------------------------------------------------------------ trajectories
    def simulate(self, x: np.ndarray, v: np.ndarray) -> np.ndarray:
        """z (N+1, n) from z(0) = x (n,) under the inputs v (N, m)."""
        z = np.empty((v.shape[0] + 1, x.size))
        z[0] = x
        Bv = (self.B @ v.T).T
        for t in range(v.shape[0]):
            z[t + 1] = self.A @ z[t] + Bv[t]
        return z

    def rollout(self, x: np.ndarray) -> Iterate:
        """The terminal controller from x (n,): v(t) = K z(t), z(t+1) = A z(t) + B v(t)."""
        z = np.empty((self.N + 1, x.size))
        v = np.empty((self.N, self.K.shape[0]))
        z[0] = x
        for t in range(self.N):
            v[t] = self.K @ z[t]
            z[t + 1] = self.A @ z[t] + self.B @ v[t]
        return Iterate(z, v)

    def shifted(self, iterate: Iterate, x: np.ndarray) -> Iterate:
        """The iterate of step k shifted to step k+1: v(1..N-1) then K z(N), from the measured x (n,).

        With the plant equal to the model, its states are z(1..N) and (A + BK) z(N)."""
        v = np.empty_like(iterate.v)
        v[:-1] = iterate.v[1:]
        v[-1] = self.K @ iterate.z[-1]
        return Iterate(self.simulate(x, v), v)

    # ------------------------------------------------------------------ cost
    def stage_costs(self, iterate: Iterate) -> np.ndarray:
        """Each subsystem's part of the cost, shape (M,): sum_t z_i'Q_i z_i + v_i'R_i v_i + z_i(N)'P_i z_i(N).

        Parameters
        ----------
        iterate : Iterate
            z (N+1, n) and v (N, m) of the whole system, deviation coordinates.
        """
        z, v = iterate.z, iterate.v
        per_state = ((self.Q @ z[:-1].T).T * z[:-1]).sum(axis=0) + (self.P @ z[-1]) * z[-1]
        per_input = ((self.R @ v.T).T * v).sum(axis=0)
        sysm = self.system
        return np.array([per_state[sysm.xs(i)].sum() + per_input[sysm.us(i)].sum() for i in range(self.M)])

    def cost(self, iterate: Iterate) -> float:
        """The global cost V of the iterate."""
        return float(self._inner(iterate.z, iterate.v, iterate.z, iterate.v))

    def _inner(self, z1: np.ndarray, v1: np.ndarray, z2: np.ndarray, v2: np.ndarray) -> float:
        """The cost's bilinear form <(z1, v1), (z2, v2)>."""
        return float(((self.Q @ z1[:-1].T).T * z2[:-1]).sum() + (self.P @ z1[-1]) @ z2[-1]
                     + ((self.R @ v1.T).T * v2).sum())

    # ------------------------------------------------------------------ constraints
    def rows(self, iterate: Iterate, x_s: np.ndarray, u_s: np.ndarray, alpha: np.ndarray,
             beta: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every constraint row of the centralised problem at the iterate: values, lower, upper.

        The inputs' rows at t = 0..N-1, the states' at t = 1..N, all moved to deviation
        coordinates around (x_s (n,), u_s (m,)), and the terminal box |z(N) - alpha| <= beta
        (alpha (n,), deviation coordinates)."""
        values, lower, upper = [], [], []
        for rows, part, shift in ((self.U, iterate.v, u_s), (self.X, iterate.z[1:], x_s)):
            if rows is None or rows.H.shape[0] == 0:
                continue
            moved = rows.H @ shift
            values.append((rows.H @ part.T).T.ravel())
            lower.append(np.tile(rows.lower - moved, part.shape[0]))
            upper.append(np.tile(rows.upper - moved, part.shape[0]))
        values.append(iterate.z[-1])
        lower.append(alpha - beta)
        upper.append(alpha + beta)
        return np.concatenate(values), np.concatenate(lower), np.concatenate(upper)

    def excess(self, iterate: Iterate, x_s: np.ndarray, u_s: np.ndarray, alpha: np.ndarray, beta: float) -> float:
        """The largest excess of the iterate over its rows (:meth:`rows`), relative to max(1, |bound|); 0 if feasible.

        Parameters
        ----------
        iterate : Iterate
            z (N+1, n) and v (N, m), deviation coordinates.
        x_s, u_s : ndarray, shapes (n,), (m,)
            The target the deviation coordinates are taken around (the state and input rows move by it).
        alpha : ndarray, shape (n,)
            The terminal box centre, deviation coordinates.
        beta : float
            The terminal box radius.
        """
        values, lower, upper = self.rows(iterate, x_s, u_s, alpha, beta)
        return _largest_excess(values, lower, upper)


def _largest_excess(values: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> float:
    with np.errstate(invalid="ignore"):
        over = np.maximum((values - upper) / np.maximum(1.0, np.abs(upper)),
                          (lower - values) / np.maximum(1.0, np.abs(lower)))
    over = over[np.isfinite(over)]
    return max(float(over.max()), 0.0) if over.size else 0.0


def combine(model: GlobalModel, iterate: Iterate, proposals: dict[int, np.ndarray], x_s: np.ndarray,
            u_s: np.ndarray, alpha: np.ndarray, beta: float, rule: StepRule = DEFAULT_STEP_RULE) -> Combination:
    """The next iterate from the agents' proposals (see the module's text).

    Parameters
    ----------
    model : GlobalModel
    iterate : Iterate
        The round's iterate, deviation coordinates.
    proposals : dict i -> ndarray (N, m_i)
        Agent i's proposed inputs, deviation coordinates; an agent without one keeps its inputs.
    x_s, u_s : ndarray, shapes (n,), (m,)
        The target the deviation coordinates are taken around (for the constraint rows).
    alpha : ndarray, shape (n,)
        The terminal box centre, deviation coordinates.
    beta : float
        The terminal box radius.
    rule : {"line", "equal"}
    """
    system = model.system
    dv = np.zeros_like(iterate.v)
    for i, proposal in proposals.items():
        part = system.us(i)
        dv[:, part] = proposal - iterate.v[:, part]
    before = model.cost(iterate)
    if not dv.any():
        return Combination(iterate, 0.0, before, before, 0.0)
    dz = model.simulate(np.zeros(iterate.z.shape[1]), dv)
    equal = 1.0 / model.M
    top = _largest_step(model, iterate, dz, dv, x_s, u_s, alpha, beta)
    step = min(equal, top) if rule == "equal" else _best_step(model, iterate, dz, dv, top)
    if step <= 0.0:
        return Combination(iterate, 0.0, before, before, 0.0)
    nxt = Iterate(iterate.z + step * dz, iterate.v + step * dv)
    after = model.cost(nxt)
    if after > before:
        # proposals solved only to the QP solver's accuracy (unpolished, or stopped at its
        # iteration cap) can be worse than the iterate, typically when it is already optimal (k = 0
        # from the centralised plan): keep the iterate, so that the cost never rises
        return Combination(iterate, 0.0, before, before, 0.0)
    change = max(float(np.abs(step * dz).max()), float(np.abs(step * dv).max()))
    return Combination(nxt, step, before, after, change)


def _best_step(model: GlobalModel, iterate: Iterate, dz: np.ndarray, dv: np.ndarray, top: float) -> float:
    """The s in [0, top] of least cost: V(s) = V(0) + 2 s g + s^2 h is a convex quadratic."""
    g = model._inner(iterate.z, iterate.v, dz, dv)
    h = model._inner(dz, dv, dz, dv)
    if h <= 0.0:
        return 0.0
    return float(min(max(-g / h, 0.0), top))


def _largest_step(model: GlobalModel, iterate: Iterate, dz: np.ndarray, dv: np.ndarray, x_s: np.ndarray,
                  u_s: np.ndarray, alpha: np.ndarray, beta: float) -> float:
    """The largest s in [0, 1] whose iterate meets every row within ROW_TOLERANCE of what the
    iterate itself does (a ratio test: each row is affine in s).

    With proposals that meet their QPs' rows exactly, s = 1/M always passes (the iterate is a
    convex combination of feasible points); proposals solved only to the solver's accuracy may
    leave a row by more than the tolerance, and then the step stops short of where they would."""
    values, lower, upper = model.rows(iterate, x_s, u_s, alpha, beta)
    direction, _, _ = model.rows(Iterate(dz, dv), np.zeros_like(x_s), np.zeros_like(u_s), np.zeros_like(alpha), 0.0)
    # direction holds the rows' change per unit s (the rows are linear in the iterate; the bounds
    # came out of the second call shifted by zero)
    allowance = _largest_excess(values, lower, upper) + ROW_TOLERANCE
    hi = upper + allowance * np.maximum(1.0, np.abs(upper))
    lo = lower - allowance * np.maximum(1.0, np.abs(lower))
    top = 1.0
    with np.errstate(divide="ignore", invalid="ignore"):
        up = direction > 0
        if up.any():
            top = min(top, float(np.min((hi[up] - values[up]) / direction[up])))
        down = direction < 0
        if down.any():
            top = min(top, float(np.min((lo[down] - values[down]) / direction[down])))
    return max(top, 0.0)
