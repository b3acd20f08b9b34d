"""Checks on finished closed-loop runs, recomputed from the scenario's own numbers (used by
tests/test_cooperative_runs.py and tests/test_cooperative_properties.py).

Bounds and weights come from the scenario's subsystem specs (the numbers the file or mapping
gives), never from the run's summary; the per-step statuses from the run folder's step log.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dmpc.api.result import Result
from dmpc.scenario import Scenario

SOLVED = "solved"
"""The status every QP of a nominal cooperative run must report (not even ``solved_inaccurate``)."""


def read_steps(folder: Path) -> list[dict]:
    """Every line of the run folder's ``steps.jsonl``, as dicts."""
    return [json.loads(line) for line in (Path(folder) / "steps.jsonl").read_text().splitlines() if line]


def dense_block_diag(blocks: list[np.ndarray]) -> np.ndarray:
    out = np.zeros((sum(b.shape[0] for b in blocks), sum(b.shape[1] for b in blocks)))
    r = c = 0
    for b in blocks:
        out[r:r + b.shape[0], c:c + b.shape[1]] = b
        r, c = r + b.shape[0], c + b.shape[1]
    return out


@dataclass(frozen=True)
class Bounds:
    """The boxes of the whole system in the global order (subsystems in scenario order);
    +-inf where a side or a whole set is missing."""

    x_lower: np.ndarray
    x_upper: np.ndarray
    u_lower: np.ndarray
    u_upper: np.ndarray


def _side(values, size: int, default: float) -> np.ndarray:
    if values is None:
        return np.full(size, default)
    return np.array([default if v is None else float(v) for v in values])


def scenario_bounds(scenario: Scenario) -> Bounds:
    """The input and state boxes as the scenario gives them (``input`` and ``state`` of every subsystem)."""
    xl, xu, ul, uu = [], [], [], []
    for spec in scenario.resolved_subsystems():
        n, m = len(spec.A), len(spec.B[0])
        state, inputs = spec.state, spec.input
        xl.append(_side(None if state is None else state.lower, n, -np.inf))
        xu.append(_side(None if state is None else state.upper, n, np.inf))
        ul.append(_side(None if inputs is None else inputs.lower, m, -np.inf))
        uu.append(_side(None if inputs is None else inputs.upper, m, np.inf))
    return Bounds(np.concatenate(xl), np.concatenate(xu), np.concatenate(ul), np.concatenate(uu))


def bound_excess(result: Result, bounds: Bounds) -> tuple[float, float]:
    """The largest excess of the states x(0..K) and of the inputs u(0..K-1) over their boxes
    (<= 0 when every bound holds)."""
    def excess(values: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> float:
        with np.errstate(invalid="ignore"):
            over = np.maximum(values - upper, lower - values)
        return float(np.max(over)) if over.size else -np.inf

    return (excess(result.stacked_x(), bounds.x_lower, bounds.x_upper),
            excess(result.stacked_u(), bounds.u_lower, bounds.u_upper))


def cost_weights(scenario: Scenario) -> tuple[np.ndarray, np.ndarray]:
    """Q = diag(Q_i) and R = diag(R_i) as the scenario gives them."""
    specs = scenario.resolved_subsystems()
    return (dense_block_diag([np.asarray(s.Q, float) for s in specs]),
            dense_block_diag([np.asarray(s.R, float) for s in specs]))


def stacked(parts, names) -> np.ndarray:
    return np.hstack([parts[name] for name in names])


@dataclass(frozen=True)
class Decrease:
    """J(k+1) - (J(k) - l(x(k), u(k))) at every k whose applied target stays at k+1 (``margin``,
    <= 0 is the decrease), those k (``steps``), and the k whose target moved (``moved``)."""

    margin: np.ndarray
    steps: np.ndarray
    moved: np.ndarray


def cost_decrease(result: Result, Q: np.ndarray, R: np.ndarray) -> Decrease:
    """The stage cost l(x(k), u(k)) around the applied target of step k (``Result.target``,
    ``Result.target_u``: zeros without setpoints) against the drop of J between k and k+1, at every
    step whose target the next step keeps (J is measured from the target applied, so it jumps
    where the target moves)."""
    names = result.names
    target, target_u = stacked(result.target, names), stacked(result.target_u, names)
    dx = result.stacked_x()[:-1] - target
    du = result.stacked_u() - target_u
    stage = np.einsum("ki,ij,kj->k", dx, Q, dx) + np.einsum("ki,ij,kj->k", du, R, du)
    J = np.asarray(result.J, float)
    stays = np.all(target[1:] == target[:-1], axis=1) & np.all(target_u[1:] == target_u[:-1], axis=1)
    k = np.flatnonzero(stays)
    return Decrease(margin=J[k + 1] - (J[k] - stage[k]), steps=k, moved=np.flatnonzero(~stays) + 1)


def statuses(steps: list[dict]) -> set[str]:
    """Every QP status the step log holds."""
    return {status for step in steps for status in step["status"]}


def fallback_steps(steps: list[dict]) -> list[tuple[int, list[str]]]:
    """(k, reasons) of every step with a fallback."""
    return [(step["k"], step["fallback_reason"]) for step in steps if any(step["fallback"])]


def recorded_iterates(folder: Path, names) -> tuple[np.ndarray, np.ndarray]:
    """The plans every step recorded, stacked over the subsystems (``trajectory.npz``'s
    ``plan_z_<name>``, ``plan_v_<name>``): z (K, N+1, n) and v (K, N, m), plant coordinates. For
    ``tv-box-coop`` they are the step's last iterate."""
    arrays = np.load(Path(folder) / "trajectory.npz")
    return (np.concatenate([arrays[f"plan_z_{name}"] for name in names], axis=2),
            np.concatenate([arrays[f"plan_v_{name}"] for name in names], axis=2))


def plan_cost(z: np.ndarray, v: np.ndarray, Q: np.ndarray, R: np.ndarray, P: np.ndarray) -> float:
    """sum_{t<N} z(t)'Q z(t) + v(t)'R v(t) + z(N)'P z(N), term by term (deviation coordinates)."""
    return sum(float(z[t] @ Q @ z[t] + v[t] @ R @ v[t]) for t in range(v.shape[0])) + float(z[-1] @ P @ z[-1])


def designed(scenario):
    """The prepared ``scenario``, or None where its design fails (a DesignError: the gains, or the
    estimator, undetectable or unstable when coupled; a panic of Clarabel in the LMI is one too)."""
    import dmpc
    from dmpc.setup import prepare

    try:
        return prepare(scenario)
    except dmpc.DesignError:
        return None
