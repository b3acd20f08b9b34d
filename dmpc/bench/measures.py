"""Benchmarks of this machine: QP, multi-process steps, memory, design, and baselines.

Everything ``dmpc bench`` measures, as functions returning plain dicts. The multi-process
figures come from real ``dmpc run`` processes; the in-process and centralised figures from
closed loops of the same scenario, so the closed-loop costs can be compared side by side.
"""
from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path
from unittest.mock import patch

import numpy as np

from dmpc.agents.local_qp import LocalQP
from dmpc.bench.common import chain_overrides, closed_loop, prepare_chain, sample_memory
from dmpc.bench.floor import FloorSpec, measure
from dmpc.bus import keys
from dmpc.bus.codec import encode
from dmpc.bus.messages import PlanMessage, Release
from dmpc.core.central_qp import CentralQP
from dmpc.offline.gains import lmi_gains
from dmpc.offline.horizon import StartCheck
from dmpc.offline.terminal_set import LOCAL_ABOVE, maximal_admissible_set
from dmpc.records.files import SUMMARY, TRAJECTORY
from dmpc.records.run_folder import stage_cost
from dmpc.runtime import inprocess
from dmpc.runtime.inprocess import simulate
from dmpc.runtime.launcher import default_topology
from dmpc.scenario import alpha0_vector, build_system, load_scenario
from dmpc.setup import protocol_options
from dmpc.setup.start import MethodStart


# ---------------------------------------------------------------------------- local QP
def qp_solve_times(horizon: int, repeat: int, root: Path = Path(".")) -> dict:
    """Replay the QPs one agent of the paper's example solves in a closed loop (30 steps) at horizon
    ``horizon``, each ``repeat`` times; ``root`` is the folder of ``scenarios/``."""
    prepared = prepare_chain(4, 30, horizon, root)
    agent = 1
    calls: list[tuple] = []
    original = LocalQP.solve

    def recording(self, x, c, centre, size):
        if getattr(self, "_bench_record", False):
            calls.append((x.copy(), c.copy(), centre.copy(), size))
        return original(self, x, c, centre, size)

    build = inprocess.build_run

    def marking(*args, **kwargs):
        run = build(*args, **kwargs)
        run.agents[agent].controller.qp._bench_record = True
        return run

    with patch.object(LocalQP, "solve", recording), patch.object(inprocess, "build_run", marking):
        simulate(prepared, lambda record: None)
    sub = prepared.system.subsystems[agent]
    qp = LocalQP(sub, prepared.design.gains.P[agent], horizon, prepared.design.tightening[agent])
    times = []
    for _ in range(repeat):
        for x, c, centre, size in calls:
            t0 = time.perf_counter()
            qp.solve(x, c, centre, size)
            times.append(time.perf_counter() - t0)
    t = np.array(times) * 1e6
    return {"N": horizon, "solves": int(t.size), "us_p50": float(np.median(t)), "us_p99": float(np.percentile(t, 99))}


# ---------------------------------------------------------------------------- multi-process
def run_multiprocess(M: int, steps: int, workdir: Path, root: Path = Path("."), timeout: float = 900) -> dict:
    """``dmpc run`` of the chain of M agents (:func:`~dmpc.bench.common.chain_overrides`) for ``steps``
    steps in lockstep, its run folder in ``workdir``, stopped after ``timeout`` seconds; ``root`` is the folder
    of ``scenarios/``.
    Step time, the bus's share, memory per process, and ``startup_s`` (the processes started to the
    first release, from the run's summary)."""
    path, overrides = chain_overrides(M, steps)
    out = workdir / f"run-M{M}"
    cmd = [sys.executable, "-m", "dmpc.cli", "run", path, "--out", str(out), "--quiet", "--startup-timeout", "600"]
    cmd += [arg for k, v in overrides.items() for arg in ("--set", f"{k}={v}")]
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, cwd=root, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    peak: dict[str, tuple[float, float]] = {}
    try:
        while proc.poll() is None:
            if time.monotonic() - t0 > timeout:
                proc.send_signal(2)
                proc.wait(30)
                return {"M": M, "completed": False, "topology": default_topology(M),
                        "reason": f"timeout after {timeout:.0f} s"}
            time.sleep(0.5)
            sample_memory(out, peak)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    wall = time.monotonic() - t0
    if proc.returncode != 0:
        stderr = proc.stderr.read() if proc.stderr is not None else b""
        return {"M": M, "completed": False, "topology": default_topology(M),
                "reason": stderr.decode(errors="replace")[-600:]}
    data = np.load(out / TRAJECTORY)
    step = data["step_time"][1:] * 1e3
    slowest = np.nanmax(data["solve_time"][1:], axis=1) * 1e3
    agents = [v for k, v in peak.items() if keys.subsystem_of(k, keys.AGENT_PREFIX) is not None]
    summary = json.loads((out / SUMMARY).read_text())
    return {
        "M": M, "completed": True, "topology": default_topology(M), "steps": int(data["step_time"].size), "wall_s": wall,
        "step_ms_p50": float(np.median(step)), "step_ms_p99": float(np.percentile(step, 99)),
        "step0_ms": float(data["step_time"][0] * 1e3), "bus_ms_p50": float(np.median(step - slowest)),
        "bus_share_p50": float(np.median((step - slowest) / step)),
        "rss_mb_per_agent": max(a[0] for a in agents) if agents else None,
        "pss_mb_per_agent": max(a[1] for a in agents) if agents else None,
        "rss_mb_plant": peak.get(keys.PLANT_ROLE, (None, None))[0],
        "rss_mb_total": sum(v[0] for v in peak.values()), "pss_mb_total": sum(v[1] for v in peak.values()),
        "closed_loop_cost": summary["closed_loop_cost"], "feasible": summary["feasible"],
        "startup_s": summary.get("startup_s"),
    }


def floor_spec(M: int, steps: int, compute_us: float, root: Path = Path(".")):
    """The bare lockstep loop (:mod:`dmpc.bench.floor`) that mirrors a run of M agents: the same
    processes, topology and neighbours, payloads of the run's release and plan sizes, and
    ``compute_us`` of CPU per agent and step, for ``steps`` steps; ``root`` is the folder of
    ``scenarios/``."""
    prepared = prepare_chain(M, steps, root=root)
    system, N = prepared.system, prepared.design.horizon
    run = f"{prepared.name}-0123abcd"  # the launcher's run ids have this length
    release = Release(run=run, k=steps, round=0, x=np.ones(system.n), centres=np.ones(system.n),
                      sizes=np.ones(system.M), assumed=np.full((system.M, 2), steps, dtype=np.int64))
    plan_bytes = max(len(encode(PlanMessage(run=run, k=steps, round=0, sender=sub.name, status="solved",
                                            z=np.ones((N + 1, sub.n)), v=np.ones((N, sub.m)), cost=1.0,
                                            solve_time=1e-4, qp_iterations=25, sent_at=1.0)))
                     for sub in system.subsystems)
    neighbours = [[j for j in system.neighbours[i] if j != i] for i in range(system.M)]
    return FloorSpec(M=M, steps=steps, neighbours=neighbours, release_bytes=len(encode(release)),
                     plan_bytes=plan_bytes, compute_us=compute_us, topology=default_topology(M))


def run_floor(M: int, steps: int, compute_us: float, root: Path = Path("."), timeout: float = 900) -> dict:
    """The floor of a run of M agents over ``steps`` steps with ``compute_us`` of CPU per agent and step:
    :func:`floor_spec` measured by :func:`dmpc.bench.floor.measure` (stopped after ``timeout``
    seconds); ``root`` is the folder of ``scenarios/``."""
    return measure(floor_spec(M, steps, compute_us, root), timeout)


def run_against_floor(M: int, steps: int, compute_us: float, workdir: Path, root: Path = Path("."),
                      timeout: float = 900, sets: int = 1) -> dict:
    """:func:`run_multiprocess` with the floor measured just before it, and the ratios of the two: M
    agents, ``steps`` steps, ``compute_us`` of CPU per agent and step for the floor, run folders in
    ``workdir``, ``root`` the folder of ``scenarios/``, each run stopped after ``timeout`` seconds.

    ``sets`` > 1 alternates floor and run that many times (this machine's speed moves from one
    minute to the next: a ratio of one pair can be off by half). The step figures and the floor's
    are then the medians over the sets, and the ratios the medians of each set's ratio; the other
    figures (memory, cost, wall time) are the first set's run.

    Adds ``floor`` (the floor's figures), ``over_floor_p50``, ``over_floor_p99`` (step median and p99
    over the floor's) and ``sets`` (each set's floor and run step median and p99, in ms).
    """
    pairs = []
    result: dict = {}
    for n in range(sets):
        floor = run_floor(M, steps, compute_us, root, timeout)
        (workdir / f"set-{n}").mkdir(parents=True, exist_ok=True)
        run = run_multiprocess(M, steps, workdir / f"set-{n}", root, timeout)
        if n == 0:
            result = dict(run, floor=floor)
        if not (run.get("completed") and floor.get("completed")):
            if n == 0:
                return result
            continue
        pairs.append({"floor_ms_p50": floor["step_ms_p50"], "floor_ms_p99": floor["step_ms_p99"],
                      "step_ms_p50": run["step_ms_p50"], "step_ms_p99": run["step_ms_p99"]})
    if not pairs:
        return result
    result["sets"] = pairs
    median = {key: float(np.median([p[key] for p in pairs])) for key in pairs[0]}
    result["step_ms_p50"], result["step_ms_p99"] = median["step_ms_p50"], median["step_ms_p99"]
    result["floor"] = dict(result["floor"], step_ms_p50=median["floor_ms_p50"], step_ms_p99=median["floor_ms_p99"])
    result["over_floor_p50"] = float(np.median([p["step_ms_p50"] / p["floor_ms_p50"] for p in pairs]))
    result["over_floor_p99"] = float(np.median([p["step_ms_p99"] / p["floor_ms_p99"] for p in pairs]))
    return result


# ---------------------------------------------------------------------------- in process / centralised


def run_inprocess(M: int, steps: int, root: Path = Path(".")) -> dict:
    """The chain of M agents (``root`` is the folder of ``scenarios/``) run for ``steps`` steps in this process
    on the in-memory
    bus: step time median and p99 (ms) and the closed-loop cost."""
    prepared = prepare_chain(M, steps, root=root)
    records, stamps = [], []

    def on_step(record):
        records.append(record)
        stamps.append(time.perf_counter())

    t0 = time.perf_counter()
    simulate(prepared, on_step)
    t = np.diff([t0] + stamps)[1:] * 1e3
    cost = sum(stage_cost(prepared.system, r.x, r.u) for r in records)
    return {"M": M, "step_ms_p50": float(np.median(t)), "step_ms_p99": float(np.percentile(t, 99)),
            "closed_loop_cost": cost}


def run_central_osqp(M: int, steps: int, root: Path = Path(".")) -> dict:
    """The centralised MPC of the chain of M subsystems (``root`` is the folder of ``scenarios/``) for ``steps``
    steps: one
    OSQP problem set up once and re-solved each step (:class:`~dmpc.core.central_qp.CentralQP`)."""
    prepared = prepare_chain(M, steps, root=root)
    qp = CentralQP(prepared.system, prepared.design.gains.P_global(), prepared.design.horizon, "omega",
                   prepared.design.terminal.omega)

    def step(x):
        sol = qp.solve(x)
        return sol.v[0] if sol.status.feasible else np.zeros(prepared.system.m)

    return {"M": M, **closed_loop(step, prepared.system, steps)}


def run_central_cvxpy(M: int, steps: int, root: Path = Path(".")) -> dict:
    """The centralised MPC of the chain of M subsystems (``root`` is the folder of ``scenarios/``) for ``steps``
    steps, as
    commonly written by hand: a cvxpy problem re-solved each step."""
    import cvxpy as cp

    prepared = prepare_chain(M, steps, root=root)
    s, N = prepared.system, prepared.design.horizon
    P = prepared.design.gains.P_global()
    omega = prepared.design.terminal.omega
    x0 = cp.Parameter(s.n)
    z = cp.Variable((N + 1, s.n))
    v = cp.Variable((N, s.m))
    ubar = np.concatenate([sub.input_set.upper for sub in s.subsystems])
    cons = [z[0] == x0, omega @ z[N] <= 1, cp.abs(v) <= np.tile(ubar, (N, 1))]
    cons += [z[t + 1] == s.A @ z[t] + s.B @ v[t] for t in range(N)]
    obj = sum(cp.quad_form(z[t], s.Q) + cp.quad_form(v[t], s.R) for t in range(N)) + cp.quad_form(z[N], P)
    problem = cp.Problem(cp.Minimize(obj), cons)

    def step(x):
        x0.value = x
        problem.solve()
        return v.value[0] if v.value is not None else np.zeros(s.m)

    result = closed_loop(step, s, steps)
    return {"M": M, "solver": problem.solver_stats.solver_name if problem.solver_stats else "?", **result}


# ---------------------------------------------------------------------------- design
def design_scaling(M: int, root: Path = Path("."), compare: bool = False) -> dict:
    """The offline design of the chain of M subsystems (LMI gains, horizon 10; ``root`` is the folder
    of ``scenarios/``), timed part by part.

    ``lmi_s``: the gains (LMI (11) and their verification); ``terminal_set_s``: X^f;
    ``start_check_s``: the start's feasibility LP at the given horizon; ``design_s``: all of
    :func:`dmpc.setup.design_for`, sigma0 and beta0 included. With ``compare``, X^f is also
    computed with one LP over the whole set per test (``terminal_set_plain_s``) and compared with
    the set from LPs on each row's neighbourhood (``same_omega``: the same rows to 1e-12;
    ``same_sigma0``: sigma(alpha0) equal to 1e-12).
    """
    path, overrides = chain_overrides(M, 1)
    overrides["design.gains"] = "lmi"
    scenario = load_scenario(root / path, overrides)
    system = build_system(scenario)
    t0 = time.perf_counter()
    gains = lmi_gains(system)
    t1 = time.perf_counter()
    terminal = maximal_admissible_set(system, gains.K)
    t2 = time.perf_counter()
    alpha0 = alpha0_vector(scenario, system)
    sigma0 = terminal.sigma(alpha0)
    beta0 = scenario.terminal.beta0 if scenario.terminal.beta0 != "auto" else 0.9 * sigma0
    start = MethodStart(system, scenario.options.method, scenario.options.coupling, protocol_options(scenario))
    check = StartCheck(system, gains, terminal, alpha0=alpha0, beta0=beta0, tube=scenario.options.tube, start=start)
    design = check.checked(int(scenario.horizon))
    t3 = time.perf_counter()
    result = {"M": M, "lmi_s": t1 - t0, "terminal_set_s": t2 - t1, "start_check_s": t3 - t2, "design_s": t3 - t0,
              "omega_rows": terminal.rows, "t_star": terminal.t_star, "sigma0": sigma0,
              "start_feasible": bool((design.start or {}).get("centrally_feasible"))}
    if compare:
        t4 = time.perf_counter()
        plain = maximal_admissible_set(system, gains.K, local=False)
        result["terminal_set_plain_s"] = time.perf_counter() - t4
        local = terminal if system.n > LOCAL_ABOVE else maximal_admissible_set(system, gains.K, local=True)
        result["same_omega"] = bool(plain.omega.shape == local.omega.shape
                                    and np.abs(plain.omega - local.omega).max() <= 1e-12)
        result["same_sigma0"] = bool(abs(plain.sigma(alpha0) - local.sigma(alpha0)) <= 1e-12)
    return result


