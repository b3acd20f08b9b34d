"""Core benchmarks: local QP solve time and offline design time for the paper's example.

    python benchmarks/bench_core.py [--repeat 20] [--json]

The QP is timed on the sequence of problems one agent really solves in a closed-loop run
(the k = 0 Jacobi rounds and the 30 steps), replayed ``--repeat`` times on one warm-started
solver, so warm starting is exercised as in a run. The time includes the vector updates.
"""
from __future__ import annotations

import argparse
import json
import platform
import time

import numpy as np
import psutil

from dmpc.console import silence_c_stdout


def machine() -> str:
    return (f"{platform.machine()}, {psutil.cpu_count(logical=True)} cores, "
            f"{psutil.virtual_memory().total / 2**30:.0f} GiB, Python {platform.python_version()}")


def record_qp_inputs(prepared, agent: int) -> list[tuple]:
    """The (x, c, alpha, beta) of every QP agent ``agent`` solves in a closed-loop run."""
    from dmpc.agents.local_qp import LocalQP
    from dmpc.runtime.inprocess import simulate

    calls = []
    original = LocalQP.solve

    def recording(self, x, c, alpha, beta):
        if self is recording.target:
            calls.append((x.copy(), c.copy(), alpha.copy(), beta))
        return original(self, x, c, alpha, beta)

    recording.target = None
    LocalQP.solve = recording
    try:
        from dmpc.runtime import inprocess

        run_holder = {}
        original_build = inprocess.build_run

        def build_and_mark(*args, **kwargs):
            run = original_build(*args, **kwargs)
            recording.target = run.agents[agent].controller.qp
            run_holder["run"] = run
            return run

        inprocess.build_run = build_and_mark
        try:
            simulate(prepared, lambda record: None)
        finally:
            inprocess.build_run = original_build
    finally:
        LocalQP.solve = original
    return calls


def bench_qp(prepared, agent: int, repeat: int) -> dict:
    from dmpc.agents.local_qp import LocalQP

    calls = record_qp_inputs(prepared, agent)
    sub = prepared.system.subsystems[agent]
    qp = LocalQP(sub, prepared.design.gains.P[agent], prepared.design.horizon, prepared.design.tightening[agent])
    times = []
    for _ in range(repeat):
        for x, c, alpha, beta in calls:
            t0 = time.perf_counter()
            qp.solve(x, c, alpha, beta)
            times.append(time.perf_counter() - t0)
    t = np.array(times) * 1e6
    return {"qp_solves": int(t.size), "qp_solve_us_p50": float(np.median(t)), "qp_solve_us_p99": float(np.percentile(t, 99))}


def bench_design(path: str, repeat: int = 3) -> dict:
    from dmpc.design import design_system
    from dmpc.scenario import alpha0_vector, build_system, load_scenario

    scn = load_scenario(path)
    system = build_system(scn)
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        design_system(system, gains="lmi", horizon=scn.horizon, alpha0=alpha0_vector(scn, system),
                      beta0=scn.terminal.beta0)
        times.append(time.perf_counter() - t0)
    return {"design_lmi_s_median": float(np.median(times)), "design_lmi_s_first": float(times[0])}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=20)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    silence_c_stdout()
    from dmpc.runtime.setup import prepare
    from dmpc.scenario import load_scenario

    prepared = prepare(load_scenario("scenarios/paper.yaml"))
    result = {"machine": machine()}
    result.update(bench_qp(prepared, agent=1, repeat=args.repeat))
    result.update(bench_design("scenarios/paper-lmi.yaml"))
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        for key, value in result.items():
            print(f"{key:24s} {value:.4g}" if isinstance(value, float) else f"{key:24s} {value}")


if __name__ == "__main__":
    main()
