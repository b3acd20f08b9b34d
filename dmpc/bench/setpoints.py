"""What a setpoint costs: a new target and its terminal set, the reference governor's step, and the
step time of a run around a target (the chain of M copies of the paper's subsystem).

A new request costs one steady-state QP (Clarabel) the first time it is seen; its terminal set
is the design's X^f scaled by lambda, so it costs a gauge (lambda) and one sigma, no LP. The
governor costs up to 40 bisections of two slacks. In a run, the target of step k + 1 is decided
at the end of step k, with the QP computed before: a scenario's schedule before step 0, a request
sent while the run goes on beside the run (benchmarks/live_setpoints.py), so that step pays only
for the governor.
"""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np

from dmpc.bench.common import prepare_chain
from dmpc.runtime.inprocess import simulate
from dmpc.tracking.schedule import SetpointEntry
from dmpc.tracking.targets import Request
from dmpc.tracking.tracker import Tracker

REQUESTS = (1.0, -0.5, 2.0, -1.5, 0.75)
"""Values asked of x_{1,1}, each a new request (a new target)."""


def _timed(call, repeat: int = 1) -> tuple[float, Any]:
    """Best wall time of ``call()`` in ms over ``repeat`` calls, and its last result."""
    best, out = np.inf, None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = call()
        best = min(best, time.perf_counter() - t0)
    return float(best * 1e3), out


def target_costs(M: int, root: Path = Path(".")) -> dict:
    """On the chain of M subsystems (``root``: the folder of ``scenarios/``), milliseconds for a new
    target (median over REQUESTS), its terminal set (lambda and sigma at its centre), and a governor
    step that bisects (a jump from the origin with settled plans)."""
    prepared = prepare_chain(M, 1, root=root)
    system, design = prepared.system, prepared.design
    K = design.gains.K_global()
    tracker = Tracker(system, design.terminal, system.A + system.B @ K, K)
    space = tracker.space
    first_ms, _ = _timed(lambda: space.target(_request(system, 0.1)))  # builds the QP's matrices
    times, targets = [], []
    for value in REQUESTS:
        ms, target = _timed(lambda value=value: space.target(_request(system, value)))
        times.append(ms)
        targets.append(target)
    far = space.target(_request(system, 20.0))
    terminal_ms, _ = _timed(lambda: design.terminal.sigma(np.zeros(system.n), space.scale(far.x, far.u)), repeat=5)
    origin = tracker.applied
    governor_ms, step = _timed(lambda: tracker.governor.step(origin.x.copy(), origin, far), repeat=3)
    return {"M": M, "n": system.n, "omega_rows": design.terminal.rows, "first_target_ms": first_ms,
            "target_ms": float(np.median(times)), "terminal_set_ms": terminal_ms, "governor_ms": governor_ms,
            "governor_theta": float(step.theta)}


def _request(system, value: float) -> Request:
    x = np.full(system.n, np.nan)
    x[0] = value
    return Request(x, np.full(system.m, np.nan))


def step_costs(M: int, steps: int = 40, change: int = 20, root: Path = Path(".")) -> dict:
    """In-process step times (ms) of the chain of M (``root``: the folder of ``scenarios/``) for
    ``steps`` steps, without setpoints and with x_{1,1} = 1 from step
    ``change``: the median step, the step that decides the new target (change - 1), and the median
    of the steps after it (around the target)."""
    prepared = prepare_chain(M, steps, root=root)
    entry = SetpointEntry(change, 0, np.array([1.0, np.nan]), np.array([np.nan]))
    plain = _step_times(prepared)
    tracked = _step_times(dataclasses.replace(prepared, setpoints=(entry,)))
    return {"M": M, "plain_ms_p50": float(np.median(plain[1:])), "tracked_ms_p50": float(np.median(tracked[1:change - 1])),
            "change_step_ms": float(tracked[change - 1]), "around_target_ms_p50": float(np.median(tracked[change:]))}


def _step_times(prepared) -> np.ndarray:
    stamps: list[float] = []
    t0 = time.perf_counter()
    simulate(prepared, lambda record: stamps.append(time.perf_counter()))
    return np.diff([t0] + stamps) * 1e3
