"""The run folder: resolved scenario, design, per-step log, arrays, summary (docs/records.md).

``steps.jsonl`` gets one line per completed step, flushed as it is written, so a crash loses
at most the step in flight. ``trajectory.npz`` and ``summary.json`` are written at the end
(and on an orderly abort) from the steps recorded.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from dmpc.plant.barrier import StepRecord
from dmpc.system import CoupledSystem

STEP_LOG = "steps.jsonl"


class RunFolderError(Exception):
    """The folder cannot be used for a new run."""


def _jsonable(value):
    if isinstance(value, np.ndarray):
        return _array_json(value)
    if isinstance(value, (list, tuple)):
        if value and all(isinstance(v, np.ndarray) for v in value):
            return [_array_json(v) for v in value]
        return [_jsonable(v) for v in value]
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (float, np.floating)):
        v = float(value)
        return None if math.isnan(v) or math.isinf(v) else v
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value


def _array_json(a: np.ndarray) -> list:
    """Nested lists with NaN and inf as None (strict JSON), without a Python-level walk."""
    if a.dtype.kind != "f" or np.isfinite(a).all():
        return a.tolist()
    obj = a.astype(object)
    obj[~np.isfinite(a)] = None
    return obj.tolist()


def write_json(path: Path, data) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(_jsonable(data), indent=2) + "\n")
    os.replace(tmp, path)


def claim_folder(path: Path, marker: str, holds: str) -> None:
    """Create ``path`` for new output, refusing one that already holds ``marker`` (what it is: ``holds``).

    Raises
    ------
    RunFolderError
        ``path / marker`` exists, or ``path`` cannot be created.
    """
    if (path / marker).exists():
        raise RunFolderError(f"{path} already holds {holds} ({marker} exists): choose another --out")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RunFolderError(f"cannot create folder {path}: {exc.strerror}") from None


class RunFolder:
    """Writes one run's records.

    Parameters
    ----------
    path : path-like
        Created if missing; refused if it already holds a run's step log.
    system : CoupledSystem
    """

    def __init__(self, path, system: CoupledSystem) -> None:
        self.path = Path(path)
        claim_folder(self.path, STEP_LOG, "a run")
        self.system = system
        self.records: list[StepRecord] = []
        self._log = open(self.path / STEP_LOG, "a", encoding="utf-8")

    def write_text(self, name: str, text: str) -> None:
        (self.path / name).write_text(text)

    def write_json(self, name: str, data) -> None:
        write_json(self.path / name, data)

    def append_step(self, rec: StepRecord) -> None:
        """Append one step to the log (flushed) and keep it for the arrays."""
        self.records.append(rec)
        line = {
            "k": rec.k, "x": rec.x, "u": rec.u, "alpha": rec.alpha, "beta": rec.beta, "J": rec.J,
            "J_agents": rec.J_agents, "S": rec.S, "rounds": rec.rounds, "max_change": rec.max_change,
            "status": rec.status, "fallback": rec.fallback, "fallback_reason": rec.fallback_reason,
            "solve_time": rec.solve_time, "qp_iterations": rec.qp_iterations, "latency": rec.latency,
            "step_time": rec.step_time, "x_next": rec.x_next, "alpha_next": rec.alpha_next,
            "beta_next": rec.beta_next, "note": rec.note,
        }
        if rec.r is not None:
            line["r"], line["r_next"] = rec.r, rec.r_next
        self._log.write(json.dumps(_jsonable(line)) + "\n")
        self._log.flush()

    def close(self) -> None:
        if not self._log.closed:
            self._log.close()

    def finish(self, extra: dict | None = None) -> dict:
        """Write ``trajectory.npz`` and ``summary.json`` from the recorded steps; returns the summary."""
        self.close()
        arrays = trajectory_arrays(self.system, self.records)
        np.savez(self.path / "trajectory.npz", **arrays)
        summary = summarise(self.system, self.records, arrays)
        summary.update(extra or {})
        self.write_json("summary.json", summary)
        return summary


def trajectory_arrays(system: CoupledSystem, records: list[StepRecord]) -> dict[str, np.ndarray]:
    """Arrays of a run: x (K+1, n), u (K, m), alpha (K+1, n), beta (K+1,), J (K,), S (K+1,), ...

    The ellipsoid methods add r (K+1, M), the levels r_i(k).
    """
    K = len(records)
    M = system.M
    if K == 0:
        x = system.x0[None, :]
        empty = np.zeros((0, M))
        return {"x": x, "u": np.zeros((0, system.m)), "alpha": np.zeros((1, system.n)), "beta": np.zeros(1),
                "J": np.zeros(0), "S": np.array([_S(system, system.x0)]), "J_agents": empty, "solve_time": empty,
                "qp_iterations": empty.astype(int), "fallback": empty.astype(bool), "latency": empty,
                "rounds": np.zeros(0, int), "step_time": np.zeros(0), "max_change": np.zeros(0)}
    x = np.vstack([r.x for r in records] + [records[-1].x_next])
    arrays = {
        "x": x,
        "u": np.vstack([r.u for r in records]),
        "alpha": np.vstack([r.alpha for r in records] + [records[-1].alpha_next]),
        "beta": np.array([r.beta for r in records] + [records[-1].beta_next]),
        "J": np.array([r.J for r in records]),
        "S": np.array([r.S for r in records] + [_S(system, records[-1].x_next)]),
        "J_agents": np.array([r.J_agents for r in records]),
        "solve_time": np.array([r.solve_time for r in records], dtype=float),
        "qp_iterations": np.array([r.qp_iterations for r in records], dtype=int),
        "fallback": np.array([r.fallback for r in records], dtype=bool),
        "latency": np.array([r.latency if r.latency else [np.nan] * M for r in records], dtype=float),
        "rounds": np.array([r.rounds for r in records], dtype=int),
        "step_time": np.array([r.step_time for r in records], dtype=float),
        "max_change": np.array([r.max_change for r in records], dtype=float),
    }
    if records[0].r is not None:
        arrays["r"] = np.vstack([r.r for r in records] + [records[-1].r_next])
    for i, s in enumerate(system.subsystems):
        arrays[f"plan_z_{s.name}"] = np.array([r.plans_z[i] for r in records])
        arrays[f"plan_v_{s.name}"] = np.array([r.plans_v[i] for r in records])
    return arrays


def _S(system: CoupledSystem, x: np.ndarray) -> float:
    parts = system.split_state(x)
    return float(sum(parts[i] @ parts[i] / len(system.neighbours[i]) for i in range(system.M)))


def stage_cost(system: CoupledSystem, x: np.ndarray, u: np.ndarray) -> float:
    """l(x, u) = x'Qx + u'Ru for the global system."""
    return float(x @ system.Q @ x + u @ system.R @ u)


def summarise(system: CoupledSystem, records: list[StepRecord], arrays: dict[str, np.ndarray]) -> dict:
    """The content of summary.json."""
    K = len(records)
    statuses = [s for r in records for s in r.status]
    u = arrays["u"]
    bound_excess = 0.0
    for i, sub in enumerate(system.subsystems):
        if K:
            Hu = u[:, system.us(i)] @ sub.input_set.H.T
            bound_excess = max(bound_excess, float(np.max(Hu - sub.input_set.upper)),
                               float(np.max(sub.input_set.lower - Hu)))
    J = arrays["J"]
    decrease = []
    for k in range(K - 1):
        l_k = stage_cost(system, arrays["x"][k], u[k])
        decrease.append(float(J[k] - l_k - J[k + 1]))
    fallbacks_per_agent = arrays["fallback"].sum(axis=0).tolist() if K else [0] * system.M
    solve = arrays["solve_time"]
    finite_solve = solve[np.isfinite(solve)]
    step_time = arrays["step_time"][np.isfinite(arrays["step_time"])]
    return {
        "steps": K,
        "feasible": bool(K > 0 and all(s in ("solved", "solved_inaccurate") for s in statuses)),
        "fallbacks": int(arrays["fallback"].sum()),
        "fallbacks_per_agent": dict(zip([s.name for s in system.subsystems], fallbacks_per_agent)),
        "fallback_steps": [[int(k), system.subsystems[i].name] for k, i in zip(*np.nonzero(arrays["fallback"]))],
        "max_abs_u": float(np.max(np.abs(u))) if K else 0.0,
        "input_bound_excess": bound_excess,
        "J": J.tolist(),
        "S": arrays["S"].tolist(),
        "beta": arrays["beta"].tolist(),
        "final_state_norm_inf": float(np.max(np.abs(arrays["x"][-1]))),
        "closed_loop_cost": float(sum(stage_cost(system, arrays["x"][k], u[k]) for k in range(K))),
        "theorem3_margin": decrease,
        "J_non_increasing": bool(all(np.diff(J) <= 1e-9)) if K > 1 else True,
        "rounds_k0": int(arrays["rounds"][0]) if K else 0,
        "notes": [f"k={r.k}: {r.note}" if not r.note.startswith("k=") else r.note for r in records if r.note],
        "solve_time_median_s": float(np.median(finite_solve)) if finite_solve.size else None,
        "step_time_median_s": float(np.median(step_time)) if step_time.size else None,
        "step_time_p99_s": float(np.percentile(step_time, 99)) if step_time.size else None,
    }
