"""The scale table: the chain of M subsystems designed, run with agents hosted many to a process,
and compared with the centralised OSQP loop on the same system (``benchmarks/scale_table.py``).

One row per M: the design is made once and timed (the same ``prepare`` as ``dmpc run``), the run
is :func:`dmpc.runtime.launcher.launch` on that design (what ``dmpc run --agents-per-process K``
does after designing), and the centralised loop uses the same design's system, P and Omega.
"""
from __future__ import annotations

import json
import secrets
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from dmpc.bench.common import calibration_ms, closed_loop, prepare_chain, sample_memory
from dmpc.core.central_qp import CentralQP
from dmpc.records.files import SUMMARY, TRAJECTORY
from dmpc.runtime.hosting import group_agents
from dmpc.runtime.launcher import LaunchResult, default_topology, launch

SAMPLE_PER_PROCESS = 0.05
"""Seconds between memory samples per process of the run, at least 0.25 s: reading a process's
memory map costs CPU that the run needs."""


def launch_sampled(prepared, out: Path, run_id: str, per_process: int,
                   startup_timeout: float) -> tuple[LaunchResult, dict[str, tuple[float, float]], int]:
    """``launch`` ``prepared`` as processes of ``per_process`` agents (``dmpc run --agents-per-process``)
    into the run folder ``out`` as run ``run_id``, each process waiting at most ``startup_timeout``
    seconds to start, while the processes' memory is sampled.

    Returns
    -------
    (result, peak, processes)
        ``launch``'s result, the peak (RSS, PSS) in MB per role (:func:`~dmpc.bench.common.sample_memory`)
        and the number of agent processes.
    """
    hosts = group_agents(prepared.names, per_process)
    peak: dict[str, tuple[float, float]] = {}
    done = threading.Event()

    def sample() -> None:
        while not done.wait(max(0.25, SAMPLE_PER_PROCESS * (len(hosts) + 1))):
            sample_memory(out, peak)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    try:
        result = launch(prepared, out, run_id, startup_timeout=startup_timeout, show_progress=False,
                        topology=default_topology(len(hosts)), agents_per_process=per_process)
    finally:
        done.set()
        sampler.join()
    return result, peak, len(hosts)


def scale_row(M: int, per_process: int, steps: int, workdir: Path, root: Path = Path("."), central: bool = True,
              startup_timeout: float = 600.0) -> dict:
    """Design, run and compare the chain of ``M`` subsystems with ``per_process`` agents per process,
    for ``steps`` steps, the run folder in ``workdir`` (``root``: the folder of ``scenarios/``), the
    processes waiting at most ``startup_timeout`` seconds to start.

    Returns
    -------
    dict
        ``M``, ``processes`` (agent processes), ``agents_per_process``, ``topology``, ``design_s``,
        ``startup_s`` (processes started to the first release), ``step_ms_p50`` and ``step_ms_p99``
        (steps 1..K-1: step 0 iterates Jacobi to convergence), ``step0_ms``, ``rss_mb_total`` (peak
        RSS of every process of the run, summed; shared pages count in each) and
        ``rss_mb_per_process`` (largest agent process), ``pss_mb_total`` (shared pages divided
        among their processes), ``wall_s`` (the launch to its end), ``closed_loop_cost`` and, with ``central``,
        ``central_cost``, ``central_solve_s_p50`` and ``cost_ratio`` (DMPC over centralised).
    """
    t0 = time.perf_counter()
    prepared = prepare_chain(M, steps, root=root)
    design_s = time.perf_counter() - t0
    hosts = group_agents(prepared.names, per_process)
    row: dict[str, Any] = {"M": M, "processes": len(hosts), "agents_per_process": max(len(h.agents) for h in hosts),
           "topology": default_topology(len(hosts)), "steps": steps, "design_s": design_s,
           "calibration_ms": calibration_ms(3)}
    out = Path(workdir) / f"scale-M{M}-K{per_process}"
    started = time.monotonic()
    result, peak, _ = launch_sampled(prepared, out, f"scale-{M}-{secrets.token_hex(4)}", per_process, startup_timeout)
    row["wall_s"] = time.monotonic() - started
    if result.code != 0 or not (out / TRAJECTORY).is_file():
        return {**row, "completed": False, "reason": result.message[-600:]}
    data = np.load(out / TRAJECTORY)
    summary = json.loads((out / SUMMARY).read_text())
    step = data["step_time"][1:] * 1e3
    agent_processes = [v[0] for role, v in peak.items() if role != "plant"]
    row.update({
        "completed": summary["steps"] == steps, "feasible": summary["feasible"], "fallbacks": summary["fallbacks"],
        "startup_s": summary.get("startup_s"), "step0_ms": float(data["step_time"][0] * 1e3),
        "step_ms_p50": float(np.median(step)), "step_ms_p99": float(np.percentile(step, 99)),
        "rss_mb_total": sum(v[0] for v in peak.values()), "pss_mb_total": sum(v[1] for v in peak.values()),
        "rss_mb_per_process": max(agent_processes) if agent_processes else None,
        "rss_mb_plant": peak.get("plant", (None, None))[0],
        "closed_loop_cost": summary["closed_loop_cost"],
    })
    if central:
        row.update(central_loop(prepared, steps))
        row["cost_ratio"] = row["closed_loop_cost"] / row["central_cost"]
    return row


def central_loop(prepared, steps: int) -> dict:
    """The centralised MPC (one OSQP problem over the whole system, X^f = {Omega x <= 1}) of the
    ``prepared`` run in closed loop for ``steps`` steps from x(0): its cost and its solve times."""
    t0 = time.perf_counter()
    qp = CentralQP(prepared.system, prepared.design.gains.P_global(), prepared.design.horizon, "omega",
                   prepared.design.terminal.omega)
    setup_s = time.perf_counter() - t0

    def step(x):
        sol = qp.solve(x)
        return sol.v[0] if sol.status.feasible else np.zeros(prepared.system.m)

    loop = closed_loop(step, prepared.system, steps)
    return {"central_cost": loop["closed_loop_cost"], "central_setup_s": setup_s,
            "central_solve_s_p50": loop["step_ms_p50"] / 1e3, "central_solve_s_p99": loop["step_ms_p99"] / 1e3}


HEADER = ["M", "processes", "agents / process", "topology", "design (s)", "start-up (s)", "step median (ms)",
          "step p99 (ms)", "RSS total (MB)", "RSS / agent process (MB)", "cost DMPC", "cost central OSQP",
          "cost ratio", "central solve median (s)"]


def markdown_row(r: dict) -> str:
    """One line of the scale table, of the :func:`scale_row` ``r``."""
    def f(key: str, digits: int = 1) -> str:
        value = r.get(key)
        return "-" if value is None else f"{value:.{digits}f}"

    if not r.get("completed"):
        why = (r.get("reason") or "?").strip().splitlines()[-1].strip()
        return f"| {r['M']} | {r['processes']} | {r['agents_per_process']} | {r['topology']} | {f('design_s')} | " \
               f"did not complete: {why} |"
    cells = [str(r["M"]), str(r["processes"]), str(r["agents_per_process"]), r["topology"], f("design_s"),
             f("startup_s"), f("step_ms_p50"), f("step_ms_p99"), f("rss_mb_total", 0), f("rss_mb_per_process", 0),
             f("closed_loop_cost"), f("central_cost"), f("cost_ratio", 4), f("central_solve_s_p50", 3)]
    return "| " + " | ".join(cells) + " |"
