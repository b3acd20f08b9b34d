"""What the benchmarks share: the machine they ran on, its speed figure, the scenarios they time
(the paper's example at M = 4, the chain family above), and their closed-loop and memory samplers."""
from __future__ import annotations

import json
import platform
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import psutil

from dmpc.records.files import PROCESSES, STEP_LOG
from dmpc.records.run_folder import stage_cost
from dmpc.scenario import load_scenario
from dmpc.setup import prepare


def machine() -> dict:
    return {"machine": platform.machine(), "cores": psutil.cpu_count(logical=True),
            "memory_gib": round(psutil.virtual_memory().total / 2**30, 1), "python": platform.python_version(),
            "calibration_ms": calibration_ms(), "load_average": load_average()}


def load_average() -> float:
    """The machine's load average over the last minute (processes running or waiting for a core)."""
    return float(psutil.getloadavg()[0])


def calibration_ms(repeat: int = 7) -> float:
    """Best of ``repeat`` times of a fixed single-threaded Python workload (10^6 additions), in ms.

    Shared or throttled virtual machines run at different speeds from one hour to the next;
    figures measured at different times compare only alongside this one.
    """
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        total = 0
        for i in range(1_000_000):
            total += i
        best = min(best, time.perf_counter() - t0)
    return float(best * 1e3)


def chain_overrides(M: int, steps: int, horizon: int | None = None) -> tuple[str, dict]:
    """The scenario file and overrides of the chain of M subsystems for ``steps`` steps (and ``horizon``,
    None: the scenario's): the paper's example for M = 4, the chain family otherwise."""
    overrides: dict = {"steps": steps}
    if horizon is not None:
        overrides["horizon"] = horizon
    if M == 4:
        return "scenarios/paper.yaml", overrides
    overrides["family.M"] = M
    return "scenarios/chain.yaml", overrides


def prepare_chain(M: int, steps: int, horizon: int | None = None, root: Path = Path(".")):
    """The prepared run of :func:`chain_overrides` (M, ``steps``, ``horizon``); ``root`` is the folder of
    ``scenarios/``."""
    path, overrides = chain_overrides(M, steps, horizon)
    return prepare(load_scenario(root / path, overrides))


def sample_memory(out: Path, peak: dict) -> None:
    """Raise each process's entry of ``peak`` (role -> (RSS, PSS) in MB) to its memory now, for the
    processes of the run folder ``out`` (none before its first step)."""
    try:
        pids = json.loads((out / PROCESSES).read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return
    if not (out / STEP_LOG).exists():
        return  # still starting: sample the steady state only
    for role, pid in pids.items():
        try:
            full = psutil.Process(pid).memory_full_info()
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
        rss, pss = full.rss / 2**20, getattr(full, "pss", full.rss) / 2**20
        old = peak.get(role, (0.0, 0.0))
        peak[role] = (max(old[0], rss), max(old[1], pss))


def closed_loop(step: Callable[[np.ndarray], np.ndarray], system, steps: int) -> dict:
    """Run ``step`` (x -> u) in closed loop on the model of ``system`` for ``steps`` steps from x(0):
    step time median and p99 (ms, step 0 left out), the closed-loop cost and ``final_state_norm_inf``."""
    x = system.x0.copy()
    cost, times = 0.0, []
    for _ in range(steps):
        t0 = time.perf_counter()
        u = step(x)
        times.append(time.perf_counter() - t0)
        cost += stage_cost(system, x, u)
        x = system.A @ x + system.B @ u
    t = np.array(times[1:]) * 1e3
    return {"step_ms_p50": float(np.median(t)), "step_ms_p99": float(np.percentile(t, 99)), "closed_loop_cost": cost,
            "final_state_norm_inf": float(np.max(np.abs(x)))}


def workdir() -> tempfile.TemporaryDirectory:
    return tempfile.TemporaryDirectory(prefix="dmpc-bench-")


def cell(value, spec: str = ".3g") -> str:
    """A table cell of ``value``: "-" for None, a float in format ``spec``, anything else as text."""
    if value is None:
        return "-"
    if isinstance(value, float):
        return format(value, spec)
    return str(value)
