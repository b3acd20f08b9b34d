"""The messages of the step protocol (typed, immutable).

- ``Release`` plant -> agent i: step k, Jacobi round, the measured states of N_i, alpha_i, beta
  and, per neighbour, which of its plans to build the assumed trajectory from.
- ``PlanMessage`` agent i -> neighbours and plant: the solved plan of (k, round).
- ``Ready`` agent -> plant: the agent is set up (with the digest of its design).
- ``Stop`` plant -> everyone: the run is over (finished, aborted, failed).

Agents are named by the scenario's subsystem names; the plant is ``"plant"``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

SCHEMA_VERSION = 1
PLANT = "plant"


@dataclass(frozen=True)
class Release:
    """Step k, round ``iteration``, released to agent ``target``.

    Attributes
    ----------
    states : dict name -> ndarray (n_j,)
        x_j(k) for every j in N_i (i included).
    alpha : ndarray, shape (n_i,)
    beta : float
    assumed : dict name -> (k', round') or None
        For each neighbour j != i: build its assumed trajectory from its plan of (k', round');
        None means the decoupled K-rollout from x_j(k).
    provided : dict name -> (z, v)
        Plans supplied by the coordinator itself (the centralised seed at k = 0); they stand for
        the neighbours' plans named in ``assumed``. Usually empty.
    """

    run: str
    k: int
    iteration: int
    target: str
    states: dict[str, np.ndarray]
    alpha: np.ndarray
    beta: float
    assumed: dict[str, tuple[int, int] | None]
    sender: str = PLANT
    provided: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)


@dataclass(frozen=True)
class PlanMessage:
    """Agent ``sender``'s plan for (k, iteration).

    Attributes
    ----------
    status : str
        A QPStatus value.
    z : ndarray, shape (N + 1, n_i)
    v : ndarray, shape (N, m_i)
        Both all-NaN when the QP was not solved.
    cost : float
        J_i of the plan (NaN when not solved).
    solve_time : float
        Seconds in the solver.
    qp_iterations : int
    sent_at : float
        Sender's clock when published (latency measurement only).
    """

    run: str
    k: int
    iteration: int
    sender: str
    status: str
    z: np.ndarray
    v: np.ndarray
    cost: float
    solve_time: float
    qp_iterations: int
    sent_at: float = 0.0


@dataclass(frozen=True)
class Ready:
    """Agent ``sender`` is set up and subscribed; ``design_digest`` identifies its design."""

    run: str
    sender: str
    design_digest: str
    pid: int = 0


@dataclass(frozen=True)
class Stop:
    """The run is over at step k; ``reason`` is ``finished``, ``aborted`` or ``failed: ...``."""

    run: str
    k: int
    reason: str
    sender: str = PLANT


Message = Release | PlanMessage | Ready | Stop

MESSAGE_TYPES: dict[str, type] = {"release": Release, "plan": PlanMessage, "ready": Ready, "stop": Stop}
TYPE_NAMES: dict[type, str] = {v: k for k, v in MESSAGE_TYPES.items()}


def messages_equal(a: Message, b: Message) -> bool:
    """Equality that compares arrays by value (NaN equal to NaN)."""
    if type(a) is not type(b):
        return False
    for name in a.__dataclass_fields__:
        x, y = getattr(a, name), getattr(b, name)
        if not _values_equal(x, y):
            return False
    return True


def _values_equal(x, y) -> bool:
    if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
        return (isinstance(x, np.ndarray) and isinstance(y, np.ndarray) and x.shape == y.shape
                and x.dtype == y.dtype and np.array_equal(x, y, equal_nan=True))
    if isinstance(x, (tuple, list)):
        return isinstance(y, (tuple, list)) and len(x) == len(y) and all(_values_equal(a, b) for a, b in zip(x, y))
    if isinstance(x, dict):
        return isinstance(y, dict) and x.keys() == y.keys() and all(_values_equal(x[k], y[k]) for k in x)
    if isinstance(x, float) and isinstance(y, float) and np.isnan(x) and np.isnan(y):
        return True
    return x == y

