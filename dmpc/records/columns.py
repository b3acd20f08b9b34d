"""The numbers of a run's steps, kept in fixed-width rows on disk (or in memory), not as objects.

A run folder must not grow in memory with the run's length: a controller may run for days.
Each completed step becomes one row of float64 values with a fixed layout (the arrays of
``trajectory.npz`` for that step, plus the codes of the fallback reasons), appended to
``.steps.f64`` in the run folder. At the end the rows are read back through a memory map and
written to ``trajectory.npz`` array by array, a block of rows at a time, so memory stays bounded
by the work of one step, whatever the number of steps.

The same class keeps the rows in a list when it has no file (tests, in-memory runs), so both
paths build their arrays with the same code.
"""
from __future__ import annotations

import os
import zipfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dmpc.core.qp_status import KEPT, PLANNED, SOLVED, QPStatus
from dmpc.core.steps import StepRecord
from dmpc.core.system import CoupledSystem

BLOCK_ROWS = 4096
"""Rows copied at a time when ``trajectory.npz`` is written."""
FINAL = ("x", "alpha", "beta", "S", "r")
"""Columns that get one more row at the end: the state (terminal set) after the last step."""
_INT = {"qp_iterations", "rounds"}
_QP_FAILED = frozenset(status.value for status in QPStatus) - SOLVED
"""Statuses of a QP that ran and gave no plan (the others without a plan: missed, lost)."""
_BOOL = {"fallback", "kept"}


@dataclass(frozen=True)
class Column:
    """Where one array lives in a row: ``row[start:start + size]`` reshaped to ``shape``."""

    start: int
    shape: tuple[int, ...]

    @property
    def size(self) -> int:
        return int(np.prod(self.shape, dtype=int))


@dataclass
class StepTally:
    """What the summary needs beyond the arrays, kept small whatever the run's length.

    Attributes
    ----------
    steps : int
    all_solved : bool
        Every agent's status of every step was a solved one.
    qp_failed : int
        Agent-steps whose QP gave no plan (infeasible, max_iter, ...).
    plans_missing : int
        Agent-steps without a plan in time (missed or lost): no QP status to judge.
    notes : list of str
        ``k=K: note`` for the steps that have a note (events, not steps: bounded by what happens).
    reasons : list of str
        The fallback reasons seen; their index is the code stored per step and agent ("" is 0).
    keeps : list of int
        Per agent, the steps it kept its plan (an event trigger).
    solve_reasons : dict
        With an event trigger: why agents solved, reason -> agent-steps.
    """

    steps: int = 0
    all_solved: bool = True
    qp_failed: int = 0
    plans_missing: int = 0
    notes: list[str] = field(default_factory=list)
    reasons: list[str] = field(default_factory=lambda: [""])
    keeps: list[int] = field(default_factory=list)
    solve_reasons: dict[str, int] = field(default_factory=dict)

    def code(self, reason: str) -> int:
        """The index of the fallback ``reason`` in :attr:`reasons` (added if new)."""
        try:
            return self.reasons.index(reason)
        except ValueError:
            self.reasons.append(reason)
            return len(self.reasons) - 1


class StepColumns:
    """Rows of step numbers, appended one per completed step.

    Parameters
    ----------
    system : CoupledSystem
    path : Path, optional
        The rows file; None keeps the rows in memory.
    disturbance_sizes : sequence of int, optional
        With estimation, n_d,i per subsystem: written as ``disturbance_sizes`` beside ``d_hat``
        (the system knows the output sizes p_i, not the disturbance models).
    """

    def __init__(self, system: CoupledSystem, path: Path | None = None,
                 disturbance_sizes: Sequence[int] | None = None) -> None:
        self.system = system
        self.path = path
        self.disturbance_sizes = None if disturbance_sizes is None else [int(v) for v in disturbance_sizes]
        self.tally = StepTally()
        self.layout: dict[str, Column] | None = None
        self.width = 0
        self.last: StepRecord | None = None
        self._rows: list[np.ndarray] = []
        self._file = None if path is None else open(path, "ab", buffering=0)
        self._end = 0 if self._file is None else self._file.tell()

    # ------------------------------------------------------------------ writing
    def _values(self, rec: StepRecord) -> dict[str, np.ndarray]:
        values = {
            "x": rec.x, "u": rec.u, "alpha": rec.alpha, "beta": rec.beta, "J": rec.J, "S": rec.S,
            "J_agents": rec.J_agents, "solve_time": rec.solve_time, "qp_iterations": rec.qp_iterations,
            "fallback": rec.fallback, "latency": rec.latency, "rounds": rec.rounds, "step_time": rec.step_time,
            "max_change": rec.max_change,
            "fallback_code": [self.tally.code(r) for r in rec.fallback_reason],
        }
        if rec.r is not None:
            values["r"] = rec.r
        if rec.solve_reason is not None:
            values["kept"] = [status == KEPT for status in rec.status]
        if rec.estimate is not None:
            e = rec.estimate
            values.update({"y": e.y, "x_hat": e.x_hat, "d_hat": e.d_hat, "innovation": e.innovation})
        if rec.tracking is not None:
            t = rec.tracking
            values.update({"setpoint": t.request.x, "setpoint_u": t.request.u, "reference": t.reference.x,
                           "reference_u": t.reference.u, "target": t.applied.x, "target_u": t.applied.u,
                           "governor": t.theta})
            if rec.estimate is not None or t.request.y is not None:
                # with estimation requests name outputs: a column in every row (free, NaN, while
                # nothing is requested), so that the rows keep one layout
                values["setpoint_y"] = t.request.y if t.request.y is not None else np.full(self.system.p, np.nan)
        for i, s in enumerate(self.system.subsystems):
            values[f"plan_z_{s.name}"] = rec.plans_z[i]
            values[f"plan_v_{s.name}"] = rec.plans_v[i]
        return {key: np.asarray(v, dtype=float) for key, v in values.items()}

    def _set_layout(self, values: dict[str, np.ndarray]) -> dict[str, Column]:
        start, layout = 0, {}
        for key, v in values.items():
            layout[key] = Column(start, v.shape)
            start += v.size
        self.layout, self.width = layout, start
        return layout

    def add(self, rec: StepRecord) -> bytes:
        """Append the step ``rec``; returns the bytes written (for the caller's error handling)."""
        values = self._values(rec)
        layout = self.layout if self.layout is not None else self._set_layout(values)
        row = np.concatenate([values[key].ravel() for key in layout])
        if row.size != self.width:
            raise ValueError(f"step {rec.k}: {row.size} values, the rows of this run have {self.width}")
        data = b""
        if self._file is None:
            self._rows.append(row)
        else:
            data = row.tobytes()
            self._write(data)
        t = self.tally
        t.steps += 1
        t.all_solved = t.all_solved and all(s in PLANNED for s in rec.status)
        t.qp_failed += sum(s in _QP_FAILED for s in rec.status)
        t.plans_missing += sum(s not in PLANNED and s not in _QP_FAILED for s in rec.status)
        if rec.solve_reason is not None:
            if not t.keeps:
                t.keeps = [0] * len(rec.status)
            for i, (status, reason) in enumerate(zip(rec.status, rec.solve_reason)):
                t.keeps[i] += status == KEPT
                if reason:
                    t.solve_reasons[reason] = t.solve_reasons.get(reason, 0) + 1
        if rec.note:
            t.notes.append(rec.note if rec.note.startswith("k=") else f"k={rec.k}: {rec.note}")
        self.last = rec
        return data

    def _write(self, data: bytes) -> None:
        """Write one whole row, or none of it (OSError, the file cut back to its last row)."""
        file, path = self._file, self.path
        assert file is not None and path is not None  # rows are written only with a rows file
        view = memoryview(data)
        try:
            while view:
                written = file.write(view)
                view = view[written:]
        except OSError:
            try:
                os.truncate(path, self._end)
                file.seek(self._end)
            except OSError:
                pass
            raise
        self._end += len(data)

    def close(self) -> None:
        if self._file is not None and not self._file.closed:
            self._file.close()

    # ------------------------------------------------------------------ reading
    def _matrix(self) -> np.ndarray:
        """All rows, shape (K, width): a read-only memory map of the file, or the rows in memory."""
        K = self.tally.steps
        if self._file is None or self.path is None:  # the rows file and its path go together
            return np.vstack(self._rows) if self._rows else np.zeros((0, self.width))
        if K == 0 or self.width == 0:
            return np.zeros((0, self.width))
        return np.memmap(self.path, dtype=np.float64, mode="r", shape=(K, self.width))

    def arrays(self) -> dict[str, np.ndarray]:
        """The arrays of ``trajectory.npz`` (see :func:`dmpc.records.run_folder.trajectory_arrays`).

        Plus ``fallback_code`` (K, M): the index in ``tally.reasons`` of each agent's fallback reason.
        With estimation also ``output_sizes`` (M,), the p_i that split ``y`` by subsystem, and
        ``disturbance_sizes`` (M,) when they were given. Large arrays are views of the memory map;
        read them a block of rows at a time.
        """
        system, M = self.system, self.system.M
        if self.tally.steps == 0:
            empty = np.zeros((0, M))
            return {"x": system.x0[None, :], "u": np.zeros((0, system.m)), "alpha": np.zeros((1, system.n)),
                    "beta": np.zeros(1), "J": np.zeros(0), "S": np.array([system.spread(system.x0)]),
                    "J_agents": empty, "solve_time": empty, "qp_iterations": empty.astype(int),
                    "fallback": empty.astype(bool), "latency": empty, "rounds": np.zeros(0, int),
                    "step_time": np.zeros(0), "max_change": np.zeros(0), "fallback_code": empty.astype(int)}
        rows = self._matrix()
        K = rows.shape[0]
        last, layout = self.last, self.layout
        assert last is not None and layout is not None  # both set by the first add()
        final = {"x": last.x_next, "alpha": last.alpha_next, "beta": last.beta_next,
                 "S": system.spread(last.x_next), "r": last.r_next}
        out = {}
        for key, col in layout.items():
            block = rows[:, col.start:col.start + col.size].reshape((K,) + col.shape)
            if key in FINAL:
                block = np.concatenate([block, np.asarray(final[key], float).reshape((1,) + col.shape)])
            if key in _INT or key == "fallback_code":
                block = block.astype(int)
            elif key in _BOOL:
                block = block.astype(bool)
            out[key] = block
        if "y" in out:
            out["output_sizes"] = np.array([s.p for s in system.subsystems], dtype=int)
            if self.disturbance_sizes is not None:
                out["disturbance_sizes"] = np.array(self.disturbance_sizes, dtype=int)
        return out


def write_npz(path: Path, arrays: dict[str, np.ndarray],
              transform: Callable[[str, np.ndarray], np.ndarray] | None = None) -> None:
    """``np.savez`` of ``arrays`` to ``path`` that copies each array a block of rows at a time (memory
    maps stay unread); ``transform(key, block)``, if given, gives what is written of each block of
    rows of the array ``key`` (the same shape and type, e.g. moved to the plant's units)."""
    tmp = path.with_suffix(path.suffix + ".tmp")
    with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
        for key, value in arrays.items():
            arr = value if isinstance(value, np.ndarray) else np.asarray(value)
            with zf.open(f"{key}.npy", "w", force_zip64=True) as fh:
                np.lib.format.write_array_header_2_0(fh, {"descr": np.lib.format.dtype_to_descr(arr.dtype),
                                                          "fortran_order": False, "shape": arr.shape})
                blocks = [arr] if arr.ndim == 0 or arr.shape[0] <= BLOCK_ROWS else \
                    (arr[start:start + BLOCK_ROWS] for start in range(0, arr.shape[0], BLOCK_ROWS))
                for block in blocks:
                    if transform is not None:
                        block = transform(key, block)
                    fh.write(np.ascontiguousarray(block).astype(arr.dtype, copy=False).tobytes())
    tmp.replace(path)
