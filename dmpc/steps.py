"""What a run's steps are made of: the protocol's settings and the record of one step.

Shared by the coordinator that builds the records, the centralised and direct loops, the run
folder that writes them and the live view that shows them, so it sits below all of them.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ProtocolOptions:
    """What the coordinator needs from the scenario's options."""

    steps: int
    iterations: int = 1
    tolerance: float = 1e-9
    initial_iterations: int = 200
    initial_tolerance: float = 1e-9


@dataclass(frozen=True)
class StepRecord:
    """Everything recorded about one step, built once when the step completes.

    Array shapes: x (n,), u (m,), alpha (n,), x_next (n,); per-agent lists have M entries.
    ``r`` and ``r_next`` (M,) are the ellipsoid levels of the ellipsoid methods (None otherwise);
    those methods record alpha = 0 and beta = NaN.

    ``latency`` (M,) is, per agent, the time from the agent publishing the plan the step used to
    the host receiving it (NaN for an agent without a plan, or where no clock is kept);
    ``step_time`` is the step's wall time on the host's clock (NaN where none is kept).
    """

    k: int
    x: np.ndarray
    u: np.ndarray
    alpha: np.ndarray
    beta: float
    x_next: np.ndarray
    alpha_next: np.ndarray
    beta_next: float
    J: float
    J_agents: list[float]
    S: float
    rounds: int
    max_change: float
    status: list[str]
    fallback: list[bool]
    fallback_reason: list[str]
    solve_time: list[float]
    qp_iterations: list[int]
    plans_z: list[np.ndarray]
    plans_v: list[np.ndarray]
    latency: list[float]
    step_time: float
    note: str = ""
    r: np.ndarray | None = None
    r_next: np.ndarray | None = None
