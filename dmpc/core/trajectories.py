"""Plans, their shifted continuations and the coupling feed-forward
(docs/algorithm.md, "Online step k, agent i", items 1, 2 and 7).

A plan made at step k' is ``z`` (N+1, n) and ``v`` (N, m). Beyond its horizon it is continued
with the local terminal controller: z(N+q) = Gamma^q z(N), v(N-1+q) = K z(N-1+q), Gamma = A_ii + B_ii K_i.
(The global tail would need the neighbours' terminal states; the local one is what an agent can
compute alone, and it is only ever used after missed plans.)

With setpoints, plans and states are taken in deviation coordinates around the step's steady state
(:class:`OperatingPoint`; docs/algorithm.md, "Setpoints"); without them that steady state is the
origin, and the same code runs with zeros.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import NamedTuple, overload

import numpy as np

from dmpc.core.system import CoupledSystem


@dataclass(frozen=True)
class Plan:
    """A plan made at step ``k`` in Jacobi round ``round``.

    Attributes
    ----------
    k, round : int
    z : ndarray, shape (N + 1, n)
    v : ndarray, shape (N, m)
    """

    k: int
    round: int
    z: np.ndarray
    v: np.ndarray


@overload
def relative_to(plan: Plan, x_s: np.ndarray, u_s: np.ndarray) -> Plan: ...
@overload
def relative_to(plan: None, x_s: np.ndarray, u_s: np.ndarray) -> None: ...
def relative_to(plan: Plan | None, x_s: np.ndarray, u_s: np.ndarray) -> Plan | None:
    """The plan in deviation coordinates around a steady state: z - x_s (x_s (n,)), v - u_s (u_s (m,));
    no plan (None, a K-rollout stands for it) stays none."""
    if plan is None:
        return None
    return Plan(plan.k, plan.round, plan.z - x_s, plan.v - u_s)


class OperatingPoint(NamedTuple):
    """The steady state (x_s, u_s) that plans and states are taken around, of the whole system or of
    one subsystem: deviation coordinates dz = z - x_s, dv = v - u_s (docs/algorithm.md, "Setpoints").

    Without a setpoint it is the origin (zeros), and the same arithmetic runs: z - 0.0 is z exactly,
    and z + 0.0 is z up to the sign of a zero (-0.0 + 0.0 = 0.0), which no comparison sees. The one
    way the agents, their neighbours and the coordinator move plans to and from a setpoint target,
    so that they compute the same floats.

    Attributes
    ----------
    x : ndarray, shape (n,)
        x_s.
    u : ndarray, shape (m,)
        u_s.
    """

    x: np.ndarray
    u: np.ndarray

    @classmethod
    def origin(cls, n: int, m: int) -> OperatingPoint:
        """The origin of n states and m inputs: the operating point without a setpoint."""
        return cls(np.zeros(n), np.zeros(m))

    def subsystem(self, system: CoupledSystem, i: int) -> OperatingPoint:
        """Subsystem i's part (x_s_i (n_i,), u_s_i (m_i,)) of an operating point of the whole ``system``."""
        return OperatingPoint(self.x[system.xs(i)], self.u[system.us(i)])

    def state_around(self, x: np.ndarray) -> np.ndarray:
        """A state (n,) in deviation coordinates: x - x_s."""
        around: np.ndarray = x - self.x
        return around

    @overload
    def plan_around(self, plan: Plan) -> Plan: ...
    @overload
    def plan_around(self, plan: None) -> None: ...
    def plan_around(self, plan: Plan | None) -> Plan | None:
        """A plan (z (N+1, n), v (N, m)) in deviation coordinates (:func:`relative_to`); None stays None."""
        return relative_to(plan, self.x, self.u)

    def trajectory_back(self, z: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """States z (T+1, n) and inputs v (T, m) of deviation coordinates in the plant's: z + x_s, v + u_s."""
        return z + self.x, v + self.u

    def plan_back(self, plan: Plan) -> Plan:
        """A plan in deviation coordinates, in the plant's (:meth:`trajectory_back`)."""
        return Plan(plan.k, plan.round, plan.z + self.x, plan.v + self.u)

    def same_as(self, other: OperatingPoint) -> bool:
        """Whether ``other`` has the same x_s and u_s as this one, value for value (shapes included)."""
        return bool(np.array_equal(self.x, other.x) and np.array_equal(self.u, other.u))


def gamma_powers(Gamma: np.ndarray, N: int) -> np.ndarray:
    """Gamma^0 .. Gamma^N, shape (N + 1, n, n), each the product of the one before and Gamma.

    Kept for the last few matrices asked for: an agent, its neighbours and the coordinator ask
    for the same few at every step, and the same floats make the same kept plans."""
    return _powers(np.asarray(Gamma, float).tobytes(), Gamma.shape[0], N)


@functools.lru_cache(maxsize=4096)
def _powers(data: bytes, n: int, N: int) -> np.ndarray:
    Gamma = np.frombuffer(data, dtype=float).reshape(n, n)
    powers = np.empty((N + 1, n, n))
    powers[0] = np.eye(n)
    for t in range(1, N + 1):
        powers[t] = Gamma @ powers[t - 1]
    powers.setflags(write=False)
    return powers


def kept_plan(plan: Plan, k: int, x_now: np.ndarray, end: np.ndarray, Gamma: np.ndarray, K: np.ndarray) -> Plan:
    """The plan made at step k - 1, kept at step k: shifted by one step, corrected for the
    prediction error e = x_now - z(k|k-1) by the terminal controller, and ended at ``end``.

    z(t) = z(k+t|k-1) + Gamma^t e and v(t) = v(k+t|k-1) + K Gamma^t e for t < N - 1,
    v(N-1) = K z(N-1), z(N) = end + Gamma^N e; ``end`` is where the coupled system takes the plans'
    last states under K (alpha_i(k) for the time-varying boxes). Every party that knows the plan,
    x_now and ``end`` computes the same floats.

    Parameters
    ----------
    plan : Plan
        Made at step k - 1: z (N+1, n), v (N, m).
    x_now : ndarray, shape (n,)
    end : ndarray, shape (n,)
    Gamma : ndarray, shape (n, n)
    K : ndarray, shape (m, n)
    """
    N = plan.v.shape[0]
    e = x_now - plan.z[1]
    correction = gamma_powers(Gamma, N) @ e  # (N + 1, n): Gamma^t e
    z = np.empty_like(plan.z, dtype=float)
    z[:N] = plan.z[1:] + correction[:N]
    z[N] = end + correction[N]
    v = np.empty_like(plan.v, dtype=float)
    v[:N - 1] = plan.v[1:] + correction[:N - 1] @ K.T
    v[N - 1] = K @ z[N - 1]
    z[0] = x_now
    return Plan(k, 0, z, v)


def kept_around(plan: Plan, k: int, x_now: np.ndarray, end: np.ndarray, Gamma: np.ndarray, K: np.ndarray,
                point: OperatingPoint) -> Plan:
    """:func:`kept_plan` of a plan in the plant's coordinates, taken in deviation coordinates around
    the operating point of step k, ``point`` = (x_s (n,), u_s (m,)) (the origin without a setpoint),
    and given back in the plant's (``end`` is relative to it, as alpha_i(k) is). The one way the
    agent, its neighbours and the coordinator build a kept plan, so that they hold the same floats.

    Parameters
    ----------
    plan : Plan
        Made at step k - 1, in the plant's coordinates: z (N+1, n), v (N, m).
    k : int
        The step at which the plan is kept.
    x_now : ndarray, shape (n,)
        The measured state x(k), in the plant's coordinates.
    end : ndarray, shape (n,)
        Where the kept plan ends, relative to x_s (alpha_i(k) for the time-varying boxes).
    Gamma : ndarray, shape (n, n)
        The local terminal dynamics A_ii + B_ii K_i.
    K : ndarray, shape (m, n)
        The local terminal gain K_i.
    point : OperatingPoint
        The step's operating point (x_s (n,), u_s (m,)); any pair of arrays is taken as one.
    """
    point = OperatingPoint(*point)
    kept = kept_plan(point.plan_around(plan), k, point.state_around(x_now), end, Gamma, K)
    return point.plan_back(kept)


def continued(plan: Plan, length: int, Gamma: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The plan extended with the terminal controller.

    Parameters
    ----------
    plan : Plan
        z (N+1, n), v (N, m).
    length : int
        The horizon of the result; at most N, the plan cut to it.
    Gamma : ndarray, shape (n, n)
        The local terminal dynamics A_ii + B_ii K_i: z(t) = Gamma z(t-1) beyond N.
    K : ndarray, shape (m, n)
        The local terminal gain: v(t) = K z(t) beyond N - 1.

    Returns
    -------
    z : ndarray, shape (length + 1, n)
    v : ndarray, shape (length, m)
    """
    N = plan.v.shape[0]
    if length <= N:
        return plan.z[: length + 1].copy(), plan.v[:length].copy()
    z = np.empty((length + 1, plan.z.shape[1]))
    z[: N + 1] = plan.z
    for t in range(N + 1, length + 1):
        z[t] = Gamma @ z[t - 1]
    v = np.empty((length, plan.v.shape[1]))
    v[:N] = plan.v
    v[N:] = z[N:length] @ K.T
    return z, v


def assumed_trajectory(plan: Plan | None, k: int, x_now: np.ndarray, N: int, Gamma: np.ndarray,
                       K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A neighbour's assumed trajectory at step k (Assumption 1 with a measured first state).

    ``zhat[0] = x_now``; ``zhat[t] = z(k+t | k')`` and ``vhat[t] = v(k+t | k')`` from the plan
    made at k' <= k; without a plan, the decoupled K-rollout from x_now.

    Parameters
    ----------
    plan : Plan or None
        The neighbour's plan made at k' <= k (z (N'+1, n), v (N', m)), or None.
    k : int
        The step.
    x_now : ndarray, shape (n,)
        The neighbour's measured state x_j(k).
    N : int
        The horizon.
    Gamma : ndarray, shape (n, n)
        The neighbour's terminal dynamics A_jj + B_jj K_j.
    K : ndarray, shape (m, n)
        The neighbour's terminal gain K_j.

    Returns
    -------
    zhat : ndarray, shape (N, n)
    vhat : ndarray, shape (N, m)
    """
    if plan is None:
        return k_rollout(x_now, N, Gamma, K)
    shift = k - plan.k
    if shift == 1 and plan.v.shape[0] == N:  # the usual case, without building the continuation
        zhat = np.empty((N, plan.z.shape[1]))
        zhat[0] = x_now
        zhat[1:] = plan.z[2:]
        vhat = np.empty((N, plan.v.shape[1]))
        vhat[:-1] = plan.v[1:]
        vhat[-1:] = plan.z[N:N + 1] @ K.T
        return zhat, vhat
    z, v = continued(plan, N + shift, Gamma, K)
    zhat = z[shift : shift + N].copy()
    zhat[0] = x_now
    return zhat, v[shift : shift + N]


def k_rollout(x: np.ndarray, N: int, Gamma: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """zhat(t) = Gamma^t x, vhat(t) = K zhat(t), t = 0..N-1; shapes (N, n) and (N, m)."""
    states = [np.asarray(x, float)]
    for _ in range(N - 1):
        states.append(Gamma @ states[-1])
    z = np.array(states)
    return z, (K @ z.T).T


def candidate_plan(plan: Plan | None, k: int, x_now: np.ndarray | None, N: int, Gamma: np.ndarray,
                   K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The candidate plan at step k: the plan made at k' <= k shifted to k and continued with the
    terminal controller, or without a plan the K-rollout from x_now (needed only then).

    Parameters
    ----------
    plan : Plan or None
        The plan made at k' <= k (z (N'+1, n), v (N', m)), or None.
    k : int
        The step.
    x_now : ndarray, shape (n,), or None
        The state x(k) the K-rollout starts from; may be None when there is a plan.
    N : int
        The horizon.
    Gamma : ndarray, shape (n, n)
        The terminal dynamics A + B K.
    K : ndarray, shape (m, n)
        The terminal gain.

    Returns
    -------
    z : ndarray, shape (N + 1, n)
    v : ndarray, shape (N, m)
    """
    if plan is None:
        if x_now is None:
            raise ValueError("a candidate without a plan is the K-rollout from x_now: give x_now")
        z, v = k_rollout(x_now, N + 1, Gamma, K)
        return z, v[:N]
    shift = k - plan.k
    if shift == 1 and plan.v.shape[0] == N:  # the usual case, without building the continuation
        z = np.empty_like(plan.z, dtype=float)
        z[:N] = plan.z[1:]
        z[N] = Gamma @ plan.z[N]
        v = np.empty_like(plan.v, dtype=float)
        v[:-1] = plan.v[1:]
        v[-1:] = plan.z[N:N + 1] @ K.T
        return z, v
    z, v = continued(plan, shift + N, Gamma, K)
    return z[shift:], v[shift:]


def shifted_input(plan: Plan | None, k: int, x_now: np.ndarray, Gamma: np.ndarray, K: np.ndarray) -> np.ndarray:
    """The fallback input v*(k|k') + K (x(k) - z*(k|k')), or K x(k) without a plan; shape (m,).

    Parameters
    ----------
    plan : Plan or None
        The last plan, made at k' <= k (z (N+1, n), v (N, m)), continued with the terminal
        controller where k is beyond its horizon; or None.
    k : int
        The step.
    x_now : ndarray, shape (n,)
        The measured state x(k).
    Gamma : ndarray, shape (n, n)
        The terminal dynamics A + B K.
    K : ndarray, shape (m, n)
        The terminal gain.
    """
    u: np.ndarray
    if plan is None:
        u = K @ x_now
        return u
    shift = k - plan.k
    z, v = continued(plan, shift + 1, Gamma, K)
    u = v[shift] + K @ (x_now - z[shift])
    return u


def coupling_feedforward(A_blocks: list[np.ndarray], B_blocks: list[np.ndarray | None],
                         assumed: list[tuple[np.ndarray, np.ndarray]], N: int, n: int) -> np.ndarray:
    """c(t) = sum_j A_ij zhat_j(t) + B_ij vhat_j(t), shape (N, n).

    ``A_blocks[q]``, ``B_blocks[q]`` and ``assumed[q]`` belong to the same neighbour j != i; a
    ``B_blocks[q]`` of None stands for zeros.
    """
    c = np.zeros((N, n))
    for Aij, Bij, (zhat, vhat) in zip(A_blocks, B_blocks, assumed):
        c += zhat @ Aij.T if Bij is None else zhat @ Aij.T + vhat @ Bij.T
    return c
