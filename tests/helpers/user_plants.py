"""Plant functions (x, u, k) -> x_next for the tests of ``plant=`` and ``--model``."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from dmpc.scenario import build_system, load_scenario

PAPER = Path(__file__).resolve().parents[2] / "scenarios" / "paper.yaml"
_SYSTEM = build_system(load_scenario(PAPER))
NONLINEARITY = 0.02


def mildly_nonlinear(x: np.ndarray, u: np.ndarray, k: int) -> np.ndarray:
    """The paper's example plus a small sine term the controllers do not know about."""
    return _SYSTEM.A @ x + _SYSTEM.B @ u + NONLINEARITY * np.sin(x)


def fails_at_step_2(x: np.ndarray, u: np.ndarray, k: int) -> np.ndarray:
    """The paper's example until step 2, where the function raises."""
    if k == 2:
        raise ZeroDivisionError("a bug in the user's plant")
    return _SYSTEM.A @ x + _SYSTEM.B @ u
