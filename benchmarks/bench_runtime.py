"""Multi-process lockstep benchmark: step time, the bus's share of it, memory per process.

    python benchmarks/bench_runtime.py [--agents 4 16 32] [--steps 300] [--json]

For each M it runs ``dmpc run`` (the paper's example for M = 4, the chain family otherwise)
in lockstep for ``--steps`` steps and reads the run folder:
- step time: release of step k to its completion on the plant's clock (k = 0 excluded: it
  holds the Jacobi iterations to convergence, reported separately);
- bus share: step time minus the slowest agent's QP solve time in that step;
- resident memory (RSS and PSS) of every process, sampled while the run is going.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import psutil

ROOT = Path(__file__).resolve().parents[1]


def scenario_args(M: int) -> list[str]:
    if M == 4:
        return ["scenarios/paper.yaml"]
    return ["scenarios/chain.yaml", "--set", f"family.M={M}"]


def sample_memory(pids: dict[str, int]) -> dict[str, tuple[float, float]]:
    out = {}
    for role, pid in pids.items():
        try:
            proc = psutil.Process(pid)
            full = proc.memory_full_info()
            out[role] = (full.rss / 2**20, getattr(full, "pss", full.rss) / 2**20)
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            pass
    return out


def bench(M: int, steps: int, workdir: Path) -> dict:
    out = workdir / f"M{M}"
    cmd = [sys.executable, "-m", "dmpc.cli", "run", *scenario_args(M), "--out", str(out), "--steps", str(steps),
           "--quiet", "--startup-timeout", "300"]
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    peak: dict[str, tuple[float, float]] = {}
    while proc.poll() is None:
        time.sleep(0.25)
        pids_file = out / "processes.json"
        steps_file = out / "steps.jsonl"
        if pids_file.exists() and steps_file.exists() and steps_file.stat().st_size > 0:
            try:
                pids = json.loads(pids_file.read_text())
            except json.JSONDecodeError:
                continue
            for role, (rss, pss) in sample_memory(pids).items():
                old = peak.get(role, (0.0, 0.0))
                peak[role] = (max(old[0], rss), max(old[1], pss))
    wall = time.monotonic() - t0
    if proc.returncode != 0:
        return {"M": M, "completed": False, "error": proc.stderr.read().decode()[-2000:], "wall_s": wall}
    data = np.load(out / "trajectory.npz")
    step = data["step_time"][1:] * 1e3
    slowest = np.nanmax(data["solve_time"][1:], axis=1) * 1e3
    bus = step - slowest
    agents = [v for k, v in peak.items() if k.startswith("agent-")]
    return {
        "M": M, "completed": True, "steps": int(data["step_time"].size), "wall_s": wall,
        "step_ms_p50": float(np.median(step)), "step_ms_p99": float(np.percentile(step, 99)),
        "step_ms_max": float(step.max()), "step0_ms": float(data["step_time"][0] * 1e3),
        "rounds_k0": int(data["rounds"][0]),
        "slowest_solve_ms_p50": float(np.median(slowest)),
        "bus_ms_p50": float(np.median(bus)), "bus_share_p50": float(np.median(bus / step)),
        "rss_mb_per_agent_max": max(a[0] for a in agents) if agents else None,
        "pss_mb_per_agent_max": max(a[1] for a in agents) if agents else None,
        "rss_mb_plant": peak.get("plant", (None, None))[0],
        "rss_mb_total": sum(v[0] for v in peak.values()), "pss_mb_total": sum(v[1] for v in peak.values()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, nargs="+", default=[4, 16, 32])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for M in args.agents:
            res = bench(M, args.steps, Path(tmp))
            results.append(res)
            if not args.json:
                print(json.dumps(res), flush=True)
    if args.json:
        print(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
