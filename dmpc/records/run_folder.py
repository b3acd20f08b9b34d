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
import orjson

from dmpc.core.errors import DmpcError, InputError
from dmpc.core.steps import StepRecord
from dmpc.core.system import CoupledSystem
from dmpc.records.columns import StepColumns, StepTally, write_npz
from dmpc.records.files import ROWS, STEP_LOG, SUMMARY, TRAJECTORY
from dmpc.records.plant_units import PlantUnits
from dmpc.records.tracking import segment_traces, target_changes, tracking_summary
from dmpc.records.verdict import RunLimits, judge, state_bound_excess


class RunFolderError(InputError):
    """The folder cannot be used for a new run."""


class RecordWriteError(DmpcError):
    """A record could not be written during or at the end of a run (disk full, read-only, ...)."""


def jsonable(value):
    """``value`` as JSON-ready data: arrays as lists, NaN and infinities as None."""
    kind = type(value)  # plain scalars first: a step line is mostly made of them
    if kind is float:
        return value if math.isfinite(value) else None
    if kind is int or kind is str or kind is bool or value is None:
        return value
    if isinstance(value, np.ndarray):
        return _array_json(value)
    if isinstance(value, (list, tuple)):
        if value and all(isinstance(v, np.ndarray) for v in value):
            return [_array_json(v) for v in value]
        return [jsonable(v) for v in value]
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
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
    """Write ``data`` (:func:`jsonable`) as indented JSON to ``path``, whole or not at all (a temporary
    file renamed)."""
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(jsonable(data), indent=2) + "\n")
    os.replace(tmp, path)


def refuse_used(path: Path, marker: str, holds: str) -> None:
    """RunFolderError if ``path`` already holds ``marker`` (what that means: ``holds``, e.g. "a run")."""
    if (path / marker).exists():
        raise RunFolderError(f"{path} already holds {holds} ({marker} exists): choose another --out")


def claim_folder(path: Path, marker: str, holds: str) -> None:
    """Create ``path`` for new output, refusing one that already holds ``marker`` (what it is: ``holds``).

    Raises
    ------
    RunFolderError
        ``path / marker`` exists, or ``path`` cannot be created.
    """
    refuse_used(path, marker, holds)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RunFolderError(f"cannot create folder {path}: {exc.strerror}") from None


class RunFolder:
    """Writes one run's records.

    Memory does not grow with the run's length: each step goes to ``steps.jsonl`` and, as one
    row of numbers, to the rows file of :class:`~dmpc.records.columns.StepColumns`; the arrays
    are built from those rows at the end.

    A write that fails (disk full, read-only, permission) raises RunFolderError naming the file
    and the system's reason; the step log is cut back to its last complete line first, so every
    completed step stays readable.

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
        self.units = PlantUnits.of(system)
        try:
            self._log = open(self.path / STEP_LOG, "a", encoding="utf-8")
            self.columns = StepColumns(system, self.path / ROWS)
        except OSError as exc:
            raise write_error(exc, self.path / STEP_LOG, RunFolderError) from None

    @property
    def steps(self) -> int:
        """Steps recorded so far."""
        return self.columns.tally.steps

    def write_text(self, name: str, text: str) -> None:
        """Write ``text`` to the file ``name`` of the run folder before the run (RunFolderError if it
        cannot be written)."""
        try:
            (self.path / name).write_text(text)
        except OSError as exc:
            raise write_error(exc, self.path / name, RunFolderError) from None

    def write_json(self, name: str, data) -> None:
        """Write ``data`` as the JSON file ``name`` of the run folder before the run (RunFolderError if it
        cannot be written)."""
        try:
            write_json(self.path / name, data)
        except OSError as exc:
            raise write_error(exc, self.path / name, RunFolderError) from None

    def append_step(self, rec: StepRecord) -> None:
        """Append the step ``rec`` to the log (flushed) and to the rows of the arrays."""
        text = step_text(rec, self.units)
        log_end = self._log.tell()
        try:
            self._log.write(text)
            self._log.flush()
        except OSError as exc:
            self._cut_back(log_end)
            raise write_error(exc, self.path / STEP_LOG) from None
        try:
            self.columns.add(rec)
        except OSError as exc:
            self._cut_back(log_end)
            raise write_error(exc, self.path / ROWS) from None

    def _cut_back(self, log_end: int) -> None:
        """Drop a partly written last line (truncating needs no free space)."""
        try:
            self._log.close()
        except OSError:
            pass  # its buffer could not be flushed: the truncation below removes what got through
        try:
            os.truncate(self.path / STEP_LOG, log_end)
        except OSError:
            pass

    def close(self) -> None:
        for closer in (self._log.close, self.columns.close):
            try:
                closer()
            except OSError:
                pass

    def finish(self, extra: dict | None = None, limits: RunLimits | None = None, labels: dict | None = None,
               dt: float | None = None) -> dict:
        """Write ``trajectory.npz`` and ``summary.json`` from the recorded steps, with ``extra`` added to
        the summary; returns the summary.

        ``limits`` (the planned steps and Jacobi caps) feed the verdict; without them the run is
        judged as planned to the steps it has; ``labels`` name the states and inputs in its
        messages; ``dt``, the seconds per step if known, gives the setpoints' settling times in
        seconds. RunFolderError if a file cannot be written.
        """
        self.close()
        arrays = self.columns.arrays()
        try:
            write_npz(self.path / TRAJECTORY, {**_public(arrays), **layout_arrays(self.system)},
                      None if self.units is None else self.units.array)
        except OSError as exc:
            raise write_error(exc, self.path / TRAJECTORY) from None
        extra = dict(extra or {})
        summary = summarise(self.system, self.columns.tally, arrays, limits or RunLimits(steps=self.steps),
                            extra.get("inputs_refused"), labels, dt)
        summary.update(extra)
        try:
            write_json(self.path / SUMMARY, summary)
        except OSError as exc:
            raise write_error(exc, self.path / SUMMARY) from None
        try:
            os.unlink(self.path / ROWS)
        except OSError:
            pass
        return summary


def step_text(rec: StepRecord, units: PlantUnits | None = None) -> str:
    """The step record ``rec`` as its ``steps.jsonl`` line (docs/records.md), with its newline, in
    the plant's ``units`` when the run has an operating point.

    Written for every step on the coordinator's step path, so serialised in one call of a C
    encoder: arrays as nested lists, NaN and infinities as ``null``, as :func:`step_line` gives them.
    """
    return orjson.dumps(_line_fields(rec, units), default=jsonable, option=_STEP_OPTIONS).decode()


_STEP_OPTIONS = orjson.OPT_SERIALIZE_NUMPY | orjson.OPT_APPEND_NEWLINE


def step_line(rec: StepRecord, units: PlantUnits | None = None) -> dict:
    """The step record ``rec`` as its ``steps.jsonl`` line (docs/records.md), JSON-ready, in the plant's
    ``units`` when the run has an operating point."""
    return jsonable(_line_fields(rec, units))


def _line_fields(rec: StepRecord, units: PlantUnits | None = None) -> dict:
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
    if rec.solve_reason is not None:
        line["solve_reason"] = rec.solve_reason
    if rec.estimate is not None:
        e = rec.estimate
        line.update({"y": e.y, "x_hat": e.x_hat, "d_hat": e.d_hat, "innovation": e.innovation})
    if rec.tracking is not None and rec.tracking.active:
        t = rec.tracking
        line.update({"setpoint": t.request.x, "setpoint_u": t.request.u, "reference": t.reference.x,
                     "reference_u": t.reference.u, "target": t.applied.x, "target_u": t.applied.u,
                     "governor": t.theta})
        if t.request.y is not None:
            line["setpoint_y"] = t.request.y
    return line if units is None else units.line(line)


def write_error(exc: OSError, path: Path, cls: type[DmpcError] = RecordWriteError) -> DmpcError:
    """One line naming the file ``path`` and the system's reason ``exc``, e.g. for a full disk, as a
    ``cls`` (RecordWriteError by default)."""
    return cls(f"cannot write {path}: {exc.strerror or exc}")


def _public(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The arrays that go into trajectory.npz (the fallback codes stay internal)."""
    return {k: v for k, v in arrays.items() if k != "fallback_code"}


def _columns_of(system: CoupledSystem, records: list[StepRecord]) -> StepColumns:
    columns = StepColumns(system)
    for rec in records:
        columns.add(rec)
    return columns


def trajectory_arrays(system: CoupledSystem, records: list[StepRecord]) -> dict[str, np.ndarray]:
    """Arrays of a run of ``system`` from its step ``records``: x (K+1, n), u (K, m), alpha (K+1, n),
    beta (K+1,), J (K,), S (K+1,), ...

    Also J_agents, solve_time, latency (K, M), qp_iterations (K, M) int, fallback (K, M) bool,
    rounds (K,) int, step_time, max_change (K,), and per subsystem plan_z_<name> (K, N+1, n_i),
    plan_v_<name> (K, N, m_i). The ellipsoid methods add r (K+1, M), the levels r_i(k).
    """
    return _public(_columns_of(system, records).arrays())


def layout_arrays(system: CoupledSystem) -> dict[str, np.ndarray]:
    """How to split the stacked arrays of ``system``: ``names`` (M,) str, ``state_sizes`` and
    ``input_sizes`` (M,) int."""
    return {"names": np.array([s.name for s in system.subsystems], dtype=str),
            "state_sizes": np.array([s.n for s in system.subsystems], dtype=int),
            "input_sizes": np.array([s.m for s in system.subsystems], dtype=int)}


def stage_cost(system: CoupledSystem, x: np.ndarray, u: np.ndarray) -> float:
    """l(x, u) = x'Qx + u'Ru for the global system."""
    return float(x @ system.Q @ x + u @ system.R @ u)


def summarise(system: CoupledSystem, steps: StepTally | list[StepRecord], arrays: dict[str, np.ndarray],
              limits: RunLimits | None = None, inputs_refused: dict[str, int] | None = None,
              labels: dict | None = None, dt: float | None = None) -> dict:
    """The content of summary.json of a run of ``system``, with the run's verdict
    (:mod:`dmpc.records.verdict`) judged against ``limits`` (the planned steps and Jacobi caps;
    None: as planned to the steps it has), and the inputs the plant refused per reason
    (``inputs_refused``).

    ``steps`` is the tally of a :class:`~dmpc.records.columns.StepColumns`, or the step records
    themselves (then ``arrays`` may come from :func:`trajectory_arrays`). ``labels`` are the
    scenario's names of states and inputs for the verdict's messages (:func:`~dmpc.records.verdict.judge`)
    and the setpoints' segments; ``dt``, the seconds per step if known, their settling times in
    seconds (:func:`~dmpc.records.tracking.segments`).
    """
    if not isinstance(steps, StepTally):
        columns = _columns_of(system, steps)
        steps = columns.tally
        arrays = {**arrays, "fallback_code": columns.arrays()["fallback_code"]}
    K = steps.steps
    u = arrays["u"]
    bound_excess = 0.0
    for i, sub in enumerate(system.subsystems):
        bound_excess = max(bound_excess, sub.input_set.largest_excess(u[:, system.us(i)]))
    J = arrays["J"]
    # costs around the targets applied (the origin without setpoints); the decrease of Theorem 3
    # holds between target changes only
    dx = arrays["x"][:K] - arrays["target"] if "target" in arrays else arrays["x"][:K]
    du = u - arrays["target_u"] if "target_u" in arrays else u
    changed = target_changes(arrays)
    decrease: list[float | None] = []
    for k in range(K - 1):
        l_k = stage_cost(system, dx[k], du[k])
        decrease.append(None if changed[k] else float(J[k] - l_k - J[k + 1]))
    fallbacks_per_agent = arrays["fallback"].sum(axis=0).tolist() if K else [0] * system.M
    solve = np.asarray(arrays["solve_time"], float)
    if "kept" in arrays:
        solve = solve[~np.asarray(arrays["kept"], bool)]  # a kept plan was not solved
    finite_solve = solve[np.isfinite(solve)]
    step_time = arrays["step_time"][np.isfinite(arrays["step_time"])]
    notes = steps.notes
    limits = limits or RunLimits(steps=K)
    traces = segment_traces(system, arrays, labels, dt, limits.setpoint_margin)
    verdict = judge(system, arrays, notes, limits, inputs_refused, steps.reasons, labels, traces)
    names = [s.name for s in system.subsystems]
    return {
        "verdict": verdict.word,
        "failures": [f.to_json() for f in verdict.failures],
        "warnings": [f.to_json() for f in verdict.warnings],
        "steps": K,
        "feasible": bool(K > 0 and steps.all_solved),
        "qp_failed": steps.qp_failed,
        "plans_missing": steps.plans_missing,
        "fallbacks": int(arrays["fallback"].sum()),
        "fallbacks_per_agent": dict(zip([s.name for s in system.subsystems], fallbacks_per_agent)),
        "fallback_steps": [[int(k), system.subsystems[i].name] for k, i in zip(*np.nonzero(arrays["fallback"]))],
        "max_abs_u": float(np.max(np.abs(u))) if K else 0.0,
        "input_bound_excess": bound_excess,
        "state_bound_excess": state_bound_excess(system, arrays["x"]),
        "J": J.tolist(),
        "S": arrays["S"].tolist(),
        "beta": arrays["beta"].tolist(),
        "final_state_norm_inf": float(np.max(np.abs(arrays["x"][-1]))),
        "closed_loop_cost": float(sum(stage_cost(system, dx[k], du[k]) for k in range(K))),
        "theorem3_margin": decrease,
        "J_non_increasing": bool(all(np.diff(J)[~changed] <= 1e-9)) if K > 1 else True,
        "rounds_k0": int(arrays["rounds"][0]) if K else 0,
        "notes": notes,
        "solve_time_median_s": float(np.median(finite_solve)) if finite_solve.size else None,
        "step_time_median_s": float(np.median(step_time)) if step_time.size else None,
        "step_time_p99_s": float(np.percentile(step_time, 99)) if step_time.size else None,
        **({"tracking": tracked} if (tracked := tracking_summary(system, arrays, labels, dt, limits.setpoint_margin,
                                                                 traces)) is not None else {}),
        # the norms above are of the model's deviations: say so when the records are in the plant's units
        **({"operating_point": True} if system.has_operating_point else {}),
        **({"keeps": sum(steps.keeps), "keeps_per_agent": dict(zip(names, steps.keeps)),
            "solve_reasons": dict(sorted(steps.solve_reasons.items()))} if steps.keeps else {}),
    }
