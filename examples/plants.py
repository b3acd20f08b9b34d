"""Plants of your own for the examples: functions (x, u, k) -> x_next.

``dmpc.simulate(scenario, plant=f)`` takes any such function; ``dmpc.run`` and
``dmpc plant --model examples/plants.py:carts_stiffening_springs`` need it at the top level of
a module like this one, which the plant process imports.
"""
from __future__ import annotations

import numpy as np

SPRING = 0.25      # N/m, as in scenarios/carts-continuous.yaml
DAMPER = 0.1       # N s/m
STIFFENING = 0.01  # N/m^3: the springs get stiffer as they stretch (not in the controllers' model)
DT = 0.1           # s, the scenario's dt
SUBSTEPS = 10


def _carts_rates(x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """dx/dt of three carts on a line joined by stiffening springs and dampers; x = (p1, v1, p2, v2, p3, v3)."""
    p, v = x[0::2], x[1::2]
    force = np.array(u, dtype=float)
    for i, j in ((0, 1), (1, 2)):
        stretch, closing = p[i] - p[j], v[i] - v[j]
        pull = SPRING * stretch + STIFFENING * stretch ** 3 + DAMPER * closing
        force[i] -= pull
        force[j] += pull
    rates = np.empty_like(x)
    rates[0::2], rates[1::2] = v, force
    return rates


def carts_stiffening_springs(x: np.ndarray, u: np.ndarray, k: int) -> np.ndarray:
    """One period dt of the three carts with stiffening springs, integrated with RK4 (u held)."""
    h = DT / SUBSTEPS
    for _ in range(SUBSTEPS):
        a = _carts_rates(x, u)
        b = _carts_rates(x + h / 2 * a, u)
        c = _carts_rates(x + h / 2 * b, u)
        d = _carts_rates(x + h * c, u)
        x = x + h / 6 * (a + 2 * b + 2 * c + d)
    return x
