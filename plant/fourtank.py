"""The quadruple-tank process of the HD-MPC benchmark (Alvarado et al., "A comparative analysis of
distributed MPC techniques applied to the HD-MPC four-tank benchmark", J. Process Control 21(5),
2011): its nonlinear equations, their equilibrium and linearisation, and the plant that integrates
them over a sampling period (``plant.model: fourtank``, docs/fourtank.md).

Four tanks of area S; tank i drains through an outlet of area a_i at the rate a_i sqrt(2 g h_i)
(Torricelli). Pump a delivers q_a, split by its valve: gamma_a q_a into tank 1, (1 - gamma_a) q_a
into tank 4; pump b delivers q_b: gamma_b q_b into tank 2, (1 - gamma_b) q_b into tank 3. Tank 3
drains into tank 1, tank 4 into tank 2:

    S dh1/dt = -a1 sqrt(2 g h1) + a3 sqrt(2 g h3) + gamma_a q_a
    S dh2/dt = -a2 sqrt(2 g h2) + a4 sqrt(2 g h4) + gamma_b q_b
    S dh3/dt = -a3 sqrt(2 g h3) + (1 - gamma_b) q_b
    S dh4/dt = -a4 sqrt(2 g h4) + (1 - gamma_a) q_a

Units: levels h in m, time in s, areas in m^2, g in m/s^2, and the flows q in m^3/h as the
benchmark gives them: every flow is divided by 3600 s/h where it enters the equations, so the
rates are in m/s. The order of the arrays here is always (h1, h2, h3, h4) and (q_a, q_b); a
scenario names its states and inputs so that :class:`FourTankPlant` finds them in any partition.

Everything here is numpy only and pure, except the plant object, which holds its parameters.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SECONDS_PER_HOUR = 3600.0
"""Flows are given in m^3/h; the equations are in m and s."""
LEVELS = ("h1", "h2", "h3", "h4")
"""The names a scenario gives the four levels (states), in the order of the arrays here."""
PUMPS = ("qa", "qb")
"""The names a scenario gives the two pump flows (inputs), in the order of the arrays here."""
SUBSTEPS = 5
"""RK4 steps per sampling period by default (1 s each at the benchmark's dt = 5 s)."""


@dataclass(frozen=True)
class FourTank:
    """The parameters of the process (defaults: the HD-MPC benchmark).

    Attributes
    ----------
    area : float
        S, the cross-section of each tank, m^2.
    outlets : tuple of 4 floats
        a_1 .. a_4, the outlet areas, m^2.
    gamma : tuple of 2 floats
        (gamma_a, gamma_b), the valve splits in (0, 1): the fraction of pump a's flow that goes to
        tank 1 and of pump b's flow that goes to tank 2.
    g : float
        Gravity, m/s^2.
    """

    area: float = 0.06
    outlets: tuple[float, float, float, float] = (1.31e-4, 1.51e-4, 9.27e-5, 8.82e-5)
    gamma: tuple[float, float] = (0.3, 0.4)
    g: float = 9.81

    def inflow_matrix(self) -> np.ndarray:
        """How the pumps feed the tanks: shape (4, 2), each column sums to 1 (tank i gets
        ``inflow_matrix() @ q``)."""
        ga, gb = self.gamma
        return np.array([[ga, 0.0], [0.0, gb], [0.0, 1.0 - gb], [1.0 - ga, 0.0]])


def outflows(tanks: FourTank, h: np.ndarray) -> np.ndarray:
    """a_i sqrt(2 g h_i) in m^3/s, shape (4,), of the ``tanks`` at levels h (4,) in m; a level
    below 0 counts as 0 (an empty tank does not drain)."""
    return np.asarray(tanks.outlets) * np.sqrt(2.0 * tanks.g * np.maximum(np.asarray(h, dtype=float), 0.0))


def rates(tanks: FourTank, h: np.ndarray, q: np.ndarray) -> np.ndarray:
    """dh/dt in m/s, shape (4,), of the ``tanks`` at levels h (4,) in m and pump flows q (2,) in m^3/h."""
    out = outflows(tanks, h)
    inflow = tanks.inflow_matrix() @ (np.asarray(q, dtype=float) / SECONDS_PER_HOUR)
    inflow[0] += out[2]  # tank 3 drains into tank 1
    inflow[1] += out[3]  # tank 4 drains into tank 2
    return (inflow - out) / tanks.area


def equilibrium(tanks: FourTank, q0: np.ndarray) -> np.ndarray:
    """The levels h0 (4,) in m at which the flows q0 (2,) in m^3/h hold the ``tanks`` at rest.

    At rest each tank's outflow equals its inflow, a_i sqrt(2 g h_i) = F_i, so h_i = (F_i / a_i)^2
    / (2 g), with F_3 = (1 - gamma_b) q_b, F_4 = (1 - gamma_a) q_a, F_1 = gamma_a q_a + F_3 and
    F_2 = gamma_b q_b + F_4 (flows in m^3/s).
    """
    ga, gb = tanks.gamma
    qa, qb = np.asarray(q0, dtype=float) / SECONDS_PER_HOUR
    f3, f4 = (1.0 - gb) * qb, (1.0 - ga) * qa
    flows = np.array([ga * qa + f3, gb * qb + f4, f3, f4])
    return (flows / np.asarray(tanks.outlets)) ** 2 / (2.0 * tanks.g)


def linearisation(tanks: FourTank, h0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The Jacobians of :func:`rates` of the ``tanks`` at levels h0 (4,) > 0: A (4, 4) in 1/s and
    B (4, 2) in (m/s) per (m^3/h).

    d/dh (a sqrt(2 g h)) = a g / sqrt(2 g h), so tank i's own entry is -a_i g / (S sqrt(2 g h_i)),
    and tank 3 (4) adds +a_3 g / (S sqrt(2 g h_3)) to tank 1's (+a_4 ... to tank 2's) row. The
    rates are affine in q, so B is the inflow matrix / (3600 S).
    """
    h0 = np.asarray(h0, dtype=float)
    slope = np.asarray(tanks.outlets) * tanks.g / np.sqrt(2.0 * tanks.g * h0) / tanks.area  # (4,)
    A = np.diag(-slope)
    A[0, 2] = slope[2]
    A[1, 3] = slope[3]
    B = tanks.inflow_matrix() / (SECONDS_PER_HOUR * tanks.area)
    return A, B


def integrate(tanks: FourTank, h: np.ndarray, q: np.ndarray, dt: float, substeps: int = SUBSTEPS) -> np.ndarray:
    """The levels (4,) of the ``tanks`` after dt seconds from h (4,) with the flows q (2,) in m^3/h held, by
    ``substeps`` classical Runge-Kutta steps; every level is clipped at 0 after each step (a tank
    cannot hold less than nothing; the square root is not defined below 0)."""
    h = np.maximum(np.asarray(h, dtype=float), 0.0)
    step = dt / substeps
    for _ in range(substeps):
        k1 = rates(tanks, h, q)
        k2 = rates(tanks, h + 0.5 * step * k1, q)
        k3 = rates(tanks, h + 0.5 * step * k2, q)
        k4 = rates(tanks, h + step * k3, q)
        h = np.maximum(h + step / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4), 0.0)
    return h


class FourTankPlant:
    """The plant function (x, u, k) -> x_next of a scenario whose states are the four levels and
    whose inputs are the two pump flows, in deviation from the operating point.

    x holds the deviations h - h0 in m, u the deviations q - q0 in m^3/h, both in the scenario's
    global order; ``state_index[i]`` is where level h_(i+1) sits in x, ``input_index`` where q_a and
    q_b sit in u. h0 is the equilibrium of q0 (:func:`equilibrium`), so x = 0, u = 0 stays at 0.

    Parameters
    ----------
    tanks : FourTank
    q0 : ndarray, shape (2,)
        The operating flows, m^3/h.
    dt : float
        The sampling period, s.
    state_index : sequence of 4 ints
    input_index : sequence of 2 ints
    substeps : int
        RK4 steps per period.
    """

    def __init__(self, tanks: FourTank, q0: np.ndarray, dt: float, state_index: tuple[int, ...],
                 input_index: tuple[int, ...], substeps: int = SUBSTEPS) -> None:
        self.tanks = tanks
        self.q0 = np.asarray(q0, dtype=float)
        self.h0 = equilibrium(tanks, self.q0)
        self.dt = float(dt)
        self.state_index = np.asarray(state_index, dtype=int)
        self.input_index = np.asarray(input_index, dtype=int)
        self.substeps = int(substeps)

    def __call__(self, x: np.ndarray, u: np.ndarray, k: int) -> np.ndarray:
        """x(k+1) (n,) from x(k) (n,) and u(k) (m,); states other than the four levels are kept."""
        x = np.asarray(x, dtype=float)
        h = self.h0 + x[self.state_index]
        q = self.q0 + np.asarray(u, dtype=float)[self.input_index]
        out = x.copy()
        out[self.state_index] = integrate(self.tanks, h, q, self.dt, self.substeps) - self.h0
        return out
